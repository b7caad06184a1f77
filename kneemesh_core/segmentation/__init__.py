"""Segmentation of sagittal knee MRI into canonical labels, on the CPU with ONNX.

Inference, in the order it runs:

1. :mod:`.preprocess` - the image into the network's orientation, pixel spacing and
   intensity scale, as slices; and back onto the input's exact grid;
2. :mod:`.infer` - onnxruntime over batches of slices (the shipped model is in ``models/``
   with its model card), arg-max, then
3. :mod:`.postprocess` - each tissue kept where anatomy puts it (bones opened to cut leaks, the patella in front of the femur, the patellar cartilage on it), holes filled; the tibial plates split by anatomy.

Training (PyTorch, the ``train`` extra): :mod:`.model` (the residual U-Net), :mod:`.synth`
(DESS-like contrast on label slices), :mod:`.dataset` (subjects, the split, training pairs),
:mod:`.train` (the loop, ONNX export and agreement check); :mod:`.evaluate` scores label maps.
"""
