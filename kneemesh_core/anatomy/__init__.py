"""Knee anatomy: joint frames, ligament and tendon attachment sites, and left/right by shape.

- :mod:`.template` - the Lenhart 2015 knee's 76 ligament fibres and its tibia, patella and
  fibula surfaces (Apache-2.0), and a femur template built once from a real knee, all in one
  template frame (millimetres: x anterior, y superior, z lateral), mirrored for left knees;
- :mod:`.frames` - the knee's coarse frame from its bones, the femur, tibia and patella frames
  and the Grood-Suntay angles between femur and tibia;
- :mod:`.register` - similarity ICP and a smooth non-rigid refinement of a template onto a
  bone, and the shape evidence for left or right;
- :mod:`.attachments` - every fibre end on the subject's bone meshes: ``attachments.json``
  and ``attachments.png``.
"""
