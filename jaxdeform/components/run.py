"""Runs of the seed-000 methods: train on a split of a mesh folder, evaluate on the unseen shapes, reload.

A run folder holds everything needed to evaluate, show or edit it later:

    run.json     method, model and training configuration, data folder, split (train / test indices),
                 timing (compile and run seconds), final loss terms
    mesh.npz     reference shape (shape 0 of the data: the ACAP rest shape), faces, feature Scaler, and the
                 per-vertex rotation reference the features' 2 pi branches are aligned to (ACAP methods)
    params/      orbax checkpoints of the autoencoder methods (multiscale, tan); the newest is the result
    history.npy  loss per epoch (autoencoder methods)
    codes.npz    latent codes of the training shapes (per level; "weights" of the linear baselines)
    model/       orbax checkpoint of the LinearModel of the linear baselines (pca, pca-xyz, splocs)

Methods: ``multiscale`` (seed 000), ``tan`` (Tan et al. 2018: one level, 50 components, clipped-linear
sparsity mask 0.2-0.4, loss weights 1 / 0.5 / 0.5 as in their public code, 2000 full-batch epochs), ``pca``
(50 components on ACAP features), ``pca-xyz`` (50 on coordinates), ``splocs`` (Neumann et al. 2013 on coordinates). The split follows Sec. 5.1: every 10th shape
trains for sequences (``split="every10"``, shapes 0, 10, 20, ...), a fixed random half for pose sets
(``split="half"``, seeded); ``split="all"`` trains on every shape and evaluates the whole set as "test".

Data is refused before any work (one sentence) when it holds fewer than 2 shapes, mixes connectivities, has an
edge of zero length in any shape or a zero-area face in the rest shape; a run.json that is not a run record is
refused by :func:`load`.

The generalization protocol (:func:`evaluate`): autoencoders encode the ACAP features of a shape, decode
them and reconstruct positions by the ACAP least squares; linear baselines project and decode. Reported per
set: Erms (unit-ball normalization, :func:`jaxdeform.metrics.erms`; also under the other two readings of
:data:`jaxdeform.metrics.NORMALIZATIONS`, the data set's shape 0 as the first shape), STED (spatial part, the shapes of a
set are not one continuous sequence; :func:`jaxdeform.metrics.sted`) and the largest relative squared
error of the features (eq. 8; ACAP-feature methods only).

Features of the ACAP methods are consistent across shapes, not only within each: each shape's consistency
solve fixes its own gauge, so a region that turns by nearly pi may land on another 2 pi branch in one shape than
in the next (horse-gallop's lower legs). Every shape's rotation vectors are put on the branch nearest the
training shapes' mean (:func:`jaxdeform.acap.turn_reference`, stored in mesh.npz, applied by
:func:`scaled_features`). Runs written before this have no reference and keep per-shape branches.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdeform import acap, metrics, runs
from jaxdeform.components import baselines, model, train
from jaxdeform.errors import DegenerateMeshError, JaxDeformError
from jaxdeform.mesh import geodesic
from jaxdeform.mesh.fingerprint import fingerprint
from jaxdeform.mesh.geometry import zero_area_faces
from jaxdeform.mesh.io import atomic_path, check_same_connectivity, load_sequence, read_npz_arrays
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import rings_from_topology

METHODS = ("multiscale", "tan", "pca", "pca-xyz", "splocs")
# Bounds of the feature scaler of the ACAP methods: these quantiles of the training features, outliers clipped
# (acap.Scaler). horse-gallop's S entries reach 13 on a few one-rings while 99.8 % lie in [-0.8, 2.8]; with the
# official min/max the decoders' tanh range spends most of itself on those few. 1e-3 costs 2.1 Erms in the
# features -> positions round trip of the unseen horse shapes (0.67 unclipped) and lowers the multiscale
# model's test Erms from 18.1 to 15.0 (2,000 epochs; 1e-4: 15.7); 0 restores the official bounds.
SCALE_QUANTILE = 1e-3
AUTOENCODERS = ("multiscale", "tan")
ACAP_METHODS = ("multiscale", "tan", "pca")  # the methods that learn from ACAP features
SPLITS = ("every10", "half", "all")


#: the run-folder API's name of this method (:mod:`jaxdeform.runs`)
KIND = "components"


class RunError(JaxDeformError):
    """A run folder is missing, incomplete or does not match the data it is used with."""


# ------------------------------------------------------------------------------------- named configs


#: Kz of the run default: AE0 with 2 components, 5 per second-level block. With the paper's Kz = (10, 5) the first
#: level alone reproduces the few training shapes of a sequence (5 on horse-gallop, 4 on samba), leaves the second
#: level no residual to learn from, and redundant-component removal keeps 0-1 of its 50 components; with 2 the
#: second level carries the detail (docs/seed000-components.md, "How many first-level components").
DEFAULT_KZ = (2, 5)
#: Epochs of the run default: with Kz = DEFAULT_KZ the unseen shapes' error is lowest after 1,000-2,000 epochs and
#: grows past 5,000 (the two-code first level extrapolates ever further); the paper's 10,000 stay with paper-kz.
DEFAULT_EPOCHS = 2000


def _default_training(**kw) -> train.TrainConfig:
    return train.TrainConfig(**{"epochs": DEFAULT_EPOCHS, **kw})


def _multiscale(**kw) -> model.Config:
    return model.Config(**{"kz": DEFAULT_KZ, **kw})


def _tan(**kw) -> model.Config:
    """Tan et al. (2018) as in their public code (train.py defaults): one level, clipped-linear mask 0.2-0.4,
    loss = L_recon + 0.5 Omega(C) + 0.5 V(Z)."""
    return model.Config(d=(0.4,), mask="linear", lambda_recon=1.0, lambda_sparse=0.5, lambda_latent=0.5, **kw)


#: Named configurations per method: (model config, training config). "test" configs run in seconds.
METHOD_CONFIGS: dict[str, dict[str, tuple[model.Config | None, train.TrainConfig]]] = {
    "multiscale": {
        "default": (_multiscale(), _default_training()),
        "no-attention": (_multiscale(attention=False), _default_training()),
        "separate": (_multiscale(), _default_training(joint=False)),
        "no-attention-separate": (_multiscale(attention=False), _default_training(joint=False)),
        "levels1": (_multiscale(kz=DEFAULT_KZ[:1], d=(0.4,)), _default_training()),
        "levels3": (_multiscale(kz=(*DEFAULT_KZ, 2), d=(0.4, 0.2, 0.1)), _default_training()),
        # the paper's Kz = (10, 5) (Sec. 4.3) and ~10,000 epochs, and its first level alone
        "paper-kz": (_multiscale(kz=(10, 5)), train.TrainConfig()),
        "paper-kz-levels1": (_multiscale(kz=(10,), d=(0.4,)), train.TrainConfig()),
        # tanh on the latent codes as well (the paper's "all the layers use tanh" read literally). On horse-gallop
        # AE0's codes saturate and it outputs a near-constant shape; the second level carries the deformation,
        # at a slightly higher test Erms and a lower STED than the default (README).
        "latent-tanh": (_multiscale(latent="tanh"), _default_training()),
        # L_recon averaged over the 9 V feature entries too (Sec. 4.1's "MSE" read literally; model.Config.recon)
        "mse": (_multiscale(recon="mean"), _default_training()),
        "test": (_multiscale(kz=(3, 2)), train.TrainConfig(epochs=30)),
        "test-no-attention": (_multiscale(kz=(3, 2), attention=False), train.TrainConfig(epochs=30)),
        "test-separate": (_multiscale(kz=(3, 2)), train.TrainConfig(epochs=30, joint=False)),
        "test-no-attention-separate": (
            _multiscale(kz=(3, 2), attention=False),
            train.TrainConfig(epochs=30, joint=False),
        ),
        "test-levels1": (_multiscale(kz=(3,), d=(0.4,)), train.TrainConfig(epochs=30)),
        "test-levels3": (_multiscale(kz=(3, 2, 2), d=(0.4, 0.2, 0.1)), train.TrainConfig(epochs=30)),
        "test-paper-kz": (_multiscale(kz=(4, 2)), train.TrainConfig(epochs=30)),
        "test-paper-kz-levels1": (_multiscale(kz=(4,), d=(0.4,)), train.TrainConfig(epochs=30)),
        "test-latent-tanh": (_multiscale(kz=(3, 2), latent="tanh"), train.TrainConfig(epochs=30)),
        "test-mse": (_multiscale(kz=(3, 2), recon="mean"), train.TrainConfig(epochs=30)),
    },
    "tan": {
        # their public code's 2,000 epochs; the decay rate these figures were measured with (0.96 per 1,000)
        "default": (_tan(kz=(50,)), train.TrainConfig(epochs=2000, decay_rate=0.96)),
        "test": (_tan(kz=(4,)), train.TrainConfig(epochs=30, decay_rate=0.96)),
    },
    "pca": {"default": (None, train.TrainConfig()), "test": (None, train.TrainConfig())},
    "pca-xyz": {"default": (None, train.TrainConfig()), "test": (None, train.TrainConfig())},
    "splocs": {"default": (None, train.TrainConfig()), "test": (None, train.TrainConfig())},
}

N_LINEAR = {"default": 50, "test": 8}
#: the run-folder API's named configurations: those of the default method, multiscale (other methods: ``method=``)
CONFIGS = METHOD_CONFIGS["multiscale"]


def resolve_config(method: str, name: str, epochs: int | None = None, seed: int | None = None):
    """The model and training configuration of a named configuration of ``method``.

    **Arguments:**

    - ``method``: one of the methods (module docstring).
    - ``name``: one of ``method``'s named configurations.
    - ``epochs``, ``seed``: override the configuration's epochs and seed (None: keep them).

    **Returns:**

    ``(config, train_config)``; ``config`` is None for the linear baselines.

    **Raises:**

    ``ValueError`` for an unknown method or configuration, or ``epochs < 1``.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}.")
    if name not in METHOD_CONFIGS[method]:
        raise ValueError(
            f"method {method} has no config {name!r}; expected one of {', '.join(METHOD_CONFIGS[method])}."
        )
    cfg, tc = METHOD_CONFIGS[method][name]
    if epochs is not None:
        if epochs < 1:
            raise ValueError(f"--epochs must be at least 1, got {epochs}.")
        tc = dataclasses.replace(tc, epochs=epochs)
    if seed is not None:
        tc = dataclasses.replace(tc, seed=seed)
    return cfg, tc


def stale_reason(
    record: dict, method: str, name: str, epochs: int | None = None, split: str | None = None
) -> str | None:
    """Why a stored run is not what ``resolve_config(method, name, epochs)`` and this code's feature preparation
    would train now.

    The epoch count is compared only when ``epochs`` is given (a run trained with ``--epochs N`` is reused by a
    later call without it), the split only when ``split`` is given. A record that lacks a field (of the model or
    the training configuration) is compared with that field's default. Linear baselines have no training
    configuration to compare.

    **Arguments:**

    - ``record``: the stored run's run.json.
    - ``method``, ``name``, ``epochs``: as :func:`resolve_config`'s.
    - ``split``: the split mode to compare (default None: not compared).

    **Returns:**

    The reason as a short sentence fragment, or None when the run matches.
    """
    if record.get("method") != method:
        return f"it is a {record.get('method')} run, not {method}"
    if split is not None and record.get("split", {}).get("mode") != split:
        return f"it trained on the {record.get('split', {}).get('mode')} split, not {split}"
    cfg, tc = resolve_config(method, name, epochs)
    if method in ACAP_METHODS:
        if record.get("feature_turns") != "aligned":
            return "its features keep per-shape rotation branches"
        if record.get("feature_scale_quantile", 0.0) != SCALE_QUANTILE:
            return f"its scaler quantile is {record.get('feature_scale_quantile', 0.0)}, not {SCALE_QUANTILE}"
    if method not in AUTOENCODERS:
        return None
    stored = record.get("config")
    if isinstance(stored, dict) and cfg is not None:  # fields added after the run was written: their defaults
        stored = {**_json_config(type(cfg)()), **stored}
    if stored != _json_config(cfg):
        return "its model configuration differs"
    stored = dataclasses.asdict(train.TrainConfig(**record.get("train_config", {})))
    for key, value in dataclasses.asdict(tc).items():
        if stored[key] != value and (key != "epochs" or epochs is not None):
            return f"its {key} is {stored[key]}, not {value}"
    return None


# ------------------------------------------------------------------------------------------- data


def split_indices(n: int, mode: str = "every10", seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Train and test shape indices.

    **Arguments:**

    - ``n``: the number of shapes (at least 2).
    - ``mode``: ``"every10"``: every 10th shape (0, 10, ...) is a test shape; ``"half"``: a seeded random half;
        ``"all"``: every shape trains and the "test" set is the whole data set again (the representation error of
        Table 5, eq. 8, read as the maximum "in the whole dataset").
    - ``seed``: the seed of ``"half"``.

    **Returns:**

    ``(train, test)`` int64 index arrays.

    **Raises:**

    ``ValueError`` for ``n < 2`` or an unknown mode.
    """
    if n < 2:
        raise ValueError(f"a components run needs at least 2 shapes, got {n}.")
    if mode == "every10":
        train_idx = np.arange(0, n, 10)
    elif mode == "all":
        every = np.arange(n, dtype=np.int64)
        return every, every.copy()
    elif mode == "half":
        perm = np.random.default_rng(seed).permutation(n)
        train_idx = np.sort(perm[: (n + 1) // 2])
    else:
        raise ValueError(f"unknown split {mode!r}; expected one of {', '.join(SPLITS)}.")
    test_idx = np.setdiff1d(np.arange(n), train_idx)
    if test_idx.size == 0:  # 2..?? shapes with every10: keep one unseen shape
        train_idx, test_idx = train_idx[:-1] if train_idx.size > 1 else train_idx, test_idx
    return train_idx.astype(np.int64), test_idx.astype(np.int64)


def load_data(data) -> tuple[np.ndarray, np.ndarray]:
    """Shapes and faces of a folder or file list.

    **Arguments:**

    - ``data``: a folder or a list of mesh files of one connectivity.

    **Returns:**

    ``(vertices (N, V, 3), faces (F, 3))``, N >= 2, checked by :func:`check_nondegenerate`.

    **Raises:**

    ``ValueError`` for fewer than 2 shapes; :func:`check_nondegenerate`'s errors; the mesh reader's errors.
    """
    vertices, faces = load_sequence(data)
    if vertices.shape[0] < 2:
        raise ValueError(f"a components run needs at least 2 shapes; {data} holds {vertices.shape[0]}.")
    check_nondegenerate(vertices, faces, str(data))
    return vertices, faces


def check_nondegenerate(vertices: np.ndarray, faces: np.ndarray, where: str) -> None:
    """Refuse coincident edge ends in any shape and zero-area faces in the rest shape.

    Erms and STED divide by edge lengths; the rest shape (shape 0) gives the geodesic distances and cotangent
    weights.

    **Arguments:**

    - ``vertices``: shapes ``(N, V, 3)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``where``: the start of the error sentence.

    **Returns:**

    Nothing.

    **Raises:**

    ``DegenerateMeshError``, one sentence naming the first offending edge or face.
    """
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lengths = np.linalg.norm(vertices[:, edges[:, 0]] - vertices[:, edges[:, 1]], axis=-1)  # (N, 3F)
    if np.any(lengths <= 0):
        k, e = np.argwhere(lengths <= 0)[0]
        raise DegenerateMeshError(
            f"{where}: shape {k} has a zero-length edge (vertices {edges[e, 0]} and "
            f"{edges[e, 1]} coincide); a components run needs every edge of positive length."
        )
    bad = zero_area_faces(vertices[0], faces)
    if bad.size:
        raise DegenerateMeshError(
            f"{where}: the rest shape (shape 0) has {bad.size} zero-area face(s), the first "
            f"face {bad[0]}; its geodesic distances need a mesh without them."
        )


def fit_feature_transform(
    train_features: np.ndarray, scale_quantile: float = SCALE_QUANTILE, align: bool = True
) -> tuple[np.ndarray | None, acap.Scaler]:
    """What the ACAP methods fit on the training shapes' features before learning.

    Apply both with :func:`apply_feature_transform`.

    **Arguments:**

    - ``train_features``: ACAP features ``(N, V, 9)``.
    - ``scale_quantile``: the scaler's quantile.
    - ``align``: align the 2 pi rotation branches to a common reference (False: per-shape branches).

    **Returns:**

    ``(turns, scaler)``: the rotation reference ``(V, 3)`` (None with ``align=False``) and the feature scaler, fitted
    on the aligned features.
    """
    dtype = np.asarray(train_features).dtype
    turns = np.asarray(acap.turn_reference(train_features), dtype) if align else None
    aligned = train_features if turns is None else np.asarray(acap.align_turns(train_features, turns), dtype)
    return turns, acap.Scaler.fit(aligned, scale_quantile)


def apply_feature_transform(
    features: np.ndarray, turns: np.ndarray | None, scaler: acap.Scaler, dtype=None
) -> np.ndarray:
    """Features as the ACAP methods see them: branches aligned to ``turns`` (when given), then scaled.

    **Arguments:**

    - ``features``: ACAP features ``(N, V, 9)``.
    - ``turns``: the rotation reference, or None.
    - ``scaler``: the feature scaler.
    - ``dtype``: the result's dtype (default None: that of ``features``).

    **Returns:**

    Scaled features ``(N, V, 9)``.
    """
    dtype = np.asarray(features).dtype if dtype is None else np.dtype(dtype)
    feats = np.asarray(features, dtype)
    if turns is not None:
        feats = np.asarray(acap.align_turns(feats, turns), dtype)
    return np.asarray(scaler.transform(feats), dtype)


def normalized_geodesics(rest: np.ndarray, faces: np.ndarray, dtype=np.float32) -> np.ndarray:
    """Normalized geodesic distances on the reference shape (all pairs: exact up to 447 vertices, heat method
    above; :data:`jaxdeform.mesh.geodesic.AUTO_EXACT_MAX_WORK`).

    **Arguments:**

    - ``rest``: the reference shape ``(V, 3)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``dtype``: the result's dtype.

    **Returns:**

    ``(V, V)`` distances.
    """
    return geodesic.geodesic_distances(rest, faces, np.arange(rest.shape[0])).astype(dtype)


# ------------------------------------------------------------------------------------------- train


def _json_config(cfg) -> dict | None:
    return (
        None
        if cfg is None
        else {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()}
    )


def _model_config(d: dict) -> model.Config:
    return model.Config(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def _fit_autoencoder(
    out, record, method, config, x, rest, faces, dist, cfg, tc, train_idx, progress, log, resume=False
) -> dict:
    """Train the autoencoder ``method`` on the scaled ACAP features ``x`` (checkpoints under out/params; with
    ``resume``, continued from the newest one there).

    Writes out/history.npy and adds the training timings, ``final_terms`` and ``final_loss`` to ``record``
    (in that order). Returns the training codes, ``{"level<i>": latents}``.
    """
    rings = rings_from_topology(build_topology(faces, rest.shape[0]))
    timing: dict = {}
    log(
        f"training {method} ({config}) on {len(train_idx)} shapes x {rest.shape[0]} vertices, "
        f"{tc.epochs} epochs{'' if tc.joint else ' per level'}"
    )
    trained, history = train.train(
        x,
        rings,
        dist,
        cfg,
        tc,
        checkpoint_dir=out / "params",
        checkpoint_every=max(tc.epochs // 10, 1),
        resume=resume,
        progress=progress,
        timing=timing,
    )
    record["timing"].update(timing)
    np.save(out / "history.npy", history)
    final = trained(jnp.asarray(x), rings, jnp.asarray(dist))
    record["final_terms"] = jax.tree_util.tree_map(float, final.terms)
    codes = {f"level{i}": np.asarray(z) for i, z in enumerate(final.latents)}
    record["final_loss"] = float(history[-1])
    return codes


def _fit_linear(out, record, method, config, x, vertices, train_idx, rest, faces) -> dict:
    """Fit the linear baseline ``method`` ("pca" on the ACAP features ``x``; "pca-xyz" or "splocs" on the
    training positions) with ``N_LINEAR[config]`` components and save it as out/model (a checkpoint folder).

    Adds ``fit_s`` to ``record["timing"]``. Returns the training codes, ``{"weights": (n, k)}``.
    """
    t1 = time.perf_counter()
    k = N_LINEAR[config]
    if method == "pca":
        lin = baselines.fit_pca(x, k, domain="acap")
    elif method == "pca-xyz":
        lin = baselines.fit_pca(vertices[train_idx], k, domain="xyz")
    else:
        rows = lambda idx: geodesic.geodesic_distances(rest, faces, idx, normalize=False)  # noqa: E731
        diameter = _diameter(rest, faces)
        lin = baselines.fit_splocs(vertices[train_idx], lambda idx: rows(idx) / diameter, k)
    baselines.save(lin, out / "model")
    train_data = x if method == "pca" else vertices[train_idx]
    codes = {"weights": np.asarray(baselines.project(lin, jnp.asarray(train_data)))}
    record["timing"]["fit_s"] = round(time.perf_counter() - t1, 3)
    return codes


def _write_run(out, record, rest, faces, scaler, turns, codes) -> None:
    """Write out/mesh.npz (rest, faces and, for the ACAP methods, the scaler and turn reference),
    out/codes.npz and out/run.json, each atomically, in that order."""
    arrays = {"rest": rest, "faces": faces}
    if scaler is not None:
        arrays["scaler"] = scaler.to_array()
        arrays["turn_reference"] = turns
    with atomic_path(out / "mesh.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    with atomic_path(out / "codes.npz") as tmp:  # training codes: the magnitudes components are shown at
        with open(tmp, "wb") as fh:
            np.savez(fh, **codes)
    with atomic_path(out / "run.json") as tmp:
        Path(tmp).write_text(json.dumps(record, indent=2))


def fit(
    data,
    config: str = "default",
    out: str | Path | None = None,
    *,
    method: str = "multiscale",
    epochs: int | None = None,
    seed: int | None = None,
    split: str = "every10",
    split_seed: int = 0,
    progress: bool = True,
    scale_quantile: float = SCALE_QUANTILE,
    dtype=np.float32,
    log: Callable[[str], None] = print,
    loaded: tuple[np.ndarray, np.ndarray] | None = None,
    resume: bool = False,
) -> Run:
    """Train ``method`` on the training split of ``data`` and write the run folder ``out``.

    The folder is built in :func:`partial_folder` beside ``out`` and renamed at the end (replacing ``out``), so
    a failed fit leaves no half-written run. An autoencoder's training interrupted by Ctrl-C or a signal after its
    first checkpoint keeps the partial folder; ``resume=True`` continues from its newest checkpoint (the same
    final parameters and loss history as an uninterrupted fit).

    **Arguments:**

    - ``data``: the data folder (shapes and faces, as :func:`load_data` reads it).
    - ``config``: the named configuration of ``method`` (default ``"default"``; :data:`METHOD_CONFIGS`).
    - ``out``: the run folder to write (required: the run's checkpoints and codes live there).
    - ``method``: one of the module docstring's methods (default ``"multiscale"``).
    - ``epochs``, ``seed``: override the configuration's number of epochs and seed (None: keep them).
    - ``split``, ``split_seed``: the train/test split (:func:`split_indices`; default every 10th shape is a test shape).
    - ``progress``: show a progress bar while training.
    - ``scale_quantile``: the quantile of the feature scaling.
    - ``dtype``: the dtype of the features and the model (default float32).
    - ``log``: receives the progress lines (what is trained, on how many shapes and vertices).
    - ``loaded``: ``load_data(data)``'s result where the caller has it already (the CLI checks the data first).
    - ``resume``: continue the interrupted fit of the same settings kept in :func:`partial_folder` (a fresh fit
      when there is none). Without it, a partial folder left by an earlier fit is discarded.

    **Returns:**

    The :class:`Run`, read back from ``out``.

    **Raises:**

    ``ValueError`` for an unknown method or configuration, or no ``out``; :class:`RunError` and the loaders'
    one-sentence errors for bad data, and for ``resume`` with a partial fit of other settings.
    """
    if out is None:
        raise ValueError("a components run needs a folder to write (out).")
    out = Path(out)
    args = (data, method, config, epochs, seed, split, split_seed, progress, scale_quantile, dtype)
    settings = {  # what identifies the fit: a resumed one must match all of it
        "data": str(data),
        "method": method,
        "config": config,
        "epochs": epochs,
        "seed": seed,
        "split": split,
        "split_seed": split_seed,
        "scale_quantile": scale_quantile,
        "dtype": np.dtype(dtype).name,
    }
    with runs.resumable(out, settings, resume, log) as (tmp, resuming):
        _fit_into(tmp, *args, log, loaded, resuming)
    return Run.load(out)


partial_folder = runs.partial_folder  # where fit builds the run folder (kept when a training is interrupted)


def _fit_into(
    out: Path,
    data,
    method,
    config,
    epochs,
    seed,
    split,
    split_seed,
    progress,
    scale_quantile,
    dtype,
    log,
    loaded,
    resume=False,
) -> dict:
    """:func:`fit`'s work, written into the folder ``out``; returns the record."""
    out = Path(out)
    cfg, tc = resolve_config(method, config, epochs, seed)
    vertices, faces = load_data(data) if loaded is None else loaded
    train_idx, test_idx = split_indices(vertices.shape[0], split, split_seed)
    if train_idx.size < 2:
        raise RunError(
            f"the training split ({split}) of the {vertices.shape[0]} shapes of {data} holds {train_idx.size}; "
            "fitting needs at least 2: give more shapes or another split (half, all)."
        )
    rest = vertices[0]
    record = {
        "kind": KIND,
        "method": method,
        "config_name": config,
        "config": _json_config(cfg),
        "train_config": _json_config(tc),
        "data": str(data),
        "split": {"mode": split, "seed": split_seed, "train": train_idx.tolist(), "test": test_idx.tolist()},
        "n_shapes": int(vertices.shape[0]),
        "n_vertices": int(vertices.shape[1]),
        "dtype": np.dtype(dtype).name,
        "shape_sizes": shape_sizes(vertices),  # with the rest shape and faces (mesh.npz): what data checks compare
        "fingerprint": fingerprint(vertices, faces),
    }
    scaler = turns = x = dist = None
    t0 = time.perf_counter()
    record["timing"] = {}
    # The autoencoders' geodesics (libigl's C++) run on a thread beside the features (mostly
    # XLA compiling the ACAP encoder): overlapped, the two take about 60 % of their time one after the other.
    with ThreadPoolExecutor(max_workers=1) as pool:
        geo = pool.submit(_timed_geodesics, rest, faces, dtype) if method in AUTOENCODERS else None
        if method in ACAP_METHODS:
            feats = np.asarray(acap.encode(rest, faces, vertices[train_idx]), dtype)
            turns, scaler = fit_feature_transform(feats, scale_quantile)
            record["feature_turns"] = "aligned"
            record["feature_scale_quantile"] = scale_quantile
            x = apply_feature_transform(feats, turns, scaler, dtype)
            record["timing"]["features_s"] = round(time.perf_counter() - t0, 3)
        if geo is not None:
            dist, record["timing"]["geodesics_s"] = geo.result()
    if method in AUTOENCODERS:
        codes = _fit_autoencoder(
            out, record, method, config, x, rest, faces, dist, cfg, tc, train_idx, progress, log, resume
        )
    else:
        codes = _fit_linear(out, record, method, config, x, vertices, train_idx, rest, faces)
    record["timing"]["total_s"] = round(time.perf_counter() - t0, 3)
    _write_run(out, record, rest, faces, scaler, turns, codes)
    return record


def _timed_geodesics(rest: np.ndarray, faces: np.ndarray, dtype) -> tuple[np.ndarray, float]:
    """normalized_geodesics and its own seconds (it runs beside the features: ``geodesics_s`` overlaps
    ``features_s``)."""
    t = time.perf_counter()
    dist = normalized_geodesics(rest, faces, dtype)
    return dist, round(time.perf_counter() - t, 3)


def _diameter(rest: np.ndarray, faces: np.ndarray) -> float:
    """Largest geodesic distance, estimated by three furthest-point passes from vertex 0."""
    src, best = 0, 0.0
    for _ in range(3):
        d = geodesic.geodesic_distances(rest, faces, [src], normalize=False)[0]
        d = np.where(np.isfinite(d), d, -1.0)
        src, best = int(np.argmax(d)), max(best, float(d.max()))
    return best


# ------------------------------------------------------------------------------------------- load


@dataclasses.dataclass
class Run:
    """A loaded run: its record, reference mesh, scaler and trained model (a :class:`model.Model` for the
    autoencoders, a LinearModel for the linear baselines; the other None)."""

    path: Path
    record: dict
    rest: np.ndarray
    faces: np.ndarray
    scaler: acap.Scaler | None
    config: model.Config | None
    model: model.Model | None
    linear: baselines.LinearModel | None
    turns: np.ndarray | None = (
        None  # (V, 3) rotation reference of the features' branches (None: a run written without one)
    )

    @classmethod
    def load(cls, path) -> Run:
        """Read a components run folder (:func:`load`).

        **Arguments:**

        - ``path``: a folder written by :func:`fit`.

        **Returns:**

        The :class:`Run`.

        **Raises:**

        :class:`RunError` (one sentence) for a folder that is not a components run.
        """
        return load(path)

    @property
    def method(self) -> str:
        return self.record["method"]

    @property
    def train_idx(self) -> np.ndarray:
        return np.asarray(self.record["split"]["train"], np.int64)

    @property
    def test_idx(self) -> np.ndarray:
        return np.asarray(self.record["split"]["test"], np.int64)


#: the files and folders of a run (the module docstring); outputs written into a run folder must not take these names
RUN_FILES = ("run.json", "mesh.npz", "params", "history.npy", "codes.npz", "model")
#: what every run.json holds (load and evaluate read these)
RECORD_KEYS = ("method", "n_shapes", "n_vertices", "split", "data")


def read_record(path: Path) -> dict:
    """run.json of the run folder ``path``, checked to be a components run's record.

    **Arguments:**

    - ``path``: the run folder.

    **Returns:**

    The record (a dict holding every key of ``RECORD_KEYS``, with a known method).

    **Raises:**

    ``RunError`` (one sentence) if run.json is not JSON, lacks a key or names an unknown method.
    """
    try:
        record = json.loads((path / "run.json").read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunError(
            f"{path / 'run.json'} is not a readable run record ({exc.__class__.__name__}: it is "
            "empty, truncated or not JSON)."
        ) from None
    if not isinstance(record, dict) or any(k not in record for k in RECORD_KEYS):
        missing = [k for k in RECORD_KEYS if not isinstance(record, dict) or k not in record]
        raise RunError(f"{path / 'run.json'} is not a components run record (it lacks {', '.join(missing)}).")
    if record.get("kind", KIND) != KIND:
        raise RunError(f"{path} is a {record['kind']} run, not a components run.")
    if record["method"] not in METHOD_CONFIGS:
        raise RunError(f"{path / 'run.json'} names an unknown method {record['method']!r}.")
    _check_record(path / "run.json", record)
    return record


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _check_record(where: Path, record: dict) -> None:
    """The types and ranges of a run record's fields (``where`` names run.json in the messages).

    **Raises:** ``RunError``, one sentence naming the first field that is wrong.
    """
    types = {"method": ("string",), "data": ("string",), "shape_sizes": ("list",), "fingerprint": ("object",)}
    try:
        runs.check_fields(where, record, types, optional=("shape_sizes", "fingerprint"))
    except runs.RunFolderError as exc:
        raise RunError(str(exc)) from None
    n = record["n_shapes"]
    if not _is_int(n) or n < 1:
        raise RunError(f"{where}: n_shapes must be a positive integer, got {n!r}.")
    if not _is_int(record["n_vertices"]) or record["n_vertices"] < 3:
        raise RunError(f"{where}: n_vertices must be an integer of at least 3, got {record['n_vertices']!r}.")
    split = record["split"]
    if not isinstance(split, dict):
        raise RunError(f"{where}: split must be an object with train and test index lists.")
    for part in ("train", "test"):
        idx = split.get(part)
        if not isinstance(idx, list) or not all(_is_int(i) for i in idx) or (part == "train" and not idx):
            raise RunError(
                f"{where}: split.{part} must be a list of shape indices{' (not empty)' * (part == 'train')}."
            )
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise RunError(
                f"{where}: split.{part} holds {bad[0]}, not a shape index (the run has {n} shapes: 0..{n - 1})."
            )
    if record.get("dtype", "float32") not in ("float32", "float64"):
        raise RunError(f"{where}: dtype must be float32 or float64, got {record['dtype']!r}.")
    if record["method"] in AUTOENCODERS:
        cfg = record.get("config")
        fields = {f.name for f in dataclasses.fields(model.Config)}
        if not isinstance(cfg, dict) or not set(cfg) <= fields:
            raise RunError(
                f"{where}: the {record['method']} method needs its model configuration (config: an object with "
                f"the fields of jaxdeform.components.model.Config), got {type(cfg).__name__}."
            )


def load(path) -> Run:
    """Load the components run in the folder ``path``.

    **Arguments:**

    - ``path``: a run folder written by :func:`fit`.

    **Returns:**

    The :class:`Run`: record, rest shape, faces, feature scaler, and the model (autoencoder parameters and
    configuration, or the linear model).

    **Raises:**

    ``RunError`` if run.json, mesh.npz or (linear baselines) model is missing or the record is not a components
    run's.
    """
    path = Path(path)
    missing = [name for name in ("run.json", "mesh.npz") if not (path / name).is_file()]
    if missing:
        raise RunError(
            f"{path} is not a components run ({' and '.join(missing)} {'is' if len(missing) == 1 else 'are'} missing)."
        )
    record = read_record(path)
    arrays = read_npz_arrays(path / "mesh.npz")
    if "rest" not in arrays or "faces" not in arrays:
        raise RunError(f"{path / 'mesh.npz'}: not a components run's mesh (rest and faces are needed).")
    scaler = acap.Scaler.from_array(arrays["scaler"]) if "scaler" in arrays else None
    dtype = np.dtype(record.get("dtype", "float32"))
    cfg = trained = linear = None
    if record["method"] in AUTOENCODERS:
        if not (path / "params").is_dir():
            raise RunError(f"{path}: params is missing (the {record['method']} method's trained parameters).")
        try:
            cfg = _model_config(record["config"])
        except (TypeError, ValueError) as exc:
            raise RunError(
                f"{path / 'run.json'}: config is not a valid {record['method']} configuration ({exc})."
            ) from None
        like = model.Model(record["n_vertices"], cfg, key=jax.random.PRNGKey(0), dtype=dtype)
        trained = train.load_params(path / "params", like)
    else:
        if not (path / "model").exists():
            raise RunError(f"{path}: model is missing.")
        linear = baselines.load(path / "model")
    runs.check_fingerprint(path / "run.json", record, arrays["rest"], arrays["faces"], f"{path / 'mesh.npz'}")
    turns = np.asarray(arrays["turn_reference"]) if "turn_reference" in arrays else None
    return Run(
        path, record, np.asarray(arrays["rest"]), np.asarray(arrays["faces"]), scaler, cfg, trained, linear, turns
    )


#: relative tolerance of the data check: shapes read back from another file format of the same data pass
DATA_RTOL = 1e-5


def shape_sizes(vertices: np.ndarray) -> list[float]:
    """Each shape's RMS distance from its centroid, ``(N,)`` as a list: the part of a run's data fingerprint that
    tells one set of shapes from another of the same count and connectivity."""
    v = np.asarray(vertices, np.float64)
    return np.sqrt(((v - v.mean(axis=1, keepdims=True)) ** 2).sum(-1).mean(-1)).tolist()


def _check_data(run: Run, vertices: np.ndarray, faces: np.ndarray, where: str) -> None:
    """``vertices`` and ``faces`` (read from ``where``) must be the data the run was fitted on: the same shape
    count and connectivity, shape 0 the run's reference, and (runs that stored them) the same shape sizes."""
    if vertices.shape[0] != run.record["n_shapes"]:
        raise RunError(
            f"{where} holds {vertices.shape[0]} shapes but the run was trained on a set of "
            f"{run.record['n_shapes']}; pass the same data folder."
        )
    check_same_connectivity(run.faces, faces, run.rest.shape[0], vertices.shape[1], where)
    rest = np.asarray(run.rest, np.float64)
    size = float(np.linalg.norm(np.ptp(rest, axis=0))) or 1.0
    off = float(np.abs(np.asarray(vertices[0], np.float64) - rest).max())
    if not off <= DATA_RTOL * size:
        raise RunError(
            f"{where} is not the data the run was fitted on: its shape 0 lies up to {off:.3g} from the run's "
            f"reference shape ({off / size:.3g} of its size); pass the run's own data."
        )
    kept = run.record.get("shape_sizes")
    if isinstance(kept, list) and len(kept) == vertices.shape[0]:
        got = np.asarray(shape_sizes(vertices))
        bad = np.flatnonzero(~(np.abs(got - np.asarray(kept, np.float64)) <= DATA_RTOL * np.abs(kept)))
        if bad.size:
            k = int(bad[0])
            raise RunError(
                f"{where} is not the data the run was fitted on: its shape {k} has size {got[k]:.6g} where the "
                f"run's had {kept[k]:.6g}; pass the run's own data."
            )


# ---------------------------------------------------------------------------------------- evaluate


def run_data(run: Run, data=None) -> tuple[np.ndarray, np.ndarray]:
    """Shapes and faces of ``data``, checked against the run.

    **Arguments:**

    - ``run``: the run.
    - ``data``: a data folder (default None: the folder the run was trained on).

    **Returns:**

    ``(vertices, faces)``: ``(N, V, 3)`` and ``(F, 3)``.

    **Raises:**

    ``RunError`` if the data's number of shapes or connectivity differs from the run's.
    """
    data = run.record["data"] if data is None else data
    vertices, faces = load_data(data)
    _check_data(run, vertices, faces, str(data))
    return vertices, faces


def scaled_features(run: Run, vertices: np.ndarray, dtype=None) -> jnp.ndarray:
    """The scaled ACAP features of ``vertices``, as the run's ACAP-based model sees them.

    Rotation branches are aligned to the run's reference, then the features are scaled.

    **Arguments:**

    - ``run``: an ACAP-based run.
    - ``vertices``: shapes ``(N, V, 3)``.
    - ``dtype``: the dtype of the result (default None: the run's).

    **Returns:**

    Scaled features ``(N, V, 9)``.
    """
    dtype = np.dtype(run.record.get("dtype", "float32") if dtype is None else dtype)
    feats = np.asarray(acap.encode(run.rest, run.faces, vertices), dtype)
    return jnp.asarray(apply_feature_transform(feats, run.turns, run.scaler, dtype))


def positions_from_scaled(run: Run, scaled) -> np.ndarray:
    """Positions of scaled ACAP features: unscaled, then the ACAP reconstruction.

    **Arguments:**

    - ``run``: an ACAP-based run.
    - ``scaled``: scaled features ``(N, V, 9)``.

    **Returns:**

    Positions ``(N, V, 3)`` (float64).
    """
    feats = np.asarray(run.scaler.inverse(scaled))
    return np.asarray(acap.decode(jnp.asarray(feats, jnp.float64), run.rest, run.faces))


def reconstruct(run: Run, vertices: np.ndarray) -> dict:
    """``vertices`` passed through the run's model.

    **Arguments:**

    - ``run``: the run.
    - ``vertices``: shapes ``(N, V, 3)``.

    **Returns:**

    A dict: ``"positions"`` ``(N, V, 3)``; for ACAP-based methods also ``"scaled"`` and ``"scaled_hat"``
    ``(N, V, 9)``, the scaled features and their reconstruction.
    """
    if run.method in ACAP_METHODS:
        x = scaled_features(run, vertices)
        if run.method == "pca":
            xh = baselines.reconstruct(run.linear, x)
        else:
            rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
            xh = _reconstruct_features(run.model, x, rings)
        return {"positions": positions_from_scaled(run, xh), "scaled": np.asarray(x), "scaled_hat": np.asarray(xh)}
    return {"positions": np.asarray(baselines.reconstruct(run.linear, jnp.asarray(vertices)))}


def _reconstruct_features(m, x, rings, chunk: int = 16):
    return jnp.concatenate([train.reconstruct(m, x[i : i + chunk], rings) for i in range(0, x.shape[0], chunk)])


def set_metrics(ref: np.ndarray, rec: dict, faces: np.ndarray, *, first: np.ndarray | None = None) -> dict:
    """Error metrics of one set's reconstruction.

    **Arguments:**

    - ``ref``: the reference shapes ``(N, V, 3)``.
    - ``rec``: :func:`reconstruct`'s result for ``ref``.
    - ``faces``: ``(F, 3)``.
    - ``first``: the data set's first shape ``(V, 3)`` for the ``"diameter-first-shape"`` Erms; None: ``ref[0]``.

    **Returns:**

    A dict: ``shapes``, ``erms`` (the RMS of the per-shape Erms, so the set's Erms, under the unit-radius
    normalization), ``erms_per_shape``, ``erms_by_normalization`` (the set's Erms under each of
    :data:`jaxdeform.metrics.NORMALIZATIONS`), ``sted``; with features also ``max_relative_squared_error`` and
    ``mean_relative_squared_error``.
    """
    by_norm = metrics.erms_per_shape_by_normalization(ref, rec["positions"], first=first)
    per_shape = by_norm["radius"]  # one normalization for the set; their RMS is the set's Erms
    out = {
        "shapes": int(ref.shape[0]),
        "erms": float(np.sqrt(np.mean(per_shape**2))),
        "erms_per_shape": [round(float(e), 4) for e in per_shape],
        "erms_by_normalization": {k: float(np.sqrt(np.mean(e**2))) for k, e in by_norm.items()},
        "sted": float(metrics.sted(ref, rec["positions"], faces, temporal=False)["sted"]),
    }
    if "scaled" in rec:
        rse = metrics.relative_squared_error(rec["scaled"], rec["scaled_hat"])
        out["max_relative_squared_error"] = float(rse.max())
        out["mean_relative_squared_error"] = float(rse.mean())
    return out


def evaluate(run: Run, data=None) -> dict:
    """Metrics of the run on its train and test split of ``data``.

    **Arguments:**

    - ``run``: the run.
    - ``data``: the data folder (checked against the run as in :func:`run_data`; None: the run's own).

    **Returns:**

    ``{"method", "config", "train": {...}, "test": {...}}``, each set's :func:`set_metrics` plus its ``seconds``.

    **Raises:**

    ``RunError`` if ``data`` does not match the run.
    """
    vertices, faces = run_data(run, data)
    result = {"method": run.method, "config": run.record["config_name"]}
    for name, idx in (("train", run.train_idx), ("test", run.test_idx)):
        t0 = time.perf_counter()
        rec = reconstruct(run, vertices[idx])
        result[name] = set_metrics(vertices[idx], rec, faces, first=vertices[0])
        result[name]["seconds"] = round(time.perf_counter() - t0, 3)
    return result


# -------------------------------------------------------------------------------------------- show


def components(run: Run):
    """The run's components and their meshes.

    Autoencoders: decoder outputs of one-hot codes at the training codes' extremes (Tan et al.'s rule), as
    ACAP feature differences applied to the reference. Linear baselines: each component at its largest
    training weight, added to the mean (features decoded by ACAP, or coordinates).

    **Arguments:**

    - ``run``: the run.

    **Returns:**

    ``(component_set, meshes)``: a :class:`~jaxdeform.components.extract.ComponentSet` and its meshes ``(K, V, 3)``.

    **Raises:**

    ``RunError`` if the run folder lacks codes.npz.
    """
    from jaxdeform.components import extract

    codes = read_npz_arrays(run.path / "codes.npz") if (run.path / "codes.npz").is_file() else None
    if codes is None:
        raise RunError(f"{run.path}: codes.npz is missing.")
    if run.method in AUTOENCODERS:
        rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
        latents = tuple(codes[f"level{i}"] for i in range(len(run.model.levels)))
        cs = extract.all_components(run.model, rings, latents=latents, scaler=run.scaler)
        return cs, extract.component_meshes(cs, run.rest, run.faces)
    lin = run.linear
    w = np.asarray(codes["weights"])
    peak = w[np.argmax(np.abs(w), axis=0), np.arange(w.shape[1])]  # signed largest training weight
    weight = float(lin.scale) * peak
    if lin.domain == "acap":
        cs = extract.from_arrays(
            np.asarray(lin.components), "acap", scaler=run.scaler, weight=weight, method=run.method
        )
        base = np.asarray(run.scaler.inverse(jnp.asarray(lin.mean)))
    else:
        cs = extract.from_arrays(np.asarray(lin.components), "xyz", weight=weight, method=run.method)
        base = np.asarray(lin.mean)
    return cs, extract.component_meshes(cs, run.rest, run.faces, base=base)


def show(run: Run, out: Path, up_axis: str | None = None) -> dict:
    """Write the run's component figures and their summary into ``out``.

    **Arguments:**

    - ``run``: the run.
    - ``out``: the folder to write components.png (kept components, one row per block, each mesh framed to fill
        its panel), similarity.png and components.json into.
    - ``up_axis``: the meshes' vertical, "y" or "z"; None guesses it from the reference
        (:func:`jaxdeform.mesh.render.guess_up_axis`).

    **Returns:**

    The summary written as components.json (method, number of components, number kept, the redundancy removal,
    the files written).
    """
    from jaxdeform.components import extract, figures
    from jaxdeform.mesh.render import guess_up_axis

    out = Path(out)
    cs, meshes = components(run)
    removal = extract.remove_redundant(cs)
    keep = np.asarray(removal.keep)
    if up_axis is None:
        up_axis = guess_up_axis(run.rest, run.faces)
    figures.component_set_figure(cs, meshes, run.faces, out / "components.png", removal=removal, up_axis=up_axis)
    names = [n for n, k in zip(cs.names(), keep) if k]
    sim = np.asarray(extract.similarity_matrix(cs.values[keep]))
    figures.similarity_figure(sim, out / "similarity.png", labels=names)
    info = {"method": run.method, "components": len(cs), "n_kept": int(keep.sum()), "up_axis": up_axis}
    info.update(removal.as_dict())
    info["files"] = ["components.png", "similarity.png", "components.json"]
    with atomic_path(out / "components.json") as tmp:
        Path(tmp).write_text(json.dumps(info, indent=2))
    return info


# -------------------------------------------------------------------------------------------- edit


@dataclasses.dataclass
class Editor:
    """A run as a function of one latent vector, for :mod:`jaxdeform.components.edit`.

    ``decode(w)`` gives scaled ACAP features (``space="features"``: multiscale, tan, pca) or positions
    (``"positions"``: pca-xyz, splocs); ``latent0`` is the code of the reference shape (the edit's start).
    ``stages``: for a model of several levels, the cumulative latent counts per level, so that an edit runs
    coarse to fine, one stage per level (level 0's codes, then levels 0-1, ...;
    :mod:`jaxdeform.components.edit`); None for one level. An edit's own ``stages=`` argument overrides it.
    Build the editor once per run and reuse it: the compiled editor is cached on the identity of ``decode``.
    """

    decode: Callable
    latent0: np.ndarray
    space: str
    run: Run
    stages: tuple[int, ...] | None = None

    def _acap(self):
        a = acap.cached(self.run.rest, self.run.faces)
        a.reconstructor(None)  # built on the host now, not inside the editor's trace
        return a

    def _options(self, kw: dict) -> dict:
        kw = dict(kw)
        kw.setdefault("stages", self.stages)
        if self.space == "positions":
            kw.pop("objective", None)  # coordinate models: the decoded mesh is fitted to the controls
        return kw

    def edit(self, controls, targets, **kw):
        """Edit the run's reference shape so that the ``controls`` vertices meet ``targets``.

        :func:`jaxdeform.components.edit.edit` for feature-space runs,
        :func:`~jaxdeform.components.edit.edit_positions` for coordinate runs (which ignore ``objective``), from
        ``latent0`` and with the editor's ``stages`` unless given.

        **Arguments:**

        - ``controls``: the control vertices ``(M,)``.
        - ``targets``: their targets ``(M, 3)``.
        - ``kw``: the editor's options (steps, regularization, method, ...).

        **Returns:**

        An :class:`~jaxdeform.components.edit.EditResult`.

        **Raises:**

        :class:`~jaxdeform.components.edit.EditInputError` for inconsistent arguments.
        """
        from jaxdeform.components import edit as ed

        kw = self._options(kw)
        if self.space == "features":
            return ed.edit(self.decode, self.latent0, self._acap(), self.run.scaler, controls, targets, **kw)
        return ed.edit_positions(self.decode, self.latent0, controls, targets, **kw)

    def edit_error(self, ground_truth, n_controls: int, **kw):
        """:func:`jaxdeform.components.edit.edit_error` of the run on one unseen shape.

        **Arguments:**

        - ``ground_truth``: the unseen shape ``(V, 3)``.
        - ``n_controls``: the number of control vertices (furthest point sampling on the rest shape).
        - ``kw``: the editor's options, as :meth:`edit`.

        **Returns:**

        An :class:`~jaxdeform.components.edit.EditErrorReport`.

        **Raises:**

        :class:`~jaxdeform.components.edit.EditInputError` for inconsistent arguments.
        """
        from jaxdeform.components import edit as ed

        rest_arg = self._acap() if self.space == "features" else self.run.rest
        return ed.edit_error(
            self.decode,
            self.latent0,
            rest_arg,
            self.run.scaler,
            ground_truth,
            n_controls,
            space=self.space,
            **self._options(kw),
        )


def editor(run: Run) -> Editor:
    """The run's :class:`Editor`.

    **Arguments:**

    - ``run``: the run.

    **Returns:**

    An :class:`Editor` over the run's latent codes (autoencoders) or component weights (linear baselines); it
    computes in float64 (the ACAP reconstruction's dtype), whatever the run's dtype.
    """
    dtype = np.float64
    to64 = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    if run.method in AUTOENCODERS:
        rings = rings_from_topology(build_topology(run.faces, run.rest.shape[0]))
        m = jax.tree_util.tree_map(to64, run.model)  # a float64 copy of the Module (nnx Modules are pytrees)
        x0 = scaled_features(run, run.rest[None], dtype)
        codes = m.encode(x0, rings)  # per level (n_l, 1, Kz_l)
        shapes = [z.shape for z in codes]
        sizes = [int(np.prod(s)) for s in shapes]

        def decode(w):
            parts, start = [], 0
            for s, n in zip(shapes, sizes):
                parts.append(w[start : start + n].reshape(s))
                start += n
            return m.decode_latents(tuple(parts), rings)[0]

        latent0 = np.concatenate([np.asarray(z).ravel() for z in codes])
        stages = tuple(int(x) for x in np.cumsum(sizes)) if len(sizes) > 1 else None
        return Editor(decode, latent0, "features", run, stages)
    lin = dataclasses.replace(run.linear, mean=to64(run.linear.mean), components=to64(run.linear.components))

    def decode_linear(w):
        return baselines.decode(lin, w[None])[0]

    if run.method == "pca":
        x0 = scaled_features(run, run.rest[None], dtype)
        return Editor(decode_linear, np.asarray(baselines.project(lin, x0))[0], "features", run)
    return Editor(decode_linear, np.asarray(baselines.project(lin, jnp.asarray(run.rest[None])))[0], "positions", run)


def read_controls(path) -> tuple[np.ndarray, np.ndarray]:
    """Control vertices and targets of an edit from a file.

    **Arguments:**

    - ``path``: a .json ``{"indices": [...], "targets": [[x, y, z], ...]}`` or a text file of lines ``index x y z``.

    **Returns:**

    ``(indices (M,) int, targets (M, 3))``, M >= 1.

    **Raises:**

    ``RunError`` (one sentence) for an unreadable file, non-integer indices or targets that are not ``(M, 3)``.
    """
    path = Path(path)
    try:
        if path.suffix.lower() == ".json":
            d = json.loads(path.read_text())
            raw = d["indices"]
            # JSON numbers only: true/false and strings are not vertex numbers (numpy would take true as 1)
            if not isinstance(raw, list) or any(isinstance(i, bool) or not isinstance(i, (int, float)) for i in raw):
                raise RunError(f"{path}: 'indices' must be a list of vertex numbers (integers).")
            idx, tgt = np.asarray(raw, np.float64), np.asarray(d["targets"], np.float64)
        else:
            with warnings.catch_warnings():  # an empty file: numpy warns, the size check below says why
                warnings.simplefilter("ignore")
                rows = np.loadtxt(path, ndmin=2)
            idx, tgt = rows[:, 0], rows[:, 1:]
    except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
        raise RunError(
            f"{path}: cannot read control points ({exc}); expected JSON with 'indices' and "
            f"'targets' or lines 'index x y z'."
        ) from None
    if idx.ndim != 1 or idx.size == 0 or tgt.shape != (idx.size, 3):
        raise RunError(f"{path}: expected M >= 1 control indices and an (M, 3) array of targets.")
    if not np.all(np.isfinite(idx)) or np.any(np.abs(idx) > 2**53) or not np.all(idx == np.round(idx)):
        raise RunError(f"{path}: control indices must be integers (vertex numbers).")
    return idx.astype(np.int64), tgt
