"""Deformation components of a trained multiscale model (seed 000, Secs. 4.2-4.3 and 5.2) and of linear baselines.

**Extraction.** A block's components are its decoder outputs for one-hot codes (eq. (4): "setting the latent
vector to a one-hot vector"), measured against the same decoder at the base code::

    delta_k = ae_decode(z_base + (s_k - z_base,k) e_k) - ae_decode(z_base)        (Kz, V, 9), scaled features

so a component is the change of the scaled ACAP features that latent ``k`` adds. ``z_base`` is zero by
default (the "rest" output); since :meth:`jaxdeform.components.model.Model.decode_latents` sums independent block
outputs, ``delta_k`` is exactly ``decode_latents(one-hot) - decode_latents(0)``. The magnitude ``s_k``: for
visualization the paper extracts components "using the same method as [10]" (Tan et al. 2018), whose public
code sweeps each latent dimension between its minimum and maximum over the training codes (other dimensions
at the reference shape's code) and keeps the end whose features differ most (largest squared norm) from the
reference. :func:`all_components` does exactly that when given the training codes (``latents``, optionally
the ``reference`` shape's code as base); without codes it uses ``s_k = theta`` (= 5, the bound V(Z) of
eq. (2) puts on |z|, i.e. the extreme a trained code reaches).

Scaled differences map back to ACAP feature differences through the linear :class:`~jaxdeform.acap.Scaler`
(``inverse(d) - inverse(0)``), and a component mesh is ``decode(X_r + diff)`` with ``X_r`` the reference
mesh's own features (identity: log R = 0, S = I) -- the reference deformed by that component alone.

**Deformation strength, eq. (7).** With ``X_diff = X_m - X_r`` (here: the component's feature differences)::

    I(X_m) = sum_i 1(||X_diff,i|| > eps1) ||X_diff,i|| / sum_i 1(||X_diff,i|| > eps1),      eps1 = 1e-6

the mean per-vertex norm over the vertices that move at all (0 when none does). Per vertex the strength is
``||X_diff,i||`` (the summand), used to colour the deformed region in figures. I is positively homogeneous:
``I(c X_diff) = c I(X_diff)`` for c > 0 whenever no vertex norm crosses eps1.

**Redundant component removal (Sec. 4.3).** "If the extracted deformation component corresponds to a slight
deformation, defined as its strength being smaller than a threshold eps2, we will remove the component";
eps2 = 0.01. The paper then checks near duplicates with the cosine similarity matrix of Fig. 3 but states no
threshold; :func:`remove_redundant` additionally drops a component whose |cosine similarity| with an earlier
kept one is at least ``duplicate_cos`` (default 1 - 1e-6: only exact duplicates or sign flips; ``None``
follows the paper's strength rule alone).

**Cosine similarity (Fig. 3).** ``S_ab = <a, b> / (||a|| ||b||)`` of the flattened components (V * c values).

**Linear baselines.** :func:`from_arrays` wraps components given as arrays (K, V, c) -- e.g. PCA or SPLOCS
(``LinearModel.components``) -- with a domain flag: ``"acap"`` (feature differences, scaled if a ``scaler`` is
given) or ``"xyz"`` (displacements added to the rest shape), so that strength, removal, similarity and
figures are shared.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxdeform.acap.features import Scaler, decode
from jaxdeform.components.model import Model
from jaxdeform.errors import ConnectivityError, DegenerateMeshError
from jaxdeform.nn.graph_conv import MU, AEBlock, Rings, ae_decode

EPS1 = 1e-6
EPS2 = 0.01
DUPLICATE_COS = 1.0 - 1e-6

#: ACAP features of the reference mesh itself: log R = 0, S = I (layout of :mod:`jaxdeform.acap.features`).
IDENTITY_FEATURES = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0])

Domain = Literal["scaled", "acap", "xyz"]
DOMAINS = ("scaled", "acap", "xyz")


@dataclasses.dataclass(frozen=True, eq=False)
class ComponentSet:
    """Components of one model, flattened over levels and blocks (order: level, block, index).

    ``values`` (K, V, c): ``"scaled"`` differences of network-scaled ACAP features (c = 9), ``"acap"``
    differences of ACAP features (c = 9) or ``"xyz"`` vertex displacements (c = 3). ``level``, ``block``,
    ``index`` (K,) locate each component (linear baselines: level 0, block 0); ``magnitude`` (K,) is the
    latent value it was extracted at (1 for linear components); ``method`` names the model in labels.
    """

    values: np.ndarray
    level: np.ndarray
    block: np.ndarray
    index: np.ndarray
    magnitude: np.ndarray
    domain: Domain
    method: str = "AE"

    def __post_init__(self):
        v = np.asarray(self.values)
        if v.ndim != 3 or v.shape[0] == 0 or v.shape[1] == 0:
            raise ValueError(f"component values must be a non-empty (K, V, c) array, got shape {v.shape}.")
        if self.domain not in DOMAINS:
            raise ValueError(f"unknown component domain {self.domain!r}; expected one of {', '.join(DOMAINS)}.")
        want = 3 if self.domain == "xyz" else MU
        if v.shape[2] != want:
            raise ValueError(f"{self.domain} components need {want} values per vertex, got {v.shape[2]}.")
        _check_finite(v, "component")
        for name in ("level", "block", "index", "magnitude"):
            a = np.asarray(getattr(self, name))
            if a.shape != (v.shape[0],):
                raise ValueError(f"{name} must have shape ({v.shape[0]},) (one per component), got {a.shape}.")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "values", v)

    def __len__(self) -> int:
        return self.values.shape[0]

    @property
    def n_vertices(self) -> int:
        return self.values.shape[1]

    def select(self, mask) -> ComponentSet:
        """The components where ``mask`` (K,) is true (or at integer positions ``mask``)."""
        m = np.asarray(mask)
        return dataclasses.replace(
            self,
            values=self.values[m],
            level=self.level[m],
            block=self.block[m],
            index=self.index[m],
            magnitude=self.magnitude[m],
        )

    def names(self) -> list[str]:
        """A short label per component: ``"AE0 #3"``, ``"AE4 #1"`` (level 1, block 3), ``"PCA #7"``."""
        return [
            component_name(int(l), int(b), int(k), self.method) for l, b, k in zip(self.level, self.block, self.index)
        ]

    def groups(self) -> list[str]:
        """The block each component belongs to, as named in figures (one row per block)."""
        return [block_name(int(l), int(b), self.method) for l, b in zip(self.level, self.block)]


def block_name(level: int, block: int, method: str = "AE") -> str:
    """``AE0`` for the first level, ``AEk`` (k = block + 1) for the second, ``L<l> AEk`` below; ``method`` for
    a linear model's single block."""
    if method != "AE":
        return method if level == 0 and block == 0 else f"{method} L{level}.{block}"
    if level == 0:
        return "AE0"
    if level == 1:
        return f"AE{block + 1}"
    return f"L{level} AE{block + 1}"


def component_name(level: int, block: int, index: int, method: str = "AE") -> str:
    return f"{block_name(level, block, method)} #{index}"


def _check_finite(a: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise DegenerateMeshError(f"{what} {int(bad[0])} has a NaN or infinite value (vertex {int(bad[1])}).")


# ---------------------------------------------------------------------------------------------- extraction


def _one_hot_codes(scale: Float[Array, " kz"], base: Float[Array, " kz"]) -> Float[Array, "kz kz"]:
    """Row k: the base code with entry k replaced by scale_k."""
    kz = base.shape[0]
    eye = jnp.eye(kz, dtype=base.dtype)
    return base[None, :] * (1.0 - eye) + eye * scale[None, :]


def _block_deltas(
    p: AEBlock, rings: Rings, scale: Float[Array, " kz"], base: Float[Array, " kz"]
) -> Float[Array, "kz v 9"]:
    out = ae_decode(p, _one_hot_codes(scale, base), rings)
    return out - ae_decode(p, base[None, :], rings)


_block_deltas_jit = jax.jit(_block_deltas)


@jax.jit
def _level_deltas(
    p: AEBlock, rings: Rings, scale: Float[Array, "n kz"], base: Float[Array, "n kz"]
) -> Float[Array, "n kz v 9"]:
    return jax.vmap(lambda q, s, b: _block_deltas(q, rings, s, b))(p, scale, base)


def _level_kz(m: Model, level: int) -> tuple[int, int]:
    if not 0 <= level < len(m.levels):
        raise ValueError(f"level {level} does not exist; the model has {len(m.levels)} levels.")
    n, kz = m.levels[level].C.shape[:2]
    return int(n), int(kz)


def block_components(m: Model, rings: Rings, level: int, block: int, scale=1.0, base=None) -> Float[Array, "kz v 9"]:
    """Components (Kz, V, 9) of block ``block`` of ``level`` of model ``m``, as scaled-feature differences.

    Row k is ``ae_decode(base with z_k = scale_k) - ae_decode(base)``; ``scale`` is a number or one per
    component (Kz,), ``base`` the block's base code (Kz,) (default zeros: the one-hot codes of eq. (4)).
    """
    n, kz = _level_kz(m, level)
    if not 0 <= block < n:
        raise ValueError(f"block {block} does not exist; level {level} has {n} blocks.")
    p = jax.tree_util.tree_map(lambda a: a[block], m.levels[level])
    dtype = p.C.dtype
    s = jnp.broadcast_to(jnp.asarray(scale, dtype), (kz,))
    b = jnp.zeros((kz,), dtype) if base is None else jnp.asarray(base, dtype).reshape(kz)
    return _block_deltas_jit(p, rings, s, b)


def latent_extremes(
    m: Model, rings: Rings, level: int, codes: Float[Array, "n b kz"], base: Float[Array, "n kz"] | None = None
) -> Float[Array, "n kz"]:
    """Per block and latent dimension, the end of the codes' range [min_m z, max_m z] whose component changes
    the features most (largest squared norm), as in the public code of Tan et al. [10] (model ``m``)."""
    n, kz = _level_kz(m, level)
    codes = jnp.asarray(codes, m.levels[level].C.dtype)
    if codes.ndim != 3 or codes.shape[0] != n or codes.shape[2] != kz or codes.shape[1] == 0:
        raise ValueError(f"codes of level {level} must have shape ({n}, B, {kz}) with B >= 1, got {codes.shape}.")
    base = jnp.zeros((n, kz), codes.dtype) if base is None else jnp.asarray(base, codes.dtype)
    lo, hi = jnp.min(codes, axis=1), jnp.max(codes, axis=1)
    d_lo = jnp.sum(jnp.square(_level_deltas(m.levels[level], rings, lo, base)), axis=(2, 3))
    d_hi = jnp.sum(jnp.square(_level_deltas(m.levels[level], rings, hi, base)), axis=(2, 3))
    return jnp.where(d_hi >= d_lo, hi, lo)


def all_components(
    m: Model,
    rings: Rings,
    *,
    scale: float | None = None,
    latents: tuple | None = None,
    reference: int | None = None,
    scaler: Scaler | None = None,
) -> ComponentSet:
    """Every block's components, level by level (K = sum_l n_l Kz_l; 60 with the paper's Kz = [10, 5]).

    **Arguments:**

    - ``m``: the model; its configuration must use the default decoder (``tie_conv=False``,
        ``decoder_tanh=True``).
    - ``rings``: the mesh's one-rings.
    - ``scale``: the code magnitude without ``latents`` (default None: ``config.theta``).
    - ``latents``: the training codes, per level ``(n_l, B, Kz_l)`` as in ``Output.latents``; the magnitudes are then
        the data extreme of [10] (:func:`latent_extremes`).
    - ``reference``: an index into B (needs ``latents``): that shape's code as base instead of zero.
    - ``scaler``: with it the values are ACAP feature differences (domain ``"acap"``), else scaled-feature
        differences (``"scaled"``).

    **Returns:**

    A :class:`ComponentSet` of K components ``(K, V, 9)`` with their level, block, index and magnitude.

    **Raises:**

    ``ValueError`` for a variant decoder, ``reference`` without ``latents`` or out of range, or ``latents`` with
    another number of levels.
    """
    config = m.config
    if config.tie_conv or not config.decoder_tanh:
        raise ValueError("component extraction needs the default decoder (tie_conv=False, decoder_tanh=True).")
    levels = tuple(m.levels)
    if reference is not None and latents is None:
        raise ValueError("a reference shape needs the training codes (latents) to take its code from.")
    if latents is not None and len(latents) != len(levels):
        raise ValueError(f"latents must give one array per level ({len(levels)}), got {len(latents)}.")
    values, level, block, index, magnitude = [], [], [], [], []
    for lv, p in enumerate(levels):
        n, kz = _level_kz(m, lv)
        dtype = p.C.dtype
        base = jnp.zeros((n, kz), dtype)
        if latents is not None:
            codes = jnp.asarray(latents[lv], dtype)
            if reference is not None:
                if not 0 <= reference < codes.shape[1]:
                    raise ValueError(f"reference {reference} is not one of the {codes.shape[1]} coded shapes.")
                base = codes[:, reference]
            s = latent_extremes(m, rings, lv, codes, base)
        else:
            s = jnp.full((n, kz), config.theta if scale is None else scale, dtype)
        values.append(np.asarray(_level_deltas(p, rings, s, base)).reshape(n * kz, -1, MU))
        level.append(np.full(n * kz, lv))
        block.append(np.repeat(np.arange(n), kz))
        index.append(np.tile(np.arange(kz), n))
        magnitude.append(np.asarray(s).reshape(-1))
    cs = ComponentSet(
        np.concatenate(values),
        np.concatenate(level),
        np.concatenate(block),
        np.concatenate(index),
        np.concatenate(magnitude),
        "scaled",
    )
    return cs if scaler is None else unscale(cs, scaler)


def from_arrays(
    components, domain: Literal["acap", "xyz"], *, scaler: Scaler | None = None, weight=1.0, method: str = "linear"
) -> ComponentSet:
    """Components given as arrays (K, V, c) (e.g. PCA or SPLOCS), as one block at level 0.

    ``domain="acap"``: ACAP feature differences (c = 9), taken as *scaled* and mapped back when ``scaler`` is
    given; ``"xyz"``: displacements (c = 3). ``weight`` (a number or (K,)) multiplies each component (the
    coefficient it is shown at); it is recorded as the magnitude.
    """
    if domain not in ("acap", "xyz"):
        raise ValueError(f"linear components live in 'acap' or 'xyz', got {domain!r}.")
    if domain == "xyz" and scaler is not None:
        raise ValueError("a Scaler applies to ACAP features, not to xyz displacements.")
    c = np.asarray(components, dtype=np.float64)
    if c.ndim != 3 or c.shape[0] == 0:
        raise ValueError(f"components must be a non-empty (K, V, c) array, got shape {c.shape}.")
    w = np.broadcast_to(np.asarray(weight, dtype=np.float64), (c.shape[0],))
    k = c.shape[0]
    zeros = np.zeros(k, dtype=np.int64)
    cs = ComponentSet(
        c * w[:, None, None], zeros, zeros, np.arange(k), w.copy(), "scaled" if scaler is not None else domain, method
    )
    return cs if scaler is None else unscale(cs, scaler)


def unscale_values(values: Float[Array, "k v 9"], scaler: Scaler) -> Float[Array, "k v 9"]:
    """Scaled-feature differences -> ACAP feature differences (the Scaler is affine: the offset cancels)."""
    x = jnp.asarray(values)
    return scaler.inverse(x) - scaler.inverse(jnp.zeros((MU,), x.dtype))


def unscale(cs: ComponentSet, scaler: Scaler) -> ComponentSet:
    """A ``"scaled"`` set as ACAP feature differences (domain ``"acap"``)."""
    if cs.domain != "scaled":
        raise ValueError(f"only scaled components can be unscaled, these are {cs.domain!r}.")
    return dataclasses.replace(cs, values=np.asarray(unscale_values(cs.values, scaler)), domain="acap")


def component_meshes(
    cs: ComponentSet, rest, faces, *, scaler: Scaler | None = None, base=None, refine: int | None = None
) -> np.ndarray:
    """Each component applied alone to the reference: vertex positions.

    ``"acap"``: ``decode(base + diff)`` with ``base`` ``(V, 9)`` defaulting to the reference's own features (identity);
    ``"scaled"`` needs the ``scaler`` first; ``"xyz"``: ``base + displacement`` with ``base`` ``(V, 3)`` defaulting to
    ``rest`` (pass a linear model's mean shape or mean features as ``base``).

    **Arguments:**

    - ``cs``: the components.
    - ``rest``: the reference shape ``(V, 3)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``scaler``: the training features' scaler (needed for ``"scaled"`` components).
    - ``base``: the base features ``(V, 9)`` or positions ``(V, 3)`` (see above).
    - ``refine``: defect-correction steps of the ACAP decode (default None: the decoder's default).

    **Returns:**

    The meshes ``(K, V, 3)``.

    **Raises:**

    ``ValueError`` for a rest shape, base or scaler that does not fit; ``ConnectivityError`` if the components have
    another number of vertices than ``rest``; ``DegenerateMeshError`` if a decoded mesh is not finite.
    """
    rest = np.asarray(rest, dtype=np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3:
        raise ValueError(f"the rest shape must be (V, 3), got {rest.shape}.")
    if rest.shape[0] != cs.n_vertices:
        raise ConnectivityError(f"the components have {cs.n_vertices} vertices but the rest shape has {rest.shape[0]}.")
    if cs.domain == "scaled":
        if scaler is None:
            raise ValueError("scaled components need the Scaler of the training features to be decoded.")
        cs = unscale(cs, scaler)
    if cs.domain == "xyz":
        b = rest if base is None else np.asarray(base, dtype=np.float64)
        if b.shape != rest.shape:
            raise ValueError(f"the xyz base must have shape {rest.shape}, got {b.shape}.")
        return b[None] + cs.values
    b = np.broadcast_to(IDENTITY_FEATURES, (cs.n_vertices, MU)) if base is None else np.asarray(base, np.float64)
    if b.shape != (cs.n_vertices, MU):
        raise ValueError(f"the ACAP base features must have shape ({cs.n_vertices}, 9), got {b.shape}.")
    kw = {} if refine is None else {"refine": refine}
    out = np.asarray(decode(jnp.asarray(b[None] + cs.values), rest, faces, **kw))
    _check_finite(out, "decoded component mesh")
    return out


# ------------------------------------------------------------------------------------- strength and similarity


@jax.jit
def vertex_strength(values: Float[Array, "k v c"]) -> Float[Array, "k v"]:
    """Per-vertex strength ||X_diff,i|| (the summand of eq. (7))."""
    return jnp.sqrt(jnp.sum(jnp.square(jnp.asarray(values)), axis=-1))


def active_vertices(values: Float[Array, "k v c"], eps1: float = EPS1) -> Bool[Array, "k v"]:
    """1(||X_diff,i|| > eps1) of eq. (7)."""
    return vertex_strength(values) > eps1


@jax.jit
def deformation_strength(values: Float[Array, "k v c"], eps1: float = EPS1) -> Float[Array, " k"]:
    """I of eq. (7): the mean of ||X_diff,i|| over the vertices where it exceeds eps1 (0 when none does)."""
    norms = vertex_strength(values)
    active = norms > eps1
    count = jnp.sum(active, axis=-1)
    total = jnp.sum(jnp.where(active, norms, 0.0), axis=-1)
    return jnp.where(count > 0, total / jnp.maximum(count, 1), 0.0)


@jax.jit
def similarity_matrix(values: Float[Array, "k v c"]) -> Float[Array, "k k"]:
    """Cosine similarity <a, b> / (||a|| ||b||) of the flattened components (Fig. 3), in [-1, 1].

    The diagonal is 1; a pair involving a zero component (no direction) has similarity 0.
    """
    x = jnp.asarray(values)
    x = x.reshape(x.shape[0], -1)
    norm = jnp.sqrt(jnp.sum(jnp.square(x), axis=1))
    unit = x / jnp.where(norm > 0, norm, 1.0)[:, None]
    s = jnp.clip(unit @ unit.T, -1.0, 1.0)
    return jnp.where(jnp.eye(x.shape[0], dtype=bool), 1.0, s)


@dataclasses.dataclass(frozen=True, eq=False)
class Removal:
    """Outcome of :func:`remove_redundant`.

    ``keep`` (K,) bool and ``strength`` (K,) eq. (7) per component; ``kept[(level, block)]``: the kept
    component indices of every block (possibly empty); ``removed[(level, block, index)]``: the reason.
    """

    keep: np.ndarray
    strength: np.ndarray
    kept: dict
    removed: dict

    def as_dict(self) -> dict:
        """JSON-ready: strengths, kept indices per block and reasons, keyed by "level/block[/index]"."""
        return {
            "strength": [float(s) for s in self.strength],
            "kept": {f"{l}/{b}": list(v) for (l, b), v in self.kept.items()},
            "removed": {f"{l}/{b}/{k}": r for (l, b, k), r in self.removed.items()},
        }


def remove_redundant(
    cs: ComponentSet, eps1: float = EPS1, eps2: float = EPS2, duplicate_cos: float | None = DUPLICATE_COS
) -> Removal:
    """Sec. 4.3: drop weak components, then duplicates.

    Drops components whose strength (eq. (7)) is below ``eps2``; then (not in the paper, see the module docstring)
    a component whose |cosine similarity| with an earlier kept one reaches ``duplicate_cos``. Earlier = level,
    block, index order.

    **Arguments:**

    - ``cs``: the components.
    - ``eps1``: the vertex-strength threshold of eq. (7) (non-negative).
    - ``eps2``: the least strength of a kept component (non-negative).
    - ``duplicate_cos``: in (0, 1], or None to skip the duplicate check.

    **Returns:**

    A :class:`Removal`: which components are kept, their strengths and the reasons for the removed ones.

    **Raises:**

    ``ValueError`` for thresholds out of range.
    """
    if not eps1 >= 0 or not eps2 >= 0:
        raise ValueError(f"eps1 and eps2 must be non-negative, got {eps1} and {eps2}.")
    if duplicate_cos is not None and not 0 < duplicate_cos <= 1:
        raise ValueError(f"duplicate_cos must lie in (0, 1] or be None, got {duplicate_cos}.")
    strength = np.asarray(deformation_strength(cs.values, eps1), dtype=np.float64)
    keep = strength >= eps2
    names = cs.names()
    removed = {}
    for i in np.flatnonzero(~keep):
        removed[(int(cs.level[i]), int(cs.block[i]), int(cs.index[i]))] = (
            f"slight deformation: strength {strength[i]:.3g} < eps2 = {eps2:g}"
        )
    if duplicate_cos is not None and keep.any():
        sim = np.abs(np.asarray(similarity_matrix(cs.values)))
        for i in np.flatnonzero(keep):  # a loop over components, not vertices
            earlier = np.flatnonzero(keep[:i])
            if earlier.size:
                j = earlier[np.argmax(sim[i, earlier])]
                if sim[i, j] >= duplicate_cos:
                    keep[i] = False
                    removed[(int(cs.level[i]), int(cs.block[i]), int(cs.index[i]))] = (
                        f"duplicate of {names[j]}: |cos| = {sim[i, j]:.6f} >= {duplicate_cos:g}"
                    )
    kept = {}
    for l, b in sorted({(int(l), int(b)) for l, b in zip(cs.level, cs.block)}):
        sel = (cs.level == l) & (cs.block == b) & keep
        kept[(l, b)] = tuple(int(k) for k in cs.index[sel])
    return Removal(keep=keep, strength=strength, kept=kept, removed=removed)


__all__ = [
    "EPS1",
    "EPS2",
    "DUPLICATE_COS",
    "IDENTITY_FEATURES",
    "ComponentSet",
    "Removal",
    "active_vertices",
    "all_components",
    "block_components",
    "block_name",
    "component_meshes",
    "component_name",
    "deformation_strength",
    "from_arrays",
    "latent_extremes",
    "remove_redundant",
    "similarity_matrix",
    "unscale",
    "unscale_values",
    "vertex_strength",
]
