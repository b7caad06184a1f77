"""The ``kneemesh`` application: the command line over :mod:`kneemesh_core`."""
