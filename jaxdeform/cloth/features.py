"""Per-frame representations of cloth sequences for the detail-synthesis network (seed 002, Sec. 3.2).

Three representations, the rows of the paper's Table 4:

- ``"ts-acap"``: TS-ACAP, the ACAP features (9-d per vertex: consistent log-rotation + symmetric stretch)
  relative to the rest mesh, with the axis orientations and 2 pi turns of every vertex made consistent with
  its neighbours AND with itself in the previous frame (``acap.encode(..., consistency="temporal")``, eqs.
  2-4). Frames of one sequence are encoded together, in order.
- ``"acap"``: the same features made consistent within each frame only (spatial ACAP, Gao et al. 2019).
- ``"coords"``: the vertex coordinates themselves (3 channels).

:class:`Representation` holds the kind, the rest meshes and the scaling fitted on the TRAINING sequences:
per channel, the mean -+ 3 standard deviations map to -+0.95 (clipped at -+1) to suit the networks' tanh
outputs. The official ACAP convention (one global min/max for the rotation entries and one for the stretch
entries, ``mode="minmax"``) is kept as an option, but on the cloth data it starved the networks: a few
vertices with 2 pi turns stretch the TS-ACAP rotation range to -8.5..7.6 rad, so that the scaled features
varied with a variance of 0.002-0.015 and both the transformer and the per-frame model learned to output
their mean.

Residual target (optional, ``residual=True``). The fine target may be the difference between the fine
features and the features of the coarse frame Loop-subdivided to the fine connectivity (the "upsampled
coarse" baseline); the network then learns what the fine simulation adds to the coarse one, and a zero
output decodes to the upsampled coarse cloth. The paper maps coarse to fine features directly (the default).

Positions from features. ACAP features carry no translation. When the scenario holds vertices fixed (the
sheet's rod, the tablecloth's weight), those fine vertices anchor the least squares at their known positions.
Otherwise a fine frame is decoded with vertex 0 held
at its rest position and then translated so that the centroid of the fine vertices that Loop subdivision
kept from the coarse mesh (fine indices 0..Vc-1: ``igl.loop`` keeps them first, :func:`place`) coincides with the centroid of the
coarse frame it was synthesised from. Decoding is the differentiable least-squares reconstruction of
``acap.decode`` (prefactored sparse Cholesky).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from typing import Literal

import numpy as np
from tqdm.auto import tqdm

from jaxdeform.acap import features as acapf

Kind = Literal["ts-acap", "acap", "coords"]
KINDS = ("ts-acap", "acap", "coords")
LIMIT = acapf.SCALE_LIMIT
#: Standard deviations mapped to -+LIMIT by the default scaling.
STD_RANGE = 3.0


def channels(kind: Kind) -> int:
    """Channels per vertex of a representation."""
    return 3 if kind == "coords" else 9


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ValueError(f"unknown representation '{kind}'; expected one of {', '.join(KINDS)}.")


def encode_sequence(kind: Kind, rest: np.ndarray, faces: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Unscaled features of one sequence of frames.

    **Arguments:**

    - ``kind``: the representation kind.
    - ``rest``, ``faces``: the mesh's rest shape ``(V, 3)`` and triangles ``(F, 3)``.
    - ``frames``: ``(T, V, 3)``.

    **Returns:**

    Features ``(T, V, C)``, C = :func:`channels` (kind).
    """
    _check_kind(kind)
    frames = np.asarray(frames, np.float64)
    if kind == "coords":
        return frames.astype(np.float32)
    mode = "temporal" if kind == "ts-acap" else "spatial"
    return np.asarray(acapf.encode(rest, faces, frames, consistency=mode), np.float32)


@dataclasses.dataclass(frozen=True)
class Scaling:
    """Affine map of each channel group to [-0.95, 0.95]: ``lo``/``hi`` per channel (C,)."""

    lo: np.ndarray
    hi: np.ndarray

    @staticmethod
    def fit(kind: Kind, seqs: list[np.ndarray], mode: str = "std") -> Scaling:
        """``mode="std"`` (default): per channel, mean -+ STD_RANGE standard deviations map to -+0.95;
        ``"minmax"``: the official ACAP convention (one range for rotations, one for S; per axis for coords)."""
        cat = np.concatenate([np.asarray(s, np.float64).reshape(-1, channels(kind)) for s in seqs])
        if mode == "std":
            mu, sd = cat.mean(axis=0), cat.std(axis=0) + 1e-6
            return Scaling(mu - STD_RANGE * sd, mu + STD_RANGE * sd)
        if mode != "minmax":
            raise ValueError(f"scaling mode must be 'std' or 'minmax', got {mode!r}.")
        if kind == "coords":
            lo, hi = cat.min(axis=0), cat.max(axis=0)
            pad = 1e-6 + 1e-3 * (hi - lo)
            return Scaling(lo - pad, hi + pad)
        sc = acapf.Scaler.fit(cat)
        lo = np.array([sc.rot_min] * 3 + [sc.s_min] * 6)
        hi = np.array([sc.rot_max] * 3 + [sc.s_max] * 6)
        return Scaling(lo, hi)

    def transform(self, f):
        """To the networks' range; values beyond it are clipped to -+1 (the tanh outputs' bound)."""
        x = (2.0 * (np.asarray(f, np.float64) - self.lo) / (self.hi - self.lo) - 1.0) * LIMIT
        return np.clip(x, -1.0, 1.0).astype(np.float32)

    def inverse(self, x):
        """Works on numpy and jax arrays (differentiable)."""
        return (x / LIMIT + 1.0) * 0.5 * (self.hi - self.lo) + self.lo

    def to_array(self) -> np.ndarray:
        return np.stack([self.lo, self.hi])

    @staticmethod
    def from_array(a) -> Scaling:
        a = np.asarray(a, np.float64)
        return Scaling(a[0], a[1])


@dataclasses.dataclass(frozen=True)
class Representation:
    """A representation kind with the rest meshes and the scalings of both resolutions."""

    kind: str
    coarse_rest: np.ndarray
    coarse_faces: np.ndarray
    fine_rest: np.ndarray
    fine_faces: np.ndarray
    coarse_scaling: Scaling
    fine_scaling: Scaling
    residual: bool = False  # fine target = features(fine) - features(Loop(coarse)) (module docstring)
    _bases: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def channels(self) -> int:
        return channels(self.kind)

    @functools.cached_property
    def upsampler(self):
        """Loop subdivision coarse -> fine as one sparse matrix (built once per representation)."""
        from jaxdeform.cloth.evaluate import Upsampler

        return Upsampler(self.coarse_faces, self.coarse_rest.shape[0], self.fine_faces)

    def base(self, coarse_frames, remember: bool = True) -> np.ndarray:
        """Unscaled fine features of the Loop-upsampled coarse frames (the residual's base), (T, Vf, C).

        Remembered per coarse sequence (by content) while the representation lives: fitting and training
        ask for the same training sequences' bases. ``remember=False`` computes it afresh and keeps nothing
        (synthesis, whose timing must include it)."""
        x = np.ascontiguousarray(coarse_frames, np.float32)
        key = (x.shape, hashlib.sha1(x.tobytes()).hexdigest()) if remember else None
        if key in self._bases:
            return self._bases[key]
        base = encode_sequence(self.kind, self.fine_rest, self.fine_faces, self.upsampler(x))
        if remember:
            self._bases[key] = base
        return base

    def encode(self, res: str, frames: np.ndarray) -> np.ndarray:
        """Scaled features of frames of one resolution.

        **Arguments:**

        - ``res``: "coarse" or "fine".
        - ``frames``: ``(T, V, 3)``.

        **Returns:**

        Scaled features ``(T, V, C)``.

        **Raises:**

        ``ValueError`` for another resolution.
        """
        rest, faces, sc = self._mesh(res)
        return sc.transform(encode_sequence(self.kind, rest, faces, frames))

    def _mesh(self, res: str):
        if res == "coarse":
            return self.coarse_rest, self.coarse_faces, self.coarse_scaling
        if res == "fine":
            return self.fine_rest, self.fine_faces, self.fine_scaling
        raise ValueError(f"resolution must be 'coarse' or 'fine', got {res!r}.")

    def decode_fine(
        self, scaled, coarse_frames, refine: int = acapf.DEFAULT_REFINE, base=None, pins=None, pin_positions=None
    ) -> np.ndarray:
        """Fine positions from scaled fine features and the coarse frames.

        With ``residual`` the scaled features are a residual over ``base``. The pins, the scenario's fixed vertices,
        anchor the reconstruction; without pins it is placed on the coarse centroid (:func:`place`).

        **Arguments:**

        - ``scaled``: scaled fine features ``(T, Vf, C)``.
        - ``coarse_frames``: ``(T, Vc, 3)``.
        - ``refine``: defect-correction steps of the ACAP reconstruction.
        - ``base``: the residual's base (default None: :meth:`base` of the coarse frames).
        - ``pins``: fine vertex indices ``(P,)``; ``pin_positions``: where they are held ``(P, 3)``.

        **Returns:**

        Fine positions ``(T, Vf, 3)``.
        """
        f = np.asarray(self.fine_scaling.inverse(np.asarray(scaled, np.float64)))
        if self.residual:
            f = f + (self.base(coarse_frames) if base is None else base)
        if self.kind == "coords":
            return f.astype(np.float32)
        if pins is not None and len(pins):
            p = acapf.decode(
                f,
                self.fine_rest,
                self.fine_faces,
                anchors=np.asarray(pins),
                targets=np.asarray(pin_positions, np.float64),
                refine=refine,
            )
            return np.asarray(p, np.float32)
        p = np.asarray(acapf.decode(f, self.fine_rest, self.fine_faces, refine=refine), np.float64)
        return place(p, np.asarray(coarse_frames, np.float64), self.coarse_rest.shape[0]).astype(np.float32)

    def to_arrays(self) -> dict:
        return {
            "kind": np.asarray(self.kind),
            "residual": np.asarray(self.residual),
            "coarse_rest": self.coarse_rest,
            "coarse_faces": self.coarse_faces,
            "fine_rest": self.fine_rest,
            "fine_faces": self.fine_faces,
            "coarse_scaling": self.coarse_scaling.to_array(),
            "fine_scaling": self.fine_scaling.to_array(),
        }

    @staticmethod
    def from_arrays(a: dict) -> Representation:
        return Representation(
            str(a["kind"]),
            np.asarray(a["coarse_rest"], np.float64),
            np.asarray(a["coarse_faces"], np.int64),
            np.asarray(a["fine_rest"], np.float64),
            np.asarray(a["fine_faces"], np.int64),
            Scaling.from_array(a["coarse_scaling"]),
            Scaling.from_array(a["fine_scaling"]),
            bool(a.get("residual", False)),
        )


def place(fine: np.ndarray, coarse: np.ndarray, n_coarse: int) -> np.ndarray:
    """Translate each fine frame so its first ``n_coarse`` vertices have the coarse frame's centroid.

    **Arguments:**

    - ``fine``: fine frames ``(T, Vf, 3)`` (Loop order: the coarse vertices first).
    - ``coarse``: coarse frames ``(T, Vc, 3)``.
    - ``n_coarse``: Vc.

    **Returns:**

    The translated fine frames ``(T, Vf, 3)``.
    """
    shift = coarse.mean(axis=-2, keepdims=True) - fine[..., :n_coarse, :].mean(axis=-2, keepdims=True)
    return fine + shift


def fit_representation(
    kind: Kind, dataset, train_names: list[str] | None = None, progress: bool = True, residual: bool = False
):
    """Fit a feature representation on the training sequences and scale every sequence with it.

    **Arguments:**

    - ``kind``: the representation kind.
    - ``dataset``: the :class:`~jaxdeform.cloth.data.ClothDataset`.
    - ``train_names``: the training sequences (default None: the dataset's training split).
    - ``progress``: show a progress bar.
    - ``residual``: the fine target is features(fine) - features(Loop(coarse)) (module docstring).

    **Returns:**

    ``(representation, scaled)``: the :class:`Representation` fitted on the training sequences and
    ``{name: (coarse features, fine target)}``, scaled, for every sequence.
    """
    _check_kind(kind)
    seqs = dataset.sequences
    train = set(train_names if train_names is not None else [s.name for s in dataset.subset("train")])
    rep = Representation(
        kind,
        dataset.coarse_rest,
        dataset.coarse_faces,
        dataset.fine_rest,
        dataset.fine_faces,
        Scaling(np.zeros(channels(kind)), np.ones(channels(kind))),
        Scaling(np.zeros(channels(kind)), np.ones(channels(kind))),
        residual,
    )
    raw = {}
    for s in tqdm(seqs, desc=f"{kind}{' residual' if residual else ''} features", unit="seq", disable=not progress):
        fine = encode_sequence(kind, dataset.fine_rest, dataset.fine_faces, s.fine)
        if residual:
            fine = fine - rep.base(s.coarse)
        raw[s.name] = (encode_sequence(kind, dataset.coarse_rest, dataset.coarse_faces, s.coarse), fine)
    sc_c = Scaling.fit(kind, [raw[n][0] for n in raw if n in train])
    sc_f = Scaling.fit(kind, [raw[n][1] for n in raw if n in train])
    bases = rep._bases
    rep = dataclasses.replace(rep, coarse_scaling=sc_c, fine_scaling=sc_f)
    rep._bases.update(bases)  # the bases do not depend on the scalings
    scaled = {n: (sc_c.transform(c), sc_f.transform(f)) for n, (c, f) in raw.items()}
    return rep, scaled


def frame_changes(features: np.ndarray) -> np.ndarray:
    """||f_(t+1) - f_t|| for every frame pair and vertex, flattened (unscaled features of one sequence)."""
    f = np.asarray(features, np.float64)
    return np.linalg.norm(np.diff(f, axis=0), axis=-1).ravel()


def largest_frame_change(features: np.ndarray) -> float:
    """max over frames t and vertices of ||f_(t+1) - f_t|| (unscaled features of one sequence)."""
    c = frame_changes(features)
    return float(c.max()) if c.size else 0.0


def frame_change_stats(seqs: list[np.ndarray]) -> dict:
    """Frame-to-frame change statistics over sequences.

    **Arguments:**

    - ``seqs``: unscaled features of each sequence, ``(T_i, V, C)``.

    **Returns:**

    A dict: the largest, 99th and 99.9th percentile change, and the fraction above pi (a rotation log jumping by
    a 2 pi turn or an axis flip).
    """
    c = np.concatenate([frame_changes(f) for f in seqs])
    return {
        "max": float(c.max()),
        "p99": float(np.percentile(c, 99)),
        "p99_9": float(np.percentile(c, 99.9)),
        "fraction_above_pi": float(np.mean(c > np.pi)),
        "count": int(c.size),
    }
