"""Annotation helpers of the annotated packages (``jaxdeform.mesh``, ``jaxdeform.acap``, ``jaxdeform.nn``).

The tests check those packages' jaxtyping annotations at run time (jaxtyping's import hook with beartype:
``--jaxtyping-packages`` in ``pyproject.toml``), so an annotation must admit everything its function accepts.
Functions that compute with ``jnp`` (or read their input with ``np.asarray``) take JAX and NumPy arrays alike:
their arrays are annotated ``Float[ArrayLike, "v 3"]`` with jaxtyping's ``ArrayLike`` (the same object as
``jax.typing.ArrayLike``, the spelling of the modules that do not import it), which with a shape means a JAX array
(tracers included) or a NumPy array of that shape and dtype kind.

:class:`NonArrayLeaf` is for the array fields of ``jax.tree_util.register_dataclass`` pytrees. :class:`Int` and
:class:`Real` replace jaxtyping's own in these packages (they also admit NumPy's ``longlong`` arrays).
"""

import jax
import jaxtyping
import numpy as np


class _NonArrayLeafMeta(type):
    def __instancecheck__(cls, obj) -> bool:
        if isinstance(obj, (jax.Array, np.ndarray)):
            return obj.dtype == jax.dtypes.float0  # the tangent of an integer leaf: no values to check
        return True


class NonArrayLeaf(metaclass=_NonArrayLeafMeta):
    """Anything but a JAX or NumPy array that holds values; for annotations only (``isinstance``).

    JAX rebuilds a ``register_dataclass`` pytree through its ``__init__`` (checked under the tests' hook) on
    every unflatten, also with what its tree utilities put in an array's place: ``None`` and sentinels,
    ``jax.ShapeDtypeStruct`` (``jax.eval_shape``), float0 tangents of integer leaves, filter booleans
    (``eqx.partition``), wrapped leaves (``eqx.tree_at``). Such a field is annotated
    ``Int[ArrayLike, "f 3"] | NonArrayLeaf``: a real array in it is still checked, shape and dtype.
    """


class Int(jaxtyping.AbstractDtype):
    """jaxtyping's ``Int``, also admitting NumPy's ``longlong``: int64 on Linux, but a type of its own that
    jaxtyping tells apart by name (libigl returns its index arrays in it)."""

    dtypes = [*jaxtyping.Int.dtypes, "longlong"]


class Real(jaxtyping.AbstractDtype):
    """jaxtyping's ``Real``, also admitting NumPy's ``longlong`` and ``ulonglong`` (see :class:`Int`)."""

    dtypes = [*jaxtyping.Real.dtypes, "longlong", "ulonglong"]
