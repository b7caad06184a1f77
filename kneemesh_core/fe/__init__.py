"""Finite element decks of the knee, and the CalculiX run that proves them.

- :mod:`.physics` - materials, the ligament law, loads, restraints, boundary conditions and the
  limits a run is judged by: one home, read by the model, both dialects and the results;
- :mod:`.model` - the knee model in the deck's frame, from the knee's meshes and anatomy: nodes,
  rigid bodies, cartilage (a rigid cartilage as its :mod:`.contact_skin`, a deformable one as its
  hexahedra), articular surfaces, ligament springs, contact pairs, seating; with its surrogates
  :mod:`.menisci` and :mod:`.prefemoral`;
- :mod:`.deck` - the shared include (``knee_model.inp``) and ``model.json``, over the two thin
  dialects :mod:`.calculix` (``knee_ccx.inp``, static) and :mod:`.abaqus` (``knee_abaqus.inp``,
  explicit), which write their keyword lines with :mod:`.inp`;
- :mod:`.simulate` - runs ccx under a time limit and refuses a log in which ccx skipped part of the deck;
- :mod:`.results` - the .dat tables to ``results.json`` and ``contact.png``, with the contact
  pressure maps of :mod:`.pressure_map`;
- :mod:`.run` - ties them to a job folder: the decks, a run, the report's entry.

Hand-written on purpose: no Python library writes Abaqus/CalculiX decks with surfaces, springs,
rigid bodies and contact (meshio drops surfaces and renumbers; see
``../shared/docs/fe-calculix-reference.md``).
"""
