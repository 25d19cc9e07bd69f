"""Errors of synthesised fine cloth sequences against the fine simulation (seed 002, Sec. 5.2, Tables 2, 4, 5).

For a test sequence with fine simulation frames ``G`` (T, V, 3) and a method's frames ``P`` (T, V, 3):

- ``rmse``: sqrt(mean over frames and vertices of ||p - g||^2), in metres (vertex correspondence is exact:
  both share the fine connectivity);
- ``hausdorff``: the symmetric Hausdorff distance between the vertex sets of each frame, averaged over frames;
- ``sted``: the spatio-temporal edge difference of Vasa and Skala (``jaxdeform.metrics.sted``: one-ring
  edge neighbourhoods, temporal edges at the data's frame rate, c = 1), the paper's dynamic-mesh metric.

Several sequences are pooled: rmse over all their frames, hausdorff and sted averaged over frames
(frame-count weighted).

The "coarse" baseline of Table 2 is the coarse simulation Loop-subdivided to the fine connectivity
(:class:`Upsampler`: the product of libigl's Loop subdivision matrices, so it is one sparse product per frame).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from jaxdeform import metrics
from jaxdeform.mesh.topology import half_edge_groups


class Upsampler:
    """Loop subdivision ``levels`` times as one sparse (Vf, Vc) matrix; checks it lands on the fine faces."""

    def __init__(
        self, coarse_faces: np.ndarray, n_coarse: int, fine_faces: np.ndarray | None = None, levels: int | None = None
    ):
        import igl

        f = np.asarray(coarse_faces, np.int64)
        s = sp.identity(n_coarse, format="csr")
        n = n_coarse
        target = None if fine_faces is None else np.asarray(fine_faces, np.int64)
        for _ in range(levels if levels is not None else 8):
            if levels is None and target is not None and f.shape[0] >= target.shape[0]:
                break
            m, f = igl.loop_matrix(f, n)
            s = sp.csr_matrix(m) @ s
            n = s.shape[0]
        if target is not None and (f.shape != target.shape or not np.array_equal(f, target)):
            raise ValueError("Loop subdivision of the coarse mesh does not give the fine connectivity.")
        self.matrix = s.tocsr()
        self.faces = f

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        """(T, Vc, 3) -> (T, Vf, 3)."""
        x = np.asarray(frames, np.float64)
        t, vc, _ = x.shape
        flat = x.transpose(1, 0, 2).reshape(vc, -1)
        return (self.matrix @ flat).reshape(-1, t, 3).transpose(1, 0, 2).astype(np.float32)


def coarse_level_split(upsampler: Upsampler, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split fine-mesh offsets into the part Loop-upsampled coarse offsets can express and the rest.

    The first part is ``U d`` with ``d`` ``(T, Vc, 3)`` the least-squares fit (``U^T U d = U^T offsets``, U the
    ``(Vf, Vc)`` subdivision matrix), the second is orthogonal to every column of U. Applied to fine - upsampled
    coarse, it tells how much of that gap lies at the coarse mesh's own scale (the two simulations moving the
    cloth differently) and how much is finer detail (wrinkles the coarse mesh cannot hold).

    **Arguments:**

    - ``upsampler``: the coarse-to-fine subdivision.
    - ``offsets``: fine-mesh offsets ``(T, Vf, 3)``.

    **Returns:**

    ``(coarse_part, rest)``, each ``(T, Vf, 3)``; the two add up to ``offsets``.
    """
    u = upsampler.matrix
    d = np.asarray(offsets, np.float64)
    if d.ndim != 3 or d.shape[1] != u.shape[0] or d.shape[2] != 3:
        raise ValueError(f"offsets must be (T, {u.shape[0]}, 3), got {d.shape}.")
    t, v, _ = d.shape
    flat = d.transpose(1, 0, 2).reshape(v, -1)
    coef = np.linalg.solve((u.T @ u).toarray(), u.T @ flat)
    low = np.asarray(u @ coef).reshape(v, t, 3).transpose(1, 0, 2)
    return low, d - low


def hinge_faces(faces: np.ndarray) -> np.ndarray:
    """The pairs of faces that share an interior edge, ``(H, 2)`` face indices (one row per interior edge)."""
    g = half_edge_groups(faces)
    s2 = g.starts[g.counts == 2]
    return np.stack([g.fid[s2], g.fid[s2 + 1]], axis=1)


def dihedral_angles(frames: np.ndarray, faces: np.ndarray, hinges: np.ndarray | None = None) -> np.ndarray:
    """The bending angle at every interior edge of every frame, ``(T, H)`` radians in [0, pi]: the angle between
    the unit normals of the two faces (0 where the surface is flat across the edge), rows of :func:`hinge_faces`."""
    x = np.asarray(frames, np.float64)
    f = np.asarray(faces, np.int64)
    h = hinge_faces(f) if hinges is None else hinges
    n = np.cross(x[:, f[:, 1]] - x[:, f[:, 0]], x[:, f[:, 2]] - x[:, f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    cos = np.clip(np.sum(n[:, h[:, 0]] * n[:, h[:, 1]], axis=-1), -1.0, 1.0)
    return np.arccos(cos)


def detail_errors(ref: np.ndarray, rec: np.ndarray, faces: np.ndarray, upsampler: Upsampler) -> dict:
    """How much fine-scale shape a sequence has, against a reference sequence of the same fine mesh.

    - ``dihedral_w1``: the 1-D Wasserstein distance (radians) between the distributions of the bending angles
      (:func:`dihedral_angles`) of every interior edge and frame of ``rec`` and of ``ref``: folds and wrinkles
      that are too few, too shallow or too sharp move it away from 0, wherever they lie;
    - ``fine_scale_rms_ref`` / ``fine_scale_rms``: the RMS (metres) of the part of each frame that the coarse mesh's
      Loop basis cannot express (:func:`coarse_level_split` of the positions), in ``ref`` and in ``rec``: 0 for the
      Loop-upsampled coarse cloth;
    - ``fine_scale_rmse``: the RMS of the difference of those parts (the detail's error, the coarse-scale part
      removed from both).

    Invariant under a rigid motion of ``rec``. **Arguments:** ``ref``, ``rec`` ``(T, V, 3)`` frames of the fine mesh
    ``faces``; ``upsampler`` from its coarse mesh. **Returns:** the dict, with ``frames`` and ``count`` (vertex-frames)
    for pooling (:func:`pool_details`). **Raises:** ``ValueError`` for sequences of other shapes.
    """
    ref = np.asarray(ref, np.float64)
    rec = np.asarray(rec, np.float64)
    if ref.shape != rec.shape:
        raise ValueError(f"shapes differ: {ref.shape} vs {rec.shape}.")
    h = hinge_faces(faces)
    a, b = np.sort(dihedral_angles(ref, faces, h), axis=None), np.sort(dihedral_angles(rec, faces, h), axis=None)
    _, hi = coarse_level_split(upsampler, np.concatenate([ref, rec]))  # one solve for both
    hi_ref, hi_rec = hi[: len(ref)], hi[len(ref) :]
    count = ref.shape[0] * ref.shape[1]
    return {
        "frames": int(ref.shape[0]),
        "count": int(count),
        "dihedral_w1": float(np.mean(np.abs(a - b))),
        "fine_scale_rms_ref": float(np.sqrt(np.sum(hi_ref**2) / count)),
        "fine_scale_rms": float(np.sqrt(np.sum(hi_rec**2) / count)),
        "fine_scale_rmse": float(np.sqrt(np.sum((hi_rec - hi_ref) ** 2) / count)),
    }


def pool_details(per_sequence: list[dict]) -> dict:
    """:func:`detail_errors` of several sequences pooled: RMS values over every vertex-frame, ``dihedral_w1``
    frame-weighted. ``ValueError`` for an empty list."""
    if not per_sequence:
        raise ValueError("no sequences to pool.")
    count = sum(r["count"] for r in per_sequence)
    frames = sum(r["frames"] for r in per_sequence)
    out = {"frames": frames, "sequences": len(per_sequence)}
    out["dihedral_w1"] = sum(r["frames"] * r["dihedral_w1"] for r in per_sequence) / frames
    for k in ("fine_scale_rms_ref", "fine_scale_rms", "fine_scale_rmse"):
        out[k] = float(np.sqrt(sum(r["count"] * r[k] ** 2 for r in per_sequence) / count))
    return out


def sequence_errors(
    ref: np.ndarray, rec: np.ndarray, faces: np.ndarray, fps: float = 30.0, upsampler: Upsampler | None = None
) -> dict:
    """rmse, hausdorff (frame mean) and sted (with its spatial/temporal parts) of one sequence.

    **Arguments:**

    - ``ref``: the reference frames ``(T, V, 3)``.
    - ``rec``: the reconstruction, same shape.
    - ``faces``: triangles ``(F, 3)``.
    - ``fps``: frames per second (STED's temporal part).
    - ``upsampler``: the coarse-to-fine subdivision; given, the result has the detail measure too.

    **Returns:**

    A dict: ``frames``, ``sum_sq``, ``count`` (for pooling), ``rmse``, ``hausdorff``, ``sted``, ``sted_s``, ``sted_t``,
    and with ``upsampler`` ``detail`` (:func:`detail_errors`).

    **Raises:**

    ``ValueError`` if the shapes differ.
    """
    ref = np.asarray(ref, np.float64)
    rec = np.asarray(rec, np.float64)
    if ref.shape != rec.shape:
        raise ValueError(f"shapes differ: {ref.shape} vs {rec.shape}.")
    sq = np.sum((ref - rec) ** 2, axis=-1)
    h = [metrics.hausdorff(a, b) for a, b in zip(ref, rec)]
    st = metrics.sted(ref, rec, faces, fps=fps)
    detail = {} if upsampler is None else {"detail": detail_errors(ref, rec, faces, upsampler)}
    return {
        **detail,
        "frames": int(ref.shape[0]),
        "sum_sq": float(sq.sum()),
        "count": int(sq.size),
        "rmse": float(np.sqrt(sq.mean())),
        "hausdorff": float(np.mean(h)),
        "sted": float(st["sted"]),
        "sted_s": float(st["sted_s"]),
        "sted_t": float(st.get("sted_t", 0.0)),
    }


def pool(per_sequence: list[dict]) -> dict:
    """Pooled errors of several sequences (rmse over all vertices and frames; others frame-weighted).

    **Arguments:**

    - ``per_sequence``: :func:`sequence_errors`' results, at least one.

    **Returns:**

    A dict of the pooled errors with the total ``frames`` and the number of ``sequences`` (and the largest
    ``max_penetration`` when every sequence has one).

    **Raises:**

    ``ValueError`` for an empty list.
    """
    if not per_sequence:
        raise ValueError("no sequences to pool.")
    frames = np.array([r["frames"] for r in per_sequence], np.float64)
    out = {
        "rmse": float(np.sqrt(sum(r["sum_sq"] for r in per_sequence) / sum(r["count"] for r in per_sequence))),
        "frames": int(frames.sum()),
        "sequences": len(per_sequence),
    }
    for k in ("hausdorff", "sted", "sted_s", "sted_t"):
        out[k] = float(np.sum(frames * np.array([r[k] for r in per_sequence])) / frames.sum())
    if all("detail" in r for r in per_sequence):
        out["detail"] = pool_details([r["detail"] for r in per_sequence])
    if all("max_penetration" in r for r in per_sequence):
        out["max_penetration"] = float(max(r["max_penetration"] for r in per_sequence))
    return out


def pooled_rmse(pairs) -> float:
    """RMSE over every vertex and frame of sequence pairs: :func:`pool`'s ``rmse`` without the Hausdorff and STED
    work.

    **Arguments:**

    - ``pairs``: ``(reference, reconstruction)`` pairs of ``(T, V, 3)`` sequences of one shape each.

    **Returns:**

    The RMSE as a float.

    **Raises:**

    ``ValueError`` for a pair of other shapes.
    """
    sq = count = 0.0
    for ref, rec in pairs:
        ref, rec = np.asarray(ref, np.float64), np.asarray(rec, np.float64)
        if ref.shape != rec.shape or ref.ndim != 3 or ref.shape[-1] != 3:
            raise ValueError(f"expected two (T, V, 3) sequences of one shape, got {ref.shape} and {rec.shape}.")
        d = ref - rec
        sq, count = sq + float(np.sum(d * d)), count + d.shape[0] * d.shape[1]
    if not count:
        raise ValueError("no sequences to pool.")
    return float(np.sqrt(sq / count))


class LinearResidual:
    """A closed-form reference: the fine cloth as the Loop-upsampled coarse frame plus a linear map of that coarse
    frame, ``U x + mu + ((x - m) / s) A B`` (per frame, no history).

    ``B`` (k, 3 Vf) are the leading principal directions of the training residuals fine - U coarse, ``A`` the
    ridge regression of their coefficients on the standardised coarse coordinates x (3 Vc). The ridge weight is
    chosen from ``lambdas`` (times the number of training frames) on validation sequences held out of the
    training set (every ``val_every``-th), then the map is refitted on all training sequences. It tells how much
    of what the fine simulation adds to the coarse one a plain linear function of the coarse frame predicts:
    the learned models should beat it.
    """

    def __init__(
        self,
        upsampler: Upsampler,
        coarse_seqs,
        fine_seqs,
        k: int = 64,
        lambdas=(1e-2, 1e-1, 1.0, 1e1, 1e2),
        val_every: int = 4,
    ):
        self.up = upsampler
        cs = [np.asarray(c, np.float64) for c in coarse_seqs]
        fs = [np.asarray(f, np.float64) for f in fine_seqs]
        if len(cs) != len(fs) or not cs:
            raise ValueError("LinearResidual needs as many fine as coarse training sequences (at least one).")
        val = [i for i in range(len(cs)) if i % val_every == val_every - 1] if len(cs) >= val_every else []
        fit = [i for i in range(len(cs)) if i not in val]
        if val:
            xs, coef = self._basis([cs[i] for i in fit], [fs[i] for i in fit], k)
            gram, rhs = xs.T @ xs, xs.T @ coef
            errs = {}
            for lam in lambdas:  # one principal basis, one ridge solve per weight
                self.a = _ridge(gram, rhs, lam * len(xs))
                errs[lam] = sum(float(np.sum((self(cs[i]) - fs[i]) ** 2)) for i in val)
            self.lam = min(errs, key=errs.get)
        else:
            self.lam = float(lambdas[len(lambdas) // 2])
        xs, coef = self._basis(cs, fs, k)
        self.a = _ridge(xs.T @ xs, xs.T @ coef, self.lam * len(xs))

    def _basis(self, cs, fs, k):
        """Set the standardisation, mean and principal directions; return (standardised x, coefficients)."""
        x = np.concatenate([c.reshape(len(c), -1) for c in cs])
        y = np.concatenate([(f - self.up(c)).reshape(len(f), -1) for c, f in zip(cs, fs)])
        self.m, self.s = x.mean(0), x.std(0) + 1e-9
        self.mu = y.mean(0)
        _, _, vt = np.linalg.svd(y - self.mu, full_matrices=False)
        self.b = vt[:k]
        return (x - self.m) / self.s, (y - self.mu) @ self.b.T

    def __call__(self, coarse: np.ndarray) -> np.ndarray:
        """(T, Vc, 3) coarse frames -> (T, Vf, 3) fine frames."""
        c = np.asarray(coarse, np.float64)
        r = ((c.reshape(len(c), -1) - self.m) / self.s) @ self.a @ self.b + self.mu
        return (self.up(c).astype(np.float64) + r.reshape(len(c), -1, 3)).astype(np.float32)


def _ridge(gram: np.ndarray, rhs: np.ndarray, weight: float) -> np.ndarray:
    """Ridge solution (X^T X + weight I)^-1 X^T Y from the Gram matrix and X^T Y."""
    return np.linalg.solve(gram + weight * np.eye(len(gram)), rhs)
