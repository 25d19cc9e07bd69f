"""jaxdeform: mesh deformation representations and methods in JAX.

Layers (imports point down only): ``mesh`` (I/O, topology, geometry, geodesics, rendering) ->
``acap`` (deformation gradients, rotations, consistency, features, reconstruction) -> methods -> ``cli``.

Importing the package changes no JAX setting: every function computes in the dtype of its input (float64 only
where the caller has enabled ``jax_enable_x64``). The ``jaxdeform`` command and the experiments enable x64 for
their own process when they start (:func:`jaxdeform.cli.main`, ``experiments/__init__.py``).
"""

__version__ = "0.1.0"
