"""Measures on finished knees: agreement between two results of one knee (``compare``) and the
overlap of meshes that should only touch (``overlap``)."""
