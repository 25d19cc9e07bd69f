"""Learning curves of eq. (8) from sweep results: Table 5 read as the representation error, epoch by epoch.

    python -m experiments.components.curves one=ONE.jsonl two=TWO.jsonl three=THREE.jsonl --out DIR \\
        [--title TEXT] [--hardware TEXT]

Each ``LABEL=FILE`` names the last line of a ``experiments.components.sweep --eval-every N --curve features
--jsonl FILE`` run. Writes ``DIR/results.json`` (per label: config, epochs, final metrics and the curve),
``DIR/results.md`` (the largest relative squared error per evaluated epoch, one column per label, and the final
Erms, "not measured" where a result line has none) and ``DIR/curves.png`` (the largest relative squared error against the epoch, log scale, with the paper's
two- and three-level figures as dashed lines).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from experiments import charts
from jaxdeform.mesh.io import atomic_path

#: Table 5 of the paper (horse, maximum of eq. 8): one, two and three levels.
PAPER = {1: 0.1219, 2: 0.005491, 3: 0.003567}


def load(specs: list[str]) -> dict:
    """``{label: sweep result}`` from ``LABEL=FILE`` arguments (the last JSON line of each file)."""
    runs = {}
    for spec in specs:
        label, sep, path = spec.partition("=")
        if not sep or not label or not path:
            raise SystemExit(f"{spec!r}: expected LABEL=FILE.")
        lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip()]
        if not lines:
            raise SystemExit(f"{path}: empty; expected the JSON lines of a sweep run.")
        res = json.loads(lines[-1])
        if not res.get("curve") or "train_max_rse" not in res["curve"][0]:
            raise SystemExit(f"{path}: no learning curve of eq. 8 in it (run the sweep with --eval-every N).")
        runs[label] = res
    return runs


def summary(runs: dict) -> dict:
    out = {}
    for label, r in runs.items():
        kz = r["config"]["kz"]
        out[label] = {
            "levels": len(kz),
            "kz": kz,
            "d": r["config"]["d"],
            "split": r.get("split", "every10"),
            "epochs": r["config"]["epochs"],
            "train_shapes": r["train_shapes"],
            "train_seconds": r["train_seconds"],
            "max_relative_squared_error": r["test_max_rse"],
            "mean_relative_squared_error": r["test_mean_rse"],
            "erms": r.get("test_erms"),
            "paper_max_relative_squared_error": PAPER.get(len(kz)),
            "curve": [
                {
                    "epoch": p["epoch"],
                    "max_rse": p.get("test_max_rse", p["train_max_rse"]),
                    "mean_rse": p.get("test_mean_rse", p["train_mean_rse"]),
                }
                for p in r["curve"]
            ],
        }
    return out


def markdown(rows: dict, title: str, hardware: str) -> str:
    labels = list(rows)
    epochs = sorted({p["epoch"] for r in rows.values() for p in r["curve"]})
    at = {lab: {p["epoch"]: p["max_rse"] for p in rows[lab]["curve"]} for lab in labels}
    lines = [
        f"# {title}",
        "",
        f"Hardware: {hardware}.",
        "",
        "Largest relative squared error (eq. 8) over the evaluated shapes, per epoch; the paper's figure "
        "(10,000 epochs) in the header.",
        "",
        "| epoch | "
        + " | ".join(
            f"{lab} ({rows[lab]['levels']} level{'s' * (rows[lab]['levels'] > 1)}; "
            f"paper {rows[lab]['paper_max_relative_squared_error']})"
            for lab in labels
        )
        + " |",
        "|---|" + "---|" * len(labels),
    ]
    for e in epochs:
        cells = [f"{at[lab][e]:.4g}" if e in at[lab] else "" for lab in labels]
        lines.append(f"| {e:,} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "| run | levels (kz) | shapes | epochs | max eq. 8 | mean eq. 8 | Erms | training incl. compile |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for lab in labels:
        r = rows[lab]
        erms = "not measured" if r["erms"] is None else f"{r['erms']:.2f}"
        lines.append(
            f"| {lab} | {r['levels']} ({', '.join(map(str, r['kz']))}) | {r['train_shapes']} | {r['epochs']:,} | "
            f"{r['max_relative_squared_error']:.4g} | {r['mean_relative_squared_error']:.4g} | "
            f"{erms} | {r['train_seconds']:.0f} s |"
        )
    return "\n".join(lines + [""])


TITLE = "Seed 000, Table 5: learning curves of eq. 8"


def plot(rows: dict, path: Path, size=charts.SIZE, title: str = TITLE) -> Path:
    """A line chart of ``size`` pixels at ``path`` (PNG): the largest relative squared error (eq. 8) against the
    epoch (log axis), one line per run; the paper's figure for each level count of the runs as a dashed
    horizontal line in the colour of the first run with that count."""
    fig, ax = charts.figure(size)
    papers = {}
    for i, (label, r) in enumerate(rows.items()):
        colour = f"C{i % 10}"
        pts = [(p["epoch"], p["max_rse"]) for p in r["curve"] if p["max_rse"] > 0]  # a log axis
        levels = f"{r['levels']} level{'s' * (r['levels'] > 1)}"
        ax.plot(
            [e for e, _ in pts],
            [v for _, v in pts],
            color=colour,
            marker="o",
            markersize=3,
            linewidth=1.6,
            label=f"{label} ({levels})",
        )
        paper = r["paper_max_relative_squared_error"]
        if paper and r["levels"] not in papers:
            papers[r["levels"]] = paper
            ax.axhline(paper, color=colour, linestyle="--", linewidth=1.2, label=f"paper, {levels} ({paper:.4g})")
    ax.set_yscale("log")
    ax.set_xlim(left=0)
    charts.thousands(ax.xaxis)
    ax.set_xlabel("epoch")
    ax.set_ylabel("largest relative squared error over the shapes\n(eq. 8, scaled features, dimensionless)")
    charts.title(ax, title)
    if rows:
        fig.legend(loc="outside right upper", fontsize="small")
    return charts.save(fig, path)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", metavar="LABEL=FILE")
    ap.add_argument("--out", required=True)
    ap.add_argument("--title", default=TITLE)
    ap.add_argument("--hardware", default="not given")
    a = ap.parse_args(argv)
    rows = summary(load(a.runs))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "results.json") as tmp:
        Path(tmp).write_text(json.dumps({"title": a.title, "hardware": a.hardware, "rows": rows}, indent=1))
    with atomic_path(out / "results.md") as tmp:
        Path(tmp).write_text(markdown(rows, a.title, a.hardware))
    plot(rows, out / "curves.png", title=a.title)
    return rows


if __name__ == "__main__":
    main()
