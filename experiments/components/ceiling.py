"""How well can localized *linear* components generalize on a split? Regional projection onto the training span.

    python -m experiments.components.ceiling [--data ../shared/data/horse-gallop] [--regions 1,10,25,50,100]
                                             [--out out/experiments/components/ceiling]

For each number of regions R (furthest-point geodesic centres, every vertex to its nearest centre), every unseen
shape of the every-10th split (a seeded random half for pose sets, as ``run.py``) is replaced region by region by
its least-squares fit in the span of the training shapes' deviations there
(:func:`jaxdeform.components.baselines.regional_projection`), in two representations:

- ``acap``: scaled ACAP features (rotation branches aligned to the training shapes' reference, as the runs do;
  ``--turns per-shape`` leaves each shape's own branches), scaled by the official min/max bounds of the training
  shapes: the runs' scaler also clips at its quantiles (``SCALE_QUANTILE``), which would mix the clipping's cost
  into this ceiling of the features; positions by the ACAP reconstruction;
- ``xyz``: vertex coordinates, as PCA on coordinates and SPLOCS use them.

Erms and STED of the result against the unseen shapes. R = 1 is PCA with every component kept. A model that
reconstructs each region from the training shapes' deviations there, linearly, cannot beat the best R; seed
000's autoencoders are nearly that (tied fully connected layers between 9x9 mesh convolutions). Writes
results.json and results.md (atomically).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from experiments.components.common import SPLITS
from jaxdeform import acap
from jaxdeform.components import baselines
from jaxdeform.components import run as crun
from jaxdeform.mesh.io import atomic_path

DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "horse-gallop"


def ceiling(data, regions=(1, 10, 25, 50, 100), split: str | None = None, turns: str = "aligned") -> dict:
    vertices, faces = crun.load_data(data)
    split = split or SPLITS.get(Path(data).name, "every10")
    tr, te = crun.split_indices(vertices.shape[0], split)
    rest = vertices[0]
    dist = crun.normalized_geodesics(rest, faces, np.float64)
    feats = np.asarray(acap.encode(rest, faces, vertices), np.float64)
    # the official min/max scaler (quantile 0): the ceiling is of the features, not of their clipping
    reference, scaler = crun.fit_feature_transform(feats[tr], 0.0, align=turns == "aligned")
    x = crun.apply_feature_transform(feats, reference, scaler, np.float64)

    def scores(positions):  # the metrics of the generalization protocol, as `components evaluate` reports them
        m = crun.set_metrics(vertices[te], {"positions": positions}, faces)
        return {"erms": m["erms"], "sted": m["sted"]}

    rows = []
    for r in regions:
        labels = baselines.geodesic_regions(dist, min(int(r), rest.shape[0]))
        xh = baselines.regional_projection(x[tr], x[te], labels)
        pos_acap = np.asarray(acap.decode(jnp.asarray(np.asarray(scaler.inverse(xh)), jnp.float64), rest, faces))
        pos_xyz = baselines.regional_projection(vertices[tr], vertices[te], labels)
        rows.append({"regions": int(r), "acap": scores(pos_acap), "xyz": scores(pos_xyz)})
        print(json.dumps(rows[-1]), flush=True)
    return {
        "data": str(data),
        "split": split,
        "turns": turns,
        "scale_quantile": 0.0,
        "train_shapes": len(tr),
        "test_shapes": len(te),
        "rows": rows,
    }


def markdown(result: dict) -> str:
    lines = [
        f"Regional projection onto the training span, {Path(result['data']).name} "
        f"({result['train_shapes']} train / {result['test_shapes']} test, split {result['split']}, "
        f"rotation branches {result.get('turns', 'per-shape')})",
        "",
        "| regions | Erms, ACAP features | STED, ACAP | Erms, coordinates | STED, coordinates |",
        "|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        a, c = row["acap"], row["xyz"]
        lines.append(f"| {row['regions']} | {a['erms']:.2f} | {a['sted']:.4f} | {c['erms']:.2f} | {c['sted']:.4f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--regions", default="1,10,25,50,100")
    ap.add_argument("--out", default="out/experiments/components/ceiling")
    ap.add_argument("--turns", choices=("aligned", "per-shape"), default="aligned")
    a = ap.parse_args(argv)
    result = ceiling(a.data, tuple(int(t) for t in a.regions.split(",")), turns=a.turns)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "results.json") as tmp:
        Path(tmp).write_text(json.dumps(result, indent=2))
    with atomic_path(out / "results.md") as tmp:
        Path(tmp).write_text(markdown(result))
    print(markdown(result))
    return result


if __name__ == "__main__":
    main()
