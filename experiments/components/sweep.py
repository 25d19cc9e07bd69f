"""Diagnostic training of one seed-000 model configuration on a sequence: generalization and localization.

    python -m experiments.components.sweep --data ../shared/data/horse-gallop --kz 10,5 --d 0.4,0.2 \\
        [--lambda-recon 10] [--lambda-sparse 1] [--mask step|linear] [--latent linear|tanh] [--no-attention] [--attention-gradient] \\
        [--separate] [--turns aligned|per-shape] [--scale-quantile 1e-3] [--epochs 2000] [--eval-every N] \\
        [--curve erms|features] [--split every10|half|all] [--lr 1e-3] [--decay-rate 0.794] [--clip-norm C] \\
        [--augment N [--batch 8] [--mix-regions 3,12] [--mix-sigma 0.15] [--mix-alpha 0.5]] [--seed 0] [--jsonl OUT.jsonl]

Unlike ``experiments.components.run`` (named configurations, run folders, STED), this trains any configuration
in memory on one split (every 10th shape by default) and prints one JSON line (appended to ``--jsonl``):

- ``train_erms`` / ``test_erms``: Erms of the whole model (encode -> decode -> ACAP reconstruction);
- ``level0_train_erms`` / ``level0_test_erms``: the same with AE0 alone (what the higher levels add);
- ``train_feature_mse`` / ``test_feature_mse``: mean squared error of the scaled features;
- ``train_max_rse`` / ``test_max_rse`` (and ``_mean_rse``): eq. (8), the relative squared error of the scaled
  features per shape, its largest and mean value (Table 5);
- ``curve`` (with ``--eval-every``): per evaluated epoch, the seconds since training began and the metrics above;
- ``inside_fraction``: per level, the median over components of the share of sum_i ||C_k,i|| that lies within
  the level's cut-off d of the component centre (1 = perfectly localized).

``--augment N`` adds N regional mixes of the training shapes' scaled features to the training set
(:func:`jaxdeform.components.finetune.regional_mixes`: each vertex a convex combination of the training shapes, the weights varying smoothly over
a few random geodesic regions), and the batch then samples ``--batch`` shapes from the enlarged set; Erms and eq. 8
are still of the real shapes only. It tests whether an encoder that has seen shapes between the training ones
generalizes better to the unseen ones.

With ``--split all`` every shape trains and "test" is the whole set again (Table 5 read as the representation
error); the test keys then repeat the train ones and are not evaluated twice. ``--curve features`` keeps the
learning curve to the feature metrics (no ACAP reconstruction per point: cheap enough for every 100 epochs).

It is how the hyper-parameter and variant studies of issue 3's notes were measured.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxdeform import acap, metrics
from jaxdeform.components import extract, model, train
from jaxdeform.components import run as crun
from jaxdeform.components.finetune import regional_mixes
from jaxdeform.mesh.topology import build_topology
from jaxdeform.nn.graph_conv import rings_from_topology
from jaxdeform.nn.losses import vertex_norms


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(t) for t in text.split(","))


def inside_fraction(c: np.ndarray, dist: np.ndarray, d: float) -> float:
    """Median over the components (rows of ``c``, any leading block axes) of the share of their group norm
    within ``d`` of their centre."""
    rows = np.asarray(c).reshape(-1, np.asarray(c).shape[-1])
    norms = np.asarray(vertex_norms(jnp.asarray(rows), dist.shape[0]))
    inside = dist[norms.argmax(axis=1)] < d
    total = np.maximum(norms.sum(axis=1), 1e-30)
    return float(np.median((norms * inside).sum(axis=1) / total))


def kept_components(m: model.Model, data: np.ndarray, rings, dist: np.ndarray, scaler) -> dict:
    """Per level: the number of components kept by the redundant-component removal (eq. (7), eps2, as
    ``jaxdeform components show``) and the largest strengths, the magnitudes taken from the codes of ``data``
    (the training shapes, scaled features)."""
    final = m(jnp.asarray(data), rings, jnp.asarray(dist))
    cs = extract.all_components(m, rings, latents=tuple(final.latents), scaler=scaler)
    removal = extract.remove_redundant(cs)
    out = {}
    for lvl in range(len(m.levels)):
        sel = cs.level == lvl
        out[f"level{lvl}"] = {
            "components": int(sel.sum()),
            "kept": int(removal.keep[sel].sum()),
            "strongest": [round(float(v), 5) for v in np.sort(removal.strength[sel])[::-1][:8]],
        }
    return out


def main(argv=None, extra_config: dict | None = None, model_options: dict | None = None) -> dict:
    """``extra_config``: entries added to the result line's configuration; ``model_options``: options of
    :class:`jaxdeform.components.model.Config` set over the command line's (callers that name a model variant,
    such as :mod:`experiments.components.reference_variants`)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--data", default=str(Path(__file__).resolve().parents[2].parent / "shared" / "data" / "horse-gallop")
    )
    ap.add_argument("--kz", default="10,5")
    ap.add_argument("--d", default="0.4,0.2")
    ap.add_argument("--lambda-recon", type=float, default=10.0)
    ap.add_argument("--lambda-sparse", type=float, default=1.0)
    ap.add_argument("--mask", choices=("step", "linear"), default="step")
    ap.add_argument("--latent", choices=("linear", "tanh"), default="linear")
    ap.add_argument("--no-attention", action="store_true")
    ap.add_argument("--attention-gradient", action="store_true")
    ap.add_argument("--separate", action="store_true", help="level-by-level training (Table 4)")
    ap.add_argument(
        "--turns",
        choices=("aligned", "per-shape"),
        default="aligned",
        help="rotation branches: aligned across shapes to the training shapes' reference (acap.align_turns; "
        "the run default) or as each shape's own consistency solve left them",
    )
    ap.add_argument(
        "--scale-quantile",
        type=float,
        default=crun.SCALE_QUANTILE,
        help="feature scaler bounds at this quantile of the training features, clipped (acap.Scaler)",
    )
    ap.add_argument("--epochs", type=int, default=2000)
    ap.add_argument(
        "--eval-every",
        type=int,
        metavar="N",
        help="also evaluate train and test Erms every N epochs (the learning curve, key 'curve')",
    )
    ap.add_argument(
        "--curve",
        choices=("erms", "features"),
        default="erms",
        help="what each point of the learning curve holds: Erms (an ACAP reconstruction of every shape) "
        "or only the feature metrics (eq. 8 and feature MSE)",
    )
    ap.add_argument(
        "--split",
        choices=crun.SPLITS,
        default="every10",
        help="training shapes: every 10th (default), a seeded random half, or all of them",
    )
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument(
        "--decay-rate",
        type=float,
        default=train.TrainConfig.decay_rate,
        help="learning rate multiplied by this every 1,000 steps",
    )
    ap.add_argument("--clip-norm", type=float, help="clip each step's gradient to this global norm before Adam")
    ap.add_argument(
        "--augment",
        type=int,
        default=0,
        metavar="N",
        help="train on the real shapes and N regional mixes of them (regional_mixes)",
    )
    ap.add_argument("--batch", type=int, default=train.TrainConfig.batch, help="shapes per step")
    ap.add_argument("--mix-regions", default="3,12", help="least and most regions of a mix")
    ap.add_argument("--mix-sigma", type=float, default=0.15, help="width of a region's weight (normalized geodesics)")
    ap.add_argument("--mix-alpha", type=float, default=0.5, help="Dirichlet concentration of a region's combination")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jsonl", help="append the result line to this file")
    a = ap.parse_args(argv)

    cfg = model.Config(
        kz=tuple(int(k) for k in _floats(a.kz)),
        d=_floats(a.d),
        lambda_recon=a.lambda_recon,
        lambda_sparse=a.lambda_sparse,
        mask=a.mask,
        latent=a.latent,
        attention=not a.no_attention,
        attention_gradient=a.attention_gradient,
        **(model_options or {}),
    )
    tc = train.TrainConfig(
        epochs=a.epochs,
        learning_rate=a.lr,
        seed=a.seed,
        joint=not a.separate,
        decay_rate=a.decay_rate,
        clip_norm=a.clip_norm,
        batch=a.batch,
    )
    vertices, faces = crun.load_data(a.data)
    tr, te = crun.split_indices(vertices.shape[0], a.split)
    same = a.split == "all"  # test is the training set again: evaluated once
    sets = (("train", tr),) if same else (("train", tr), ("test", te))
    rest = vertices[0]
    dist = crun.normalized_geodesics(rest, faces)
    feats = np.asarray(acap.encode(rest, faces, vertices), np.float32)
    turns, scaler = crun.fit_feature_transform(feats[tr], a.scale_quantile, align=a.turns == "aligned")
    x = crun.apply_feature_transform(feats, turns, scaler, np.float32)
    rings = rings_from_topology(build_topology(faces, rest.shape[0]))

    def features_hat(idx, m):
        xs = jnp.asarray(x[idx])
        return jnp.concatenate([train.reconstruct(m, xs[i : i + 16], rings) for i in range(0, len(idx), 16)])

    def feature_metrics(idx, xh) -> dict:
        rse = metrics.relative_squared_error(x[idx], xh)
        return {
            "feature_mse": float(np.mean((np.asarray(xh) - x[idx]) ** 2)),
            "max_rse": float(rse.max()),
            "mean_rse": float(rse.mean()),
        }

    def evaluate(idx, m):
        xh = features_hat(idx, m)
        pos = np.asarray(acap.decode(jnp.asarray(np.asarray(scaler.inverse(xh)), jnp.float64), rest, faces))
        return metrics.erms(vertices[idx], pos), feature_metrics(idx, xh)

    curve = []

    def snapshot(epoch, m):
        point = {"epoch": epoch, "seconds": round(time.perf_counter() - t0, 1)}
        for name, idx in sets:
            if a.curve == "erms":
                point[f"{name}_erms"], fm = evaluate(idx, m)
            else:
                fm = feature_metrics(idx, features_hat(idx, m))
            point.update({f"{name}_{k}": v for k, v in fm.items()})
        curve.append(point)
        print(json.dumps(curve[-1]), flush=True)

    data = x[tr]
    if a.augment:
        lo, hi = (int(t) for t in a.mix_regions.split(","))
        data = np.concatenate(
            [
                data,
                regional_mixes(
                    data, dist, a.augment, np.random.default_rng(a.seed), (lo, hi), a.mix_sigma, a.mix_alpha
                ),
            ]
        )
    t0 = time.perf_counter()
    trained, history = train.train(
        data,
        rings,
        dist,
        cfg,
        tc,
        progress=True,
        snapshot=snapshot if a.eval_every else None,
        snapshot_every=a.eval_every or 1000,
    )
    seconds = time.perf_counter() - t0

    result = {
        "config": {
            **dataclasses.asdict(cfg),
            **dataclasses.asdict(tc),
            "turns": a.turns,
            "scale_quantile": a.scale_quantile,
            "augment": a.augment,
            **(extra_config or {}),
            **({"mix_regions": a.mix_regions, "mix_sigma": a.mix_sigma, "mix_alpha": a.mix_alpha} if a.augment else {}),
        },
        "data": str(a.data),
        "train_shapes": len(tr),
        "test_shapes": len(te),
        "train_seconds": round(seconds, 1),
        "final_loss": float(history[-1]),
        # the loss per 100 epochs: last value and largest (spikes of Adam's instability show here)
        "loss_per_100": [
            [float(w[-1]), float(w.max())] for w in (history[i : i + 100] for i in range(0, len(history), 100))
        ],
    }
    result["split"] = a.split
    for name, idx in sets:
        result[f"{name}_erms"], fm = evaluate(idx, trained)
        result.update({f"{name}_{k}": v for k, v in fm.items()})
    if cfg.levels > 1:
        for name, idx in sets:
            result[f"level0_{name}_erms"] = evaluate(idx, trained.first_levels(1))[0]
    if same:
        result.update(
            {
                k.replace("train_", "test_", 1): v
                for k, v in list(result.items())
                if "train_" in k and k != "train_seconds"
            }
        )
    if curve:
        result["curve"] = curve
    result["inside_fraction"] = [
        inside_fraction(np.asarray(level.C[...]), dist, cfg.d[lvl]) for lvl, level in enumerate(trained.levels)
    ]
    if not cfg.tie_conv and cfg.decoder_tanh:  # component extraction reads the default decoder only
        result["components"] = kept_components(trained, x[tr], rings, dist, scaler)
    line = json.dumps(result, default=float)
    print(line)
    if a.jsonl:
        with open(a.jsonl, "a") as fh:
            fh.write(line + "\n")
    return result


if __name__ == "__main__":
    main()
