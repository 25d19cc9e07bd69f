"""experiments/report.py: the README's results tables are what the committed JSON gives, and the README stays short."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

from experiments import report

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "experiments.report", *args], cwd=ROOT, capture_output=True, text=True, timeout=120
    )


def _copy_results(dst: Path) -> None:
    """The JSON every table reads, at the same relative paths under ``dst``."""
    for name in dir(report):
        rel = getattr(report, name)
        if name.isupper() and isinstance(rel, str) and rel.endswith(".json"):
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(ROOT / rel, dst / rel)


def test_readme_tables_match_the_committed_json():
    proc = _run("--check")
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]


def test_check_fails_when_a_number_in_the_json_changes(tmp_path):
    readme = tmp_path / "README.md"
    shutil.copy(ROOT / "README.md", readme)
    results = tmp_path / "results"
    _copy_results(results)
    args = ("--check", "--readme", str(readme), "--results-root", str(results))
    proc = _run(*args)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]  # the copies render the same text

    path = results / report.CLOTH
    data = json.loads(path.read_text())
    data["datasets"]["sheet"]["rmse"]["ours"] += 0.01  # 0.0242 -> 0.0342 in the README's cloth table
    path.write_text(json.dumps(data))
    proc = _run(*args)
    assert proc.returncode == 1
    assert "0.0342" in proc.stdout  # the diff shows the new figure
    assert readme.read_text() == (ROOT / "README.md").read_text()  # --check writes nothing

    # without --check the tables are rewritten, and then they match
    assert _run("--readme", str(readme), "--results-root", str(results)).returncode == 0
    assert _run(*args).returncode == 0
    assert "0.0342 / 0.047" in readme.read_text()


def test_check_fails_when_a_table_block_is_missing(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text((ROOT / "README.md").read_text().replace("<!-- /results:parts -->", ""))
    proc = _run("--check", "--readme", str(readme))
    assert proc.returncode != 0
    assert "results:parts" in proc.stderr


def test_readme_is_a_short_reference():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 260, len(lines)
    first = "\n".join(lines[:40])
    assert "make test" in first and "make demo" in first
