"""Seed 002 end to end: generate paired data, train a detail model, synthesise fine cloth, evaluate, time.

A RUN folder holds ``model/`` (an orbax checkpoint folder, :func:`jaxdeform.cloth.train.save_model`),
``representation.npz`` (the representation kind, rest meshes and feature scalings fitted on the training
sequences) and ``run.json`` (the dataset it was trained on, its split, the configurations and the training
record). Each is written atomically, ``run.json`` last.

Synthesis of a coarse sequence (Fig. 2): coarse frames -> representation (TS-ACAP by default, scaled) ->
autoregressive model -> fine features -> positions (ACAP least squares, placed on the coarse centroid) ->
collision refinement against the scenario's obstacles (:mod:`jaxdeform.cloth.refine`, margin = the
simulation's cloth thickness). :func:`synthesize_timed` reports the seconds per frame of each stage.
"""

from __future__ import annotations

import functools
import json
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxdeform import runs
from jaxdeform.cloth import data as cdata
from jaxdeform.cloth import evaluate as ceval
from jaxdeform.cloth import features as cfeat
from jaxdeform.cloth.refine import Refiner
from jaxdeform.errors import ConnectivityError, JaxDeformError
from jaxdeform.mesh.fingerprint import difference, fingerprint
from jaxdeform.mesh.io import atomic_path, read_npz_arrays
from jaxdeform.mesh.topology import build_topology

RUN_FORMAT = "jaxdeform-cloth-run"


# ------------------------------------------------------------------------------------------------ data


def generate(
    kind: str,
    out: str | Path,
    n_sequences: int = 10,
    n_frames: int | None = None,
    seed: int = 0,
    progress: bool = True,
    levels: int = 3,
    motions=None,
) -> dict:
    """Simulate ``n_sequences`` paired (coarse, fine) sequences of a scenario into ``out``.

    A sequence file already in ``out`` whose stored scenario record equals the one asked for is kept, not
    simulated again (an interrupted generation resumes; a dataset grows by raising ``n_sequences`` where the
    scenarios do not depend on it).

    **Arguments:**

    - ``kind``: the scenario (``"sheet"``, ``"disk"``, ``"skirt"`` or ``"pants"``, :mod:`jaxdeform.cloth.scenarios`).
    - ``out``: the dataset folder.
    - ``n_sequences``: how many sequences (at least 2: one to train on, one to test).
    - ``n_frames``: frames per sequence (default None: :func:`jaxdeform.cloth.scenarios.default_frames`).
    - ``seed``: the scenarios' seed.
    - ``progress``: show a progress bar.
    - ``levels``: Loop levels from the coarse to the fine mesh (3: the paper's sizes).
    - ``motions``: garments: the body's motions to draw from (:func:`jaxdeform.cloth.scenarios.scenario`).

    **Returns:**

    The dataset index record (dataset.json as written): frames, seed, vertex counts, the maximum obstacle
    penetrations (also relative to the mean edge length) and the median seconds per frame of both resolutions.

    **Raises:**

    ``JaxDeformError`` if ``n_sequences < 2``.
    """
    from jaxdeform.cloth import scenarios

    if n_sequences < 2:
        raise JaxDeformError("a dataset needs at least 2 sequences (one to train on, one to test).")
    out = Path(out)
    names, pen_c, pen_f, t_c, t_f, edge_c, edge_f, pen_n = [], [], [], [], [], [], [], []
    frames = n_frames or scenarios.default_frames(kind)
    for i in tqdm(range(n_sequences), desc=f"simulate {kind}", unit="seq", disable=not progress):
        sc = scenarios.scenario(kind, i, seed, frames, n_sequences, levels, motions)
        name = f"seq_{i:03d}.npz"
        pair = _stored_pair(out / name, sc.meta)
        if pair is None:
            pair = scenarios.simulate_pair(sc, progress=False)
            cdata.write_sequence(out / name, pair)
        names.append(name)
        m = pair["meta"]
        pen_c.append(m["coarse_max_penetration"])
        pen_f.append(m["fine_max_penetration"])
        pen_n.append(int(m.get("penetration_samples", 0)))  # 0: a record measured at the vertices only
        t_c.append(m["coarse_seconds_per_frame"])
        t_f.append(m["fine_seconds_per_frame"])
        edge_c.append(_mean_edge(pair["coarse_rest"], pair["coarse_faces"]))
        edge_f.append(_mean_edge(pair["fine_rest"], pair["fine_faces"]))
    ec, ef = float(np.mean(edge_c)), float(np.mean(edge_f))
    info = {
        "frames_per_sequence": frames,
        "seed": seed,
        "vertices": {"coarse": int(pair["coarse"].shape[1]), "fine": int(pair["fine"].shape[1])},
        "penetration": {
            "coarse_max_m": float(max(pen_c)),
            "fine_max_m": float(max(pen_f)),
            "coarse_mean_edge_m": ec,
            "fine_mean_edge_m": ef,
            "coarse_max_over_edge": float(max(pen_c)) / ec,
            "fine_max_over_edge": float(max(pen_f)) / ef,
            "samples_per_edge": min(pen_n),
        },
        "timing": {"coarse_seconds_per_frame": float(np.median(t_c)), "fine_seconds_per_frame": float(np.median(t_f))},
    }
    cdata.write_index(out, kind, names, **info)
    return json.loads((out / "dataset.json").read_text())


def _stored_pair(path: Path, meta: dict) -> dict | None:
    """The sequence at ``path`` as a simulate_pair-like dict if it holds the scenario ``meta``, else None."""
    if not path.is_file():
        return None
    try:
        seq, shared = cdata.read_sequence(path)
    except JaxDeformError:
        return None
    want = json.loads(json.dumps(meta, default=cdata._jsonable))
    if any(seq.meta.get(k) != v for k, v in want.items()):
        return None
    return {**shared, **seq.pins, "coarse": seq.coarse, "fine": seq.fine, "meta": seq.meta}


def holds_scenario(path: str | Path, meta: dict) -> bool:
    """Whether the sequence file at ``path`` was simulated from the scenario ``meta`` (its stored record equals it)."""
    return _stored_pair(Path(path), meta) is not None


def _mean_edge(v, f) -> float:
    from jaxdeform.mesh.topology import unique_edges

    e = unique_edges(np.asarray(f, np.int64))
    v = np.asarray(v, np.float64)
    return float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean())


# ------------------------------------------------------------------------------------------------ runs


@dataclass
class Run:
    """A trained detail model with its representation and record."""

    model: object
    rep: cfeat.Representation
    record: dict
    root: Path | None = None

    @property
    def kind(self) -> str:
        return self.model.config.kind

    @property
    def path(self) -> Path | None:
        """The run folder (None: not saved yet)."""
        return self.root

    @classmethod
    def load(cls, path) -> Run:
        """Read a cloth run folder (:func:`load_run`; its record must name kind "cloth" where it names one).

        **Arguments:**

        - ``path``: a folder written by :func:`fit` or :func:`save_run`.

        **Returns:**

        The :class:`Run`.

        **Raises:**

        ``JaxDeformError`` (one sentence) for a folder that is not a cloth run.
        """
        run = load_run(path)
        if run.record.get("kind", KIND) != KIND:
            raise JaxDeformError(f"{path} is a {run.record['kind']} run, not a cloth run.")
        return run

    @functools.cached_property
    def refiner(self) -> Refiner:
        """Collision refinement on the fine connectivity (built once per run)."""
        return Refiner(self.rep.fine_faces, self.rep.fine_rest.shape[0])


def check_training_data(ds: cdata.ClothDataset, window: int) -> None:
    if len(ds.subset("train")) < 1:
        raise JaxDeformError(f"{ds.root}: the training split is empty.")
    lengths = [s.coarse.shape[0] for s in ds.subset("train")]
    if max(lengths) < window:
        raise JaxDeformError(f"{ds.root}: no training sequence has the {window} frames of one training window.")


def train_run(
    data: str | Path | cdata.ClothDataset,
    *,
    representation: str = "ts-acap",
    model_cfg=None,
    train_cfg=None,
    progress: bool = True,
    features: tuple | None = None,
    residual: bool = False,
    checkpoint_dir=None, resume: bool = False,
) -> Run:  # fmt: skip
    """Train a detail model on the dataset's training split.

    **Arguments:**

    - ``data``: a dataset folder or a loaded :class:`~jaxdeform.cloth.data.ClothDataset`.
    - ``representation``: the feature representation (default ``"ts-acap"``).
    - ``model_cfg``: the model's configuration (default None: ``ModelConfig()``; ``in_channels`` follows ``representation``).
    - ``train_cfg``: the training configuration (default None: ``TrainConfig()``).
    - ``progress``: show progress bars.
    - ``features``: a cached ``fit_representation`` result ``(representation, scaled features)`` (default None: fit it).
    - ``residual``: the fine target is features(fine) - features(Loop(coarse)) (:mod:`jaxdeform.cloth.features`).
    - ``checkpoint_dir``, ``resume``: save the training state there every tenth of the steps, continue from it.

    **Returns:**

    The :class:`Run` (model, representation and record: dataset, split, configurations, final loss, timings,
    thickness); not yet saved (:func:`save_run`).

    **Raises:**

    ``JaxDeformError`` if the dataset cannot train a model with this window (:func:`check_training_data`).
    """
    from jaxdeform.cloth import model as cmodel
    from jaxdeform.cloth import train as ctrain

    ds = data if isinstance(data, cdata.ClothDataset) else cdata.load_dataset(data)
    mcfg = model_cfg or cmodel.ModelConfig()
    check_training_data(ds, mcfg.window)
    train_names = [s.name for s in ds.subset("train")]
    rep, scaled = features or cfeat.fit_representation(
        representation, ds, train_names, progress=progress, residual=residual
    )
    if mcfg.in_channels != rep.channels:
        mcfg = replace(mcfg, in_channels=rep.channels)
    tcfg = train_cfg or ctrain.TrainConfig()
    ct = build_topology(ds.coarse_faces, ds.coarse_rest.shape[0])
    ft = build_topology(ds.fine_faces, ds.fine_rest.shape[0])
    positions = position_target(ds, rep, train_names) if tcfg.position_weight > 0 else None
    model, hist = ctrain.train(
        mcfg,
        tcfg,
        ct,
        ft,
        [scaled[n][0] for n in train_names],
        [scaled[n][1] for n in train_names],
        progress=progress,
        positions=positions,
        upsample=rep.upsampler.matrix.toarray() if mcfg.skip else None,
        **{"checkpoint_dir": checkpoint_dir, "checkpoint_every": max(tcfg.steps // 10, 1), "resume": resume},
    )
    record = {
        "format": RUN_FORMAT,
        "kind": KIND,
        "dataset": str(Path(ds.root).resolve()),
        "scenario": ds.scenario,
        "split": ds.split,
        "representation": rep.kind,
        "residual": rep.residual,
        "model": mcfg.to_dict(),
        "train": _asdict(tcfg),
        "final_loss": float(np.mean(hist.loss[-50:])) if len(hist.loss) else None,
        "loss_curve": loss_curve(hist.loss),
        "train_seconds": float(hist.seconds),
        "compile_seconds": float(hist.compile_seconds),
        "thickness": _thickness(ds),
        "fingerprint": data_fingerprint(ds),
    }
    return Run(model, rep, record)


def data_fingerprint(ds: cdata.ClothDataset) -> dict:
    """What a cloth run records of its dataset: ``{"coarse", "fine"}`` fingerprints of the rest meshes
    (:func:`jaxdeform.mesh.fingerprint.fingerprint`) and ``"n_sequences"``."""
    coarse, fine = fingerprint(ds.coarse_rest, ds.coarse_faces), fingerprint(ds.fine_rest, ds.fine_faces)
    return {"coarse": coarse, "fine": fine, "n_sequences": len(ds.sequences)}


#: steps per point of a run's recorded loss curve
LOSS_CURVE_EVERY = 25


def loss_curve(loss, every: int = LOSS_CURVE_EVERY) -> dict:
    """The training loss as means over consecutive blocks of ``every`` steps (a trailing partial block too):
    ``{"every": every, "mean": [...]}``."""
    loss = np.asarray(loss, np.float64)
    starts = np.arange(0, len(loss), every)
    return {"every": int(every), "mean": [float(loss[i : i + every].mean()) for i in starts]}


def position_target(ds: cdata.ClothDataset, rep: cfeat.Representation, names: list[str]):
    """The fine frames, residual bases and pinned reconstruction the position term of the loss needs."""
    from jaxdeform.acap import features as acapf
    from jaxdeform.cloth import train as ctrain

    seqs = [s for s in ds.subset("train") if s.name in set(names)]
    pins = [s.pins for s in seqs]
    if not pins or any("fine_pins" not in p for p in pins):
        raise JaxDeformError(f"{ds.root}: the position term of the loss needs the scenario's pinned fine vertices.")
    idx, at = pins[0]["fine_pins"], pins[0]["fine_pin_positions"]
    if any(not (np.array_equal(p["fine_pins"], idx) and np.allclose(p["fine_pin_positions"], at)) for p in pins):
        raise JaxDeformError(f"{ds.root}: the training sequences pin different fine vertices or positions.")
    rec = None if rep.kind == "coords" else acapf.cached(rep.fine_rest, rep.fine_faces).reconstructor(idx)
    base = [rep.base(s.coarse) for s in seqs] if rep.residual else None
    return ctrain.PositionTarget.build(
        [s.fine for s in seqs],
        base,
        rep.fine_scaling.lo,
        rep.fine_scaling.hi,
        rec,
        None if rec is None else at,
        _mean_edge(rep.fine_rest, rep.fine_faces),
    )


def _asdict(cfg) -> dict:
    import dataclasses

    return dataclasses.asdict(cfg)


def _thickness(ds: cdata.ClothDataset) -> float:
    params = ds.sequences[0].meta.get("params", {})
    return float(params.get("thickness", 0.005))


#: the files of a run folder (what :func:`load_run` reads)
RUN_FILES = ("model", "representation.npz", "run.json")


def save_run(run: Run, root: str | Path) -> Path:
    """Write the run into the folder ``root`` (created if needed): model (a checkpoint folder), representation.npz
    and run.json.

    **Arguments:**

    - ``run``: the run; its ``root`` is set to ``root``.
    - ``root``: the run folder.

    **Returns:**

    ``root`` as a ``Path``.
    """
    from jaxdeform.cloth import train as ctrain

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    ctrain.save_model(root / "model", run.model, {"representation": run.rep.kind})
    with atomic_path(root / "representation.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **run.rep.to_arrays())
    with atomic_path(root / "run.json") as tmp:
        tmp.write_text(json.dumps(run.record, indent=1) + "\n")
    run.root = root
    return root


#: the fields of a cloth run.json and their JSON types (:func:`jaxdeform.runs.check_fields`)
RECORD_FIELDS = {
    "kind": ("string",),
    "dataset": ("string",),
    "scenario": ("string", "null"),
    "split": ("object",),
    "representation": ("string",),
    "residual": ("boolean",),
    "model": ("object",),
    "train": ("object",),
    "final_loss": ("number", "null"),
    "train_seconds": ("number",),
    "thickness": ("number",),
    "fingerprint": ("object",),
}
#: fields a cloth run.json may lack (runs saved without a dataset or before the field existed)
RECORD_OPTIONAL = tuple(RECORD_FIELDS)


def load_run(root: str | Path) -> Run:
    """Load the cloth run in the folder ``root``.

    **Arguments:**

    - ``root``: a folder written by :func:`save_run`.

    **Returns:**

    The :class:`Run` (model, representation, record, root).

    **Raises:**

    ``JaxDeformError`` if run.json is missing, not JSON or not a cloth run record, its split or thickness is
    invalid, model is not a cloth model checkpoint, or representation.npz is not a cloth feature representation.
    """
    from jaxdeform.cloth import train as ctrain

    root = Path(root)
    path = root / "run.json"
    if not path.is_file():
        raise JaxDeformError(f"{root}: not a cloth run (no run.json).")
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError:
        raise JaxDeformError(f"{path}: not valid JSON.") from None
    if not isinstance(record, dict) or record.get("format") != RUN_FORMAT:
        raise JaxDeformError(f"{path}: not a jaxdeform cloth run record.")
    runs.check_fields(path, record, RECORD_FIELDS, optional=RECORD_OPTIONAL)
    if record.get("representation", "ts-acap") not in cfeat.KINDS:
        raise JaxDeformError(
            f"{path}: its representation must be one of {', '.join(cfeat.KINDS)}, got {record['representation']!r}."
        )
    cdata.check_split(record.get("split", {}), path)
    thickness = record.get("thickness", 0.005)
    if isinstance(thickness, bool) or not isinstance(thickness, (int, float)) or not 0 <= thickness < float("inf"):
        raise JaxDeformError(f"{path}: its 'thickness' must be a finite number >= 0, got {thickness!r}.")
    model, _ = ctrain.load_model(root / "model")
    rep_path = root / "representation.npz"
    arrays = read_npz_arrays(rep_path)
    try:
        rep = cfeat.Representation.from_arrays(arrays)
    except KeyError as exc:
        raise JaxDeformError(f"{rep_path}: not a cloth feature representation (missing {exc.args[0]}).") from None
    except (TypeError, ValueError) as exc:
        raise JaxDeformError(f"{rep_path}: not a cloth feature representation ({exc}).") from None
    if record.get("representation", rep.kind) != rep.kind:
        raise JaxDeformError(
            f"{path}: it names the {record['representation']} representation, {rep_path} holds {rep.kind}."
        )
    prints = record.get("fingerprint", {})
    for name, rest, faces in (("coarse", rep.coarse_rest, rep.coarse_faces), ("fine", rep.fine_rest, rep.fine_faces)):
        if name in prints:
            runs.check_fingerprint(path, {"fingerprint": prints[name]}, rest, faces, f"the {name} mesh of {rep_path}")
    return Run(model, rep, record, root)


# ------------------------------------------------------------------------------------------- synthesis


def obstacle_sdf(obstacles: dict, t: int):
    """Host-side signed distance of the obstacles at frame ``t`` of a stored track (for the refinement)."""
    from jaxdeform.cloth import obstacles as obst

    if not obstacles:
        return None
    frame = obst.obstacles_at(obst.from_dict(obstacles), t)

    def sdf(x):
        d, n = obst.signed_distance(frame, np.asarray(x, np.float32))  # jitted in obstacles
        return np.asarray(d, np.float64), np.asarray(n, np.float64)

    return sdf


def synthesize_timed(
    run: Run, coarse: np.ndarray, obstacles: dict | None = None, refine: bool = True, pins: dict | None = None
) -> tuple[np.ndarray, dict]:
    """Fine frames from coarse frames, and seconds per frame of each stage.

    **Arguments:**

    - ``run``: the cloth run.
    - ``coarse``: coarse frames ``(T, Vc, 3)``.
    - ``obstacles``: the scenario's obstacle track (for the refinement; None: no refinement).
    - ``refine``: refine the frames against the obstacles (when ``obstacles`` is given).
    - ``pins``: the scenario's fixed vertices (``Sequence.pins``: fine_pins, fine_pin_positions) that anchor the
        reconstruction.

    **Returns:**

    ``(fine, timing)``: fine frames ``(T, Vf, 3)`` and a dict of seconds per frame of ``extraction``, ``synthesis``,
    ``reconstruction`` and ``refinement``, plus the number of ``refined_frames``.
    """
    from jaxdeform.cloth import train as ctrain

    coarse = np.asarray(coarse, np.float32)
    n = coarse.shape[0]
    t0 = time.perf_counter()
    fc = run.rep.encode("coarse", coarse)
    base = run.rep.base(coarse, remember=False) if run.rep.residual else None  # timed: never a cached base
    t1 = time.perf_counter()
    ff = np.asarray(jax.block_until_ready(ctrain.synthesize(run.model, fc)))
    t2 = time.perf_counter()
    pins = pins or {}
    fine = run.rep.decode_fine(
        ff, coarse, base=base, pins=pins.get("fine_pins"), pin_positions=pins.get("fine_pin_positions")
    )
    t3 = time.perf_counter()
    refined = 0
    if refine and obstacles:
        refiner = run.refiner
        margin = float(run.record.get("thickness", 0.005))
        out = np.empty_like(fine)
        for t in range(n):
            p, st = refiner(fine[t], obstacle_sdf(obstacles, t), margin)
            out[t] = p
            refined += st.iterations > 0
        fine = out
    t4 = time.perf_counter()
    timing = {
        "extraction": (t1 - t0) / n,
        "synthesis": (t2 - t1) / n,
        "reconstruction": (t3 - t2) / n,
        "refinement": (t4 - t3) / n,
        "refined_frames": refined,
    }
    return fine, timing


def check_meshes(run: Run, where, coarse: tuple, fine: tuple | None = None) -> None:
    """Check that rest meshes read from ``where`` are the ones ``run`` was trained on.

    **Arguments:**

    - ``run``: the run.
    - ``where``: names the data in the message.
    - ``coarse``: ``(rest (V, 3), faces (F, 3))`` of the coarse mesh.
    - ``fine``: the same of the fine mesh (None: not checked).

    **Raises:**

    ``ConnectivityError``, one sentence naming the mesh and what differs (:func:`jaxdeform.mesh.fingerprint.difference`
    against the run's own rest meshes).
    """
    pairs = [("coarse", coarse, run.rep.coarse_rest, run.rep.coarse_faces)]
    if fine is not None:
        pairs.append(("fine", fine, run.rep.fine_rest, run.rep.fine_faces))
    for name, (rest, faces), run_rest, run_faces in pairs:
        what = difference(fingerprint(run_rest, run_faces), rest, faces, whose=f"the run's {name} mesh")
        if what is not None:
            raise ConnectivityError(
                f"{where}: its {name} mesh is not the one the run was trained on ({what}); pass the run's data."
            )


def check_dataset(run: Run, ds: cdata.ClothDataset, data: str | Path, run_dir: str | Path) -> None:
    """Check that ``ds`` (read from ``data``) has the rest meshes ``run`` (read from ``run_dir``) was trained on
    (:func:`check_meshes`), and give it the run's split when it is the run's own dataset (the split checked against
    its sequences). One sentence (ConnectivityError, or the split's error) on a mismatch."""
    check_meshes(run, data, (ds.coarse_rest, ds.coarse_faces), (ds.fine_rest, ds.fine_faces))
    if "split" in run.record and Path(run.record.get("dataset", "")) == Path(data).resolve():
        cdata.check_split(
            run.record["split"], f"{Path(run_dir) / 'run.json'} (read against {data})", {x.name for x in ds.sequences}
        )
        ds.split = run.record["split"]


def evaluate_run(
    run: Run, ds: cdata.ClothDataset, part: str = "test", refine: bool = True, progress: bool = True
) -> dict:
    """Errors of the run's synthesis and of the upsampled coarse baseline on a split of a dataset.

    **Arguments:**

    - ``run``: the cloth run.
    - ``ds``: the dataset.
    - ``part``: the split to evaluate (default ``"test"``).
    - ``refine``: refine the synthesised frames against the obstacles.
    - ``progress``: show a progress bar.

    **Returns:**

    ``{part: pooled errors, "upsampled_coarse": {part: pooled errors}}`` (:func:`jaxdeform.cloth.evaluate.pool`).
    """
    ups = ceval.Upsampler(ds.coarse_faces, ds.coarse_rest.shape[0], ds.fine_faces)
    ours, coarse = [], []
    for s in tqdm(ds.subset(part), desc=f"evaluate {part}", unit="seq", disable=not progress):
        fine, _ = synthesize_timed(run, s.coarse, s.obstacles, refine=refine, pins=s.pins)
        ours.append(ceval.sequence_errors(s.fine, fine, ds.fine_faces))
        coarse.append(ceval.sequence_errors(s.fine, ups(s.coarse), ds.fine_faces))
    return {part: ceval.pool(ours), "upsampled_coarse": {part: ceval.pool(coarse)}}


# ------------------------------------------------------------------------------------ run-folder API

KIND = "cloth"


@dataclass(frozen=True)
class Config:
    """What :func:`fit` trains: the detail model, its training, the feature representation and the target."""

    model: object = None  # a jaxdeform.cloth.model.ModelConfig; None: its defaults
    train: object = None  # a jaxdeform.cloth.train.TrainConfig; None: its defaults
    representation: str = "ts-acap"
    residual: bool = True  # the target is the fine features' residual over the Loop-upsampled coarse cloth


def _test_config() -> Config:
    from jaxdeform.cloth.model import ModelConfig
    from jaxdeform.cloth.train import TrainConfig

    return Config(ModelConfig(d_model=16, heads=2, blocks=1, ffn=32), TrainConfig(steps=3, batch_size=4))


#: named configurations: the paper's model and our training, and a CPU-sized one (a small model, 3 steps)
CONFIGS = {"default": Config(), "test": _test_config()}


def fit(
    data, config: str | Config = "default", out=None, *, progress: bool = True, resume: bool = False, log=print
) -> Run:
    """Train a detail model on the dataset's training split and write the run folder ``out``.

    **Arguments:**

    - ``data``: a dataset folder or a loaded :class:`~jaxdeform.cloth.data.ClothDataset`.
    - ``config``: a name of :data:`CONFIGS` or a :class:`Config`.
    - ``out``: the run folder, built beside it with the training's checkpoints (:func:`jaxdeform.runs.resumable`)
        and renamed at the end; None: nothing is written.
    - ``progress``: show progress bars.
    - ``resume``: continue the interrupted fit of the same settings kept beside ``out`` (training interrupted by
        Ctrl-C or a signal after a checkpoint keeps it); without it a kept partial fit is discarded.
    - ``log``: receives a line when a fit resumes.

    **Returns:**

    The :class:`Run` (:func:`train_run`).

    **Raises:**

    ``JaxDeformError`` as :func:`train_run`, and for ``resume`` with a partial fit of other settings.
    """
    cfg = runs.config(KIND, config, Config)

    def work(checkpoints, resuming):
        return train_run(
            data,
            representation=cfg.representation,
            model_cfg=cfg.model,
            train_cfg=cfg.train,
            progress=progress,
            residual=cfg.residual,
            checkpoint_dir=checkpoints,
            resume=resuming,
        )

    if out is None:
        return work(None, False)
    source = data.root if isinstance(data, cdata.ClothDataset) else data
    settings = {"config": repr(cfg), "data": str(Path(source).resolve())}
    with runs.resumable(Path(out), settings, resume, log) as (tmp, resuming):
        run = work(tmp / "checkpoints", resuming)
        shutil.rmtree(tmp / "checkpoints", ignore_errors=True)
        save_run(run, tmp)
    run.root = Path(out)
    return run


def _dataset(run: Run, data) -> cdata.ClothDataset:
    """``data`` (None: the dataset of the run's record) loaded and checked against the run."""
    source = run.record.get("dataset") if data is None else data
    if source is None:
        raise JaxDeformError("the run records no dataset; pass the data to evaluate it on.")
    ds = data if isinstance(data, cdata.ClothDataset) else cdata.load_dataset(source)
    check_dataset(run, ds, ds.root, run.root or ".")
    return ds


def evaluate(run: Run, data=None, *, part: str = "test", progress: bool = False) -> dict:
    """Errors of the run's synthesis and of the upsampled coarse cloth on a split of the dataset.

    **Arguments:**

    - ``run``: the run.
    - ``data``: a dataset folder or :class:`~jaxdeform.cloth.data.ClothDataset` with the run's meshes (None: the
        dataset recorded in run.json).
    - ``part``: the split (default ``"test"``).
    - ``progress``: show a progress bar.

    **Returns:**

    :func:`evaluate_run`'s dict.
    """
    ds = _dataset(run, data)
    return evaluate_run(run, ds, part=part, progress=progress)


def strip_figure(coarse_up, ours, fine, faces, path, size: int = 256, scene=None) -> np.ndarray:
    """One frame side by side: the upsampled coarse cloth, the synthesis, the fine simulation and its error.

    **Arguments:**

    - ``coarse_up``, ``ours``, ``fine``: the frame's fine-mesh positions ``(V, 3)`` each.
    - ``faces``: the fine faces ``(F, 3)``.
    - ``path``: the PNG to write (atomically).
    - ``size``: the panels' height in pixels.
    - ``scene``: ``(vertices, faces)`` of what the cloth lies on (a garment's body, :func:`jaxdeform.cloth.body.
        capsules_mesh`), drawn in the first three panels; None: the cloth alone.

    **Returns:**

    The image ``(H, W, 3)`` uint8.
    """
    from jaxdeform.mesh.render import auto_camera, caption, hstack, render, save_png

    sv, sf = (np.zeros((0, 3)), np.zeros((0, 3), np.int64)) if scene is None else scene
    cam = auto_camera(np.concatenate([fine, ours, coarse_up, sv]), azimuth_deg=35, elevation_deg=25)
    err = np.linalg.norm(ours - fine, axis=1)
    vmax = float(max(np.linalg.norm(coarse_up - fine, axis=1).max(), err.max(), 1e-6))
    plain = {"camera": cam, "width": size, "height": size, "colorbar": False}
    colours = np.concatenate([np.tile([0.62, 0.70, 0.88], (len(fine), 1)), np.tile([0.86, 0.72, 0.60], (len(sv), 1))])

    def with_scene(x):
        if not len(sv):
            return render(x, faces, **plain)
        return render(np.concatenate([x, sv]), np.concatenate([faces, sf + len(x)]), vertex_colors=colours, **plain)

    panels = [
        caption(with_scene(coarse_up), "coarse (upsampled)"),
        caption(with_scene(ours), "ours"),
        caption(with_scene(fine), "fine simulation"),
        caption(
            render(
                ours,
                faces,
                scalar=err,
                camera=cam,
                width=size + 90,
                height=size,
                vmin=0.0,
                vmax=vmax,
                cmap="viridis",
                label="m",
            ),
            "error of ours",
        ),
    ]
    image = hstack(panels)
    save_png(image, path)
    return image


def show(run: Run, out, data=None, *, frames: int = 3, size: int = 256) -> dict:
    """Synthesise the first test sequence and write strips of a few frames (:func:`strip_figure`) into ``out``.

    **Arguments:**

    - ``run``: the run.
    - ``out``: the folder (created if needed; each PNG replaces a file of its name, atomically).
    - ``data``: the dataset (None: the one recorded in run.json).
    - ``frames``: how many frames, spread over the sequence's last three quarters.
    - ``size``: the panels' height in pixels.

    **Returns:**

    ``{"sequence", "frames", "files"}``.
    """
    ds = _dataset(run, data)
    seqs = ds.subset("test") or ds.sequences
    x = seqs[0]
    fine, _ = synthesize_timed(run, x.coarse, x.obstacles, pins=x.pins)
    coarse_up = ceval.Upsampler(ds.coarse_faces, ds.coarse_rest.shape[0], ds.fine_faces)(x.coarse)
    n = x.coarse.shape[0]
    picked = sorted({int(t) for t in np.linspace(n // 4, n - 1, frames)})
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for t in picked:
        files.append(f"strip_{x.name.removesuffix('.npz')}_f{t:03d}.png")
        scene = body_scene(ds.scenario, x.obstacles, t)
        strip_figure(coarse_up[t], fine[t], x.fine[t], ds.fine_faces, out / files[-1], size, scene)
    return {"sequence": x.name, "frames": picked, "files": files}


def body_scene(kind: str, obstacles: dict, t: int):
    """The body a garment of scenario ``kind`` is worn on at frame ``t`` of its obstacle track, as a mesh
    ``(vertices, faces)`` for :func:`strip_figure`; None for the scenes without a body."""
    from jaxdeform.cloth import body, scenarios

    if kind not in scenarios.GARMENT_KINDS or not obstacles:
        return None
    return body.capsules_mesh(obstacles["capsule_a"][t], obstacles["capsule_b"][t], obstacles["capsule_r"][t])
