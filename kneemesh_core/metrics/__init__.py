"""Measures on finished knees: agreement of two label maps (``labels``: one grid rule, Dice), between two
results of one knee (``compare``: surface deviation, contact curves) and the overlap of meshes that should
only touch (``overlap``)."""
