"""jaxdeform: mesh deformation representations and methods in JAX.

Layers (imports point down only): ``mesh`` (I/O, topology, geometry, geodesics, rendering) ->
``acap`` (deformation gradients, rotations, consistency, features, reconstruction) -> methods -> ``cli``.
"""

import jax

# Geometry is tested in float32 and float64; enabling x64 keeps float64 inputs in float64.
# Arrays created from float32 data stay float32.
jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
