"""The terminal-silence measure of benchmarks/feedback.py on two tiny processes of known timing (it measures
nothing of the library; `python -m benchmarks.feedback` runs the README's examples)."""

import sys

from benchmarks.feedback import EXAMPLES, silence


def test_the_longest_silence_of_a_known_process(tmp_path):
    code = "import time; print('a', flush=True); time.sleep(1.5); print('b', flush=True); time.sleep(0.2)"
    r = silence([sys.executable, "-c", code], tmp_path)
    assert r["rc"] == 0 and r["writes"] >= 2 and not r["stopped_at_limit"]
    assert 1.3 <= r["longest_silence_s"] <= 3.0 and r["silence_ends_at_s"] <= r["seconds"]


def test_a_command_past_the_limit_is_terminated(tmp_path):
    r = silence([sys.executable, "-c", "import time; time.sleep(30)"], tmp_path, limit=1.0)
    assert r["stopped_at_limit"] and r["rc"] != 0 and r["seconds"] < 10


def test_the_examples_are_the_readme_commands():
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    for label, _ in EXAMPLES:
        assert f"jaxdeform {label} " in readme, label
