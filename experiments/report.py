"""The README's results tables, rendered from the committed result JSON.

    python -m experiments.report            # write every table into README.md between its markers
    python -m experiments.report --check    # exit 1 if README.md's tables differ from what the JSON gives

Each table sits in the README between ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->``; everything
between the two markers is this script's output, byte for byte. ``--readme PATH`` names another README and
``--results-root DIR`` another folder to read the JSON from (the repository root by default: the paths below,
``benchmarks/results/...`` and ``experiments/*/results/...``, are relative to it). The links the tables print are
always relative to the repository root, so a copy of the JSON renders the same text as the original.

Reads JSON only and imports nothing of jaxdeform (the ``experiments`` package itself imports JAX).
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import os
import re
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# the JSON each table reads, relative to the results root (and, as links, to the README)
ACAP = "benchmarks/results/acap_h100_cpu_2026-11-27.json"
ACAP_SOLVERS = "benchmarks/results/acap_cpu_solvers_smoke.json"
C_TABLE2 = "experiments/components/results/kz25/table2.json"
C_TABLE4 = "experiments/components/results/kz25/table4.json"
C_TABLE5 = "experiments/components/results/kz25/table5.json"
C_PAPER_KZ = "experiments/components/results/table4_decay.json"
C_FINETUNE = "experiments/components/results/finetune_horse/results.json"
C_FIG6 = "experiments/components/results/fig6_deformation.json"
CLOTH = "experiments/cloth/results/summary.json"
PARTS = "experiments/parts/results/summary.json"
HANDLES = "experiments/handles/results/summary.json"

# Where a JSON names its machine only vaguely, the README's record of the same run says which it was (the
# summary.json files of seeds 002 and 004 say "x86_64, 2 cores, CPU only").
CLOTH_HARDWARE = (
    "accuracy: one run on the 2-core AMD EPYC VM, 2026-11-29; timing stage (`--stages timing`): "
    "the 2-core Intel Xeon VM, 2026-11-30"
)
HANDLES_HARDWARE = "one run on the 2-core AMD EPYC VM, float32"

# The papers' figures (constants of the papers, not measurements of ours)
PAPER_TABLE4 = {"separate": 11.59, "no-attention-separate": 17.42, "no-attention": 20.89}
PAPER_TABLE5 = {"levels1": 0.1219, "default": 0.005491, "levels3": 0.003567, "paper-kz-levels1": 0.1219}
PAPER_TABLE2 = {"tan": "12.96 / 0.0400", "splocs": "7.37 / 0.0807"}
LABEL4 = {
    "separate": "separate, attention",
    "no-attention-separate": "separate, no attention",
    "no-attention": "joint, no attention",
}
LABEL5 = {
    "levels1": "one level (Kz = 2)",
    "default": "two (default)",
    "levels3": "three (2, 5, 2)",
    "paper-kz-levels1": "one level, Kz = 10 (10,000 epochs)",
}
PAPER_REBIND_MS = {"1": 4, "10": 12, "100": 34}  # seed 004, on an A40 GPU


def num(x: float | None, sig: int = 3) -> str:
    """``x`` to ``sig`` significant digits: thousands separated, small values as 5.6e-4; None as "-"."""
    if x is None:
        return "-"
    x = float(x)
    if x == 0:
        return "0"
    if abs(x) >= 10**sig:
        return f"{round(x):,}"
    if abs(x) < 1e-3:
        mantissa, exponent = f"{x:.{sig - 1}e}".split("e")
        return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"
    digits = max(sig - 1 - math.floor(math.log10(abs(x))), 0)
    return f"{x:,.{digits}f}"


def fixed(x: float, digits: int) -> str:
    return f"{float(x):.{digits}f}"


def load(root: Path, rel: str) -> dict:
    return json.loads((root / rel).read_text())


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def short_hardware(text: str) -> str:
    """A table cell for a JSON's hardware string."""
    gpu = re.search(r"NVIDIA ([A-Z]\d+)", text)
    if gpu:
        return f"1x {gpu.group(1)}"
    if "EPYC" in text:
        return "2-core AMD EPYC"
    if "Xeon" in text:
        return "2-core Intel Xeon"
    return text


# --------------------------------------------------------------------------------------------------- tables


def slashed(values, fmt: Callable[[float], str] = num) -> str:
    """``a / b / c``, with "-" for a missing value."""
    return " / ".join("-" if v is None else fmt(v) for v in values)


def link(rel: str, text: str = "JSON") -> str:
    return f"[{text}]({rel})"


def short_dtype(dtype: str) -> str:
    return dtype.replace("float", "f")


def acap_table(root: Path) -> str:
    d = load(root, ACAP)
    gpu_name = re.search(r"NVIDIA ([A-Z]\d+)", d["note"]).group(1)
    first_sentence = d["note"].split(". ")[0].removeprefix("benchmarks.acap ")
    gpu: dict[tuple, tuple[dict, dict]] = {}  # (case, dtype) -> (record, its run); the first run that has it
    for run in d["gpu_h100"]:
        for rec in run["records"]:
            gpu.setdefault((rec["case"], rec["dtype"]), (rec, run))
    cpu_run = d["cpu_2core"]
    cpu = {(r["case"], r["dtype"]): r for r in cpu_run["records"]}

    def round_trip(rec: dict) -> str:
        return f"{num(rec['roundtrip']['mean_rel'], 2)} / {num(rec['roundtrip']['max_rel'], 2)}"

    rows = []
    for key, (g, run) in gpu.items():
        c = cpu[key]
        data = Path(run["data"]).name
        rows.append(
            [
                data if g["case"] == "dataset" else f"{data}, Loop-subdivided",
                f"{g['vertices']:,}",
                short_dtype(g["dtype"]),
            ]
            + [
                slashed([g[k]["per_frame_ms_median"], c[k]["per_frame_ms_median"]])
                for k in ("encode_local", "encode", "encode_temporal", "decode", "decode_plain")
            ]
            + [
                slashed([g["cholespy_solve_3rhs_ms"], c["cholespy_solve_3rhs_ms"]]),
                " ; ".join(dict.fromkeys(round_trip(r) for r in (g, c))),
            ]
        )  # one pair where both agree
    head = [
        "case",
        "V",
        "dtype",
        "encode, local",
        "encode, spatial",
        "encode, TS-ACAP",
        "decode, refine=1",
        "decode, refine=0",
        "cholespy solve, 3 rhs",
        "round trip mean / max (x bbox diag), both devices",
    ]
    cpu_name = short_hardware(next(iter(cpu.values()))["cpu"])
    lines = [
        f"`python -m benchmarks.acap` {first_sentence} ({link(ACAP)}). Milliseconds per frame, median of "
        f"{cpu_run['repeats']} warm calls over every frame, each cell {gpu_name} (jax {run['jax_version']}) / "
        f"{cpu_name} (jax {cpu_run['jax_version']}); the host solver (cholespy) on both.",
        "",
    ]
    return "\n".join(lines + table(head, rows))


def acap_solvers_table(root: Path) -> str:
    d = load(root, ACAP_SOLVERS)
    recs = d["records"]
    loads = [x for r in recs for x in (r.get("load_avg_1m") or [])]
    by = {(r["solver"], r["dtype"]): r for r in recs}
    dtypes = sorted({r["dtype"] for r in recs})

    def cg_steps(r: dict) -> str:
        if r["cg_steps"] is None:
            return "-"
        return f"{r['cg_steps']}" + ("" if r["cg_converged"] else " (not converged)")

    cells = (
        lambda r: num(r["decode"]["call_ms_median"]),
        lambda r: num(r["cholespy_solve_all_ms"]),
        lambda r: num(r["decode_over_solve"]),
        cg_steps,
        lambda r: num(r["max_dev_from_host"], 2),
    )
    rows = []
    for solver in d["solvers"]:
        rs = [by[(solver, t)] for t in dtypes]
        rows.append([solver] + [" / ".join(cell(r) for r in rs) for cell in cells])
    head = [
        "solver",
        f"decode, {recs[0]['frames']} frames (ms)",
        "bare cholespy solve, same rhs (ms)",
        "decode / solve",
        "CG steps (converged)",
        "max deviation from host (x bbox diag)",
    ]
    load_text = f", load average {min(loads):g}-{max(loads):g}: compare ratios within the table" if loads else ""
    lines = [
        f"{Path(d['data']).name}, {recs[0]['vertices']:,} vertices, {short_hardware(recs[0]['cpu'])} (CPU only, "
        f"jax {d['jax_version']}, {d['date'][:10]}{load_text}; `python -m benchmarks.acap --skip-big --repeats "
        f"{d['repeats']}`, {link(ACAP_SOLVERS)}). Each cell "
        + " / ".join(short_dtype(t) for t in dtypes)
        + "; decode: the default (one refinement step), all frames in one call.",
        "",
    ]
    return "\n".join(lines + table(head, rows))


def components_table(root: Path) -> str:
    t2, t4, t5 = load(root, C_TABLE2), load(root, C_TABLE4), load(root, C_TABLE5)
    old4, ft = load(root, C_PAPER_KZ), load(root, C_FINETUNE)
    fig6 = load(root, C_FIG6)
    rows = []

    def erms(v: float) -> str:
        return fixed(v, 2)

    def sted(v: float) -> str:
        return fixed(v, 4)

    def kept(r: dict) -> str:
        return " + ".join(map(str, r["kept_per_level"])) if r.get("kept_per_level") else "-"

    def row(table_name, model, tests, eq8, kept_cell, paper, hardware, source):
        rows.append(
            [
                table_name,
                model,
                slashed([t["erms"] for t in tests], erms),
                slashed([t.get("erms_by_normalization", {}).get("diameter-first-shape") for t in tests], erms),
                slashed([t["sted"] for t in tests], sted),
                slashed(eq8),
                kept_cell,
                paper,
                f"{short_hardware(hardware)}, {source}",
            ]
        )

    d4 = t4["rows"]["horse-gallop/default"]
    row(
        "2, 4",
        "multiscale, default: Kz = 2, 5, 2,000 epochs (joint, attention)",
        [d4["test"]],
        [d4["test"]["max_relative_squared_error"]],
        kept(d4),
        "6.92 / 0.0336",
        t4["hardware"],
        link(C_TABLE4),
    )
    p4 = old4["rows"]["horse-gallop/default"]["test"]
    row(
        "2",
        "multiscale, `paper-kz`: Kz = 10, 5, 10,000 epochs",
        [p4],
        [p4["max_relative_squared_error"]],
        "-",
        "6.92 / 0.0336",
        old4["hardware"],
        link(C_PAPER_KZ),
    )
    for key, label in (
        ("tan", "Tan et al."),
        ("pca", "PCA, ACAP features"),
        ("pca-xyz", "PCA, coordinates"),
        ("splocs", "SPLOCS (coordinates)"),
    ):
        r = t2["rows"][f"horse-gallop/{key}"]
        paper = PAPER_TABLE2.get(key, "-")
        row("2", label, [r["test"]], [None], kept(r), paper, t2["hardware"], link(C_TABLE2))
    keys4 = ("separate", "no-attention-separate", "no-attention")
    found4 = [k for k in keys4 if f"horse-gallop/{k}" in t4["rows"]]
    row(
        "4",
        " / ".join(LABEL4[k] for k in found4),
        [t4["rows"][f"horse-gallop/{k}"]["test"] for k in found4],
        [t4["rows"][f"horse-gallop/{k}"]["test"]["max_relative_squared_error"] for k in found4],
        " / ".join(kept(t4["rows"][f"horse-gallop/{k}"]) for k in found4),
        slashed([PAPER_TABLE4[k] for k in found4], erms) + " (Erms)",
        t4["hardware"],
        link(C_TABLE4),
    )
    keys5 = [k for k in ("levels1", "default", "levels3", "paper-kz-levels1") if f"horse-gallop/{k}" in t5["rows"]]
    tests = [t5["rows"][f"horse-gallop/{k}"]["test"] for k in keys5]
    row(
        "5",
        " / ".join(LABEL5[k] for k in keys5),
        tests,
        [t["max_relative_squared_error"] for t in tests],
        " / ".join(kept(t5["rows"][f"horse-gallop/{k}"]) for k in keys5),
        "eq. 8: " + slashed([PAPER_TABLE5[k] for k in keys5]),
        t5["hardware"],
        link(C_TABLE5),
    )
    r = ft["multiscale_finetuned_3000_rigid_plus1000_generated400_round6"]["evaluate"]["test"]
    row(
        "2",
        "Kz = 10, 5 + `components finetune` (3,000 + 6 x 1,000 steps)",
        [r],
        [r["max_relative_squared_error"]],
        "-",
        "6.92 / 0.0336",
        ft["hardware"],
        link(C_FINETUNE),
    )
    samba = [t2["rows"].get(f"samba/{k}") for k in ("multiscale", "tan", "pca", "pca-xyz", "splocs")]
    if all(samba):
        row(
            "2 (samba)",
            "multiscale default / Tan et al. / PCA, features / PCA, coordinates / SPLOCS",
            [x["test"] for x in samba],
            [samba[0]["test"]["max_relative_squared_error"], None, None, None, None],
            kept(samba[0]),
            "-",
            t2["hardware"],
            link(C_TABLE2),
        )
    head = [
        "paper table",
        "model",
        "test Erms",
        "test Erms, diameter 1",
        "test STED",
        "max eq. 8",
        "kept per level",
        "paper Erms / STED",
        "hardware, source",
    ]
    timing = d4.get("timing", {})
    f_ms, f_tan = fig6["rows"]["horse-gallop/multiscale"]["20"], fig6["rows"]["horse-gallop/tan"]["20"]
    lines = [
        "horse-gallop: every 10th shape trains (5), the other 43 test; Erms in the paper's units (unit ball, "
        "x 1000) and as the group's scalemodel.m scales (the first shape in a ball of diameter 1); max eq. 8: the "
        "largest relative squared error of the features over the test shapes; kept "
        "per level: components left by the redundant-component removal (eq. 7, eps2 = 0.01).",
        "",
    ]
    tail = [
        "",
        "Default training (`jaxdeform components train`, Kz = 2, 5, 2,000 epochs): compile "
        f"{fixed(timing.get('compile_s'), 1)} s + {fixed(timing.get('run_s'), 1)} s on "
        f"{short_hardware(t4['hardware'])} ({link(C_TABLE4)}). Editing toward 8 unseen shapes with 20 controls "
        f"(Fig. 6, Kz = 10, 5): mean error {num(f_ms['mean_error'])} of the diagonal (multiscale) against "
        f"{num(f_tan['mean_error'])} (Tan et al.), {short_hardware(fig6['hardware'])} ({link(C_FIG6)}).",
    ]
    return "\n".join(lines + table(head, rows) + tail)


def cloth_table(root: Path) -> str:
    d = load(root, CLOTH)
    sheet, disk = d["datasets"]["sheet"], d["datasets"]["disk"]
    labels = [
        ("upsampled_coarse", "coarse simulation, Loop-upsampled"),
        ("ours", "**ours**: DeformTransformer on TS-ACAP (teacher forcing, the paper's)"),
        ("ours_self_fed", "ours, self-fed in training (`--self-feed 0.5`, the CLI's default)"),
        ("ours_direct", "ours_direct: the paper's direct coarse-to-fine feature mapping"),
        ("no_temporal", "no temporal module (per-frame encoder-decoder)"),
        ("lstm", "LSTM in place of the transformer"),
        ("acap", "transformer on plain ACAP"),
        ("coords", "transformer on coordinates"),
        ("linear_residual", "reference: upsampled coarse + a ridge-regressed linear map"),
    ]

    def accuracy(rmse: float, sted: float) -> str:
        return f"{fixed(rmse, 4)} / {fixed(sted, 3)}"

    def floor(ds: dict) -> str:
        return accuracy(ds["floor"]["perturbed_fine_rmse"], ds["floor"]["perturbed_fine_sted"])

    def speed(ds: dict) -> str:
        t = ds["timing"]
        return (
            f"{fixed(t['ours_total'] * 1e3, 1)} ms / {num(t['fine_simulation'] * 1e3)} ms "
            f"(**{fixed(t['speedup'], 1)}x**)"
        )

    def name(label: str, ds: dict) -> str:
        v, split = ds["data"]["vertices"], ds["data"]["split"]
        return (
            f"{label} ({v['coarse']:,} / {v['fine']:,} vertices, {len(split['train'])} / {len(split['test'])} "
            "train / test sequences)"
        )

    rows = [
        [label, accuracy(sheet["rmse"][m], sheet["sted"][m]), accuracy(disk["rmse"][m], disk["sted"][m])]
        for m, label in labels
    ]
    rows.append(
        ["floor: the fine simulation against itself from a start perturbed by 0.1 mm", floor(sheet), floor(disk)]
    )
    rows.append(
        ["per frame: ours (coarse simulation to refined fine cloth) / the fine simulation", speed(sheet), speed(disk)]
    )
    head = ["test RMSE (m) / STED", name("SHEET", sheet), name("DISK", disk)]
    lines = [
        f"`python -m experiments.cloth.run --datasets sheet disk` (CPU only, float32; {CLOTH_HARDWARE}; the "
        f'JSON: "{d["machine"]}"; {link(CLOTH)}).',
        "",
    ]
    return "\n".join(lines + table(head, rows))


def parts_table(root: Path) -> str:
    d = load(root, PARTS)
    rows = []
    for r in d["results"]:
        o, p = r["ours"], r["dem_bones_rigid"]
        pps, its = o["parts_per_stage"], o["iterations"]
        rows.append(
            [
                r["dataset"],
                str(r["shapes"]),
                f"{pps['coarse']}/{pps['refine']}/{pps['final']}",
                f"{its['coarse']}/{its['refine']}/{its['final']}",
                fixed(o["rmse_over_diagonal"], 5),
                fixed(o["seconds"], 1),
                fixed(p["rmse_over_diagonal"], 5),
                fixed(p["seconds"], 1),
                f"{o['max_joint_gap_over_diagonal']:.0e}".replace("e-0", "e-"),
            ]
        )
    head = [
        "data",
        "shapes",
        "parts (coarse/refined/final)",
        "AECM iterations (coarse/refine/final)",
        "ours RMSE / diag",
        "ours s",
        "Dem Bones rigid, same bones: RMSE / diag",
        "Dem Bones s",
        "max joint gap / diag",
    ]
    lines = [
        f"`python -m experiments.parts.run` ({d['hardware']}, {d['date']}; {link(PARTS)}, transcribed from "
        "that run's table). Dem Bones: py-dem-bones with one influence per vertex, as many bones as our parts.",
        "",
    ]
    return "\n".join(lines + table(head, rows))


def handles_table(root: Path) -> str:
    d = load(root, HANDLES)
    dm, ds, rb, pose = d["distill_mesh"], d["distill_seconds"], d["rebind_ms"], d["pose"]
    by_faces = {t["faces"]: t for t in d["timing"]}
    at = max(f for f, t in by_faces.items() if t.get("arap"))  # the largest mesh the baselines ran on
    t = by_faces[at]
    distill = " / ".join(fixed(ds[k], 1) for k in ("render", "features", "field"))
    rows = [
        [
            f"distil {dm['name']} ({dm['vertices']:,} vertices), {dm['views']} views at {dm['resolution']}: "
            "render / features / field / total",
            f"{distill} / **{fixed(ds['total'], 1)} s**",
            "-",
        ],
        [
            "rebind (weights of a new handle set): " + " / ".join(rb) + " handles",
            " / ".join(num(v) for v in rb.values()) + " ms",
            " / ".join(str(PAPER_REBIND_MS[k]) for k in rb) + " ms",
        ],
        [
            f"pose, {pose['faces']:,} faces, {pose['handles']} affine handles",
            f"{fixed(pose['pose_ms'], 1)} ms = {round(pose['fps'])} frames/s",
            "-",
        ],
        [
            f"bind 10 handles at {at:,} faces: DFD / ARAP (libigl) / biharmonic (libigl)",
            slashed([t["dfd"]["bind"], t["arap"]["bind"], t["biharmonic"]["bind"]]) + " s",
            "-",
        ],
        [
            "symmetry score (eq. 9, detected below 0.1): " + ", ".join(d["symmetry"]),
            ", ".join(num(min(p["score"] for p in s["planes"]), 2) for s in d["symmetry"].values()),
            "-",
        ],
    ]
    lines = [
        f'`python -m experiments.handles.run` ({HANDLES_HARDWARE}; the JSON: "{d["machine"]}"; '
        f"{link(HANDLES)}). The paper's figures ran on an A40 GPU.",
        "",
    ]
    return "\n".join(lines + table(["what", "ours", "paper"], rows))


TABLES: dict[str, Callable[[Path], str]] = {
    "acap": acap_table,
    "acap-solvers": acap_solvers_table,
    "components": components_table,
    "cloth": cloth_table,
    "parts": parts_table,
    "handles": handles_table,
}


# ------------------------------------------------------------------------------------------------- the README


def _pattern(name: str) -> re.Pattern:
    return re.compile(rf"(<!-- results:{re.escape(name)} -->\n)(.*?)(<!-- /results:{re.escape(name)} -->)", re.S)


def render(readme_text: str, root: Path) -> str:
    """``readme_text`` with every table replaced by what the JSON under ``root`` gives."""
    text = readme_text
    for name, make in TABLES.items():
        pattern = _pattern(name)
        if len(pattern.findall(text)) != 1:
            raise SystemExit(f"README: expected one '<!-- results:{name} -->' ... '<!-- /results:{name} -->' block.")
        block = make(root) + "\n"
        if block.splitlines()[-1].startswith("|"):
            block += "\n"  # a table ends at a blank line: without one the closing marker would be read as a row
        text = pattern.sub(lambda m: m.group(1) + block + m.group(3), text)
    return text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="compare only; exit 1 if README.md's tables differ")
    p.add_argument("--readme", type=Path, default=ROOT / "README.md")
    p.add_argument(
        "--results-root",
        type=Path,
        default=ROOT,
        help="the folder holding benchmarks/results/ and experiments/*/results/ (default: the repository)",
    )
    args = p.parse_args(argv)
    current = args.readme.read_text()
    try:
        new = render(current, args.results_root)
    except (OSError, KeyError, ValueError) as e:  # a missing or malformed JSON
        print(f"experiments.report: cannot render the tables from {args.results_root}: {e}", file=sys.stderr)
        return 2
    if args.check:
        if new == current:
            print(f"{args.readme}: the results tables match the JSON.")
            return 0
        sys.stdout.writelines(
            difflib.unified_diff(current.splitlines(True), new.splitlines(True), str(args.readme), "from the JSON")
        )
        print(
            f"{args.readme}: the results tables differ from the JSON; run python -m experiments.report.",
            file=sys.stderr,
        )
        return 1
    if new != current:
        fd, tmp = tempfile.mkstemp(dir=args.readme.parent, prefix=".README.", suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            f.write(new)
        os.chmod(tmp, os.stat(args.readme).st_mode & 0o777)
        os.replace(tmp, args.readme)
    print(f"{args.readme}: {len(TABLES)} tables written.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
