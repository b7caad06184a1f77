"""Finite element decks of the knee, and the CalculiX run that proves them.

- :mod:`.model` - the knee model in the deck's frame: nodes, rigid bodies, cartilage hexahedra,
  articular and bone-side surfaces, ligament springs (Blankevoort), the contact law, loads;
- :mod:`.deck` - the shared include (``knee_model.inp``, both dialects) and the two thin
  wrappers: ``knee_abaqus.inp`` (Abaqus/Explicit) and ``knee_ccx.inp`` (CalculiX, static);
- :mod:`.simulate` - runs ccx under a time limit and refuses a log in which ccx skipped
  part of the deck;
- :mod:`.results` - the .dat tables to ``results.json`` and ``contact.png``.

Hand-written on purpose: no Python library writes Abaqus/CalculiX decks with surfaces,
springs, rigid bodies and contact (meshio drops surfaces and renumbers; see
``../shared/docs/fe-calculix-reference.md``).
"""
