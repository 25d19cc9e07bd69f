"""Ctrl-C and SIGTERM end a command with one line and status 130 / 143 and leave no partial output; an
interrupted ``components train`` keeps its checkpoints and ``--resume`` ends bit-identical to an uninterrupted
run. Each command runs in a fresh process (``python -m jaxdeform``)."""

import io
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxdeform.components import run as crun
from jaxdeform.data.synthetic import bending_tube_sequence
from jaxdeform.mesh.io import save_mesh

EPOCHS = 3000  # checkpoints every 300 epochs: the first appears well before the end


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    vertices, faces = bending_tube_sequence(n_frames=12, n_around=8, n_along=16)
    d = tmp_path_factory.mktemp("tube")
    for k in range(len(vertices)):
        save_mesh(d / f"f{k}.obj", vertices[k], faces)
    return d


def _train_cmd(seq_dir, out, *extra):
    return [sys.executable, "-m", "jaxdeform", "components", "train", str(seq_dir), "--out", str(out)] + [
        "--config",
        "test",
        "--epochs",
        str(EPOCHS),
        "--quiet",
        *extra,
    ]


def _wait_for(predicate, proc, timeout=240.0):
    t0 = time.monotonic()
    while not predicate():
        assert proc.poll() is None, "the command ended before it could be interrupted"
        assert time.monotonic() - t0 < timeout, "timed out waiting for the command"
        time.sleep(0.05)


def _interrupt(cmd, sig, ready):
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        _wait_for(ready, proc)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, out, err


def _env():
    env = dict(os.environ)
    env.setdefault("JAX_PLATFORMS", "cpu")
    return env


def _has_checkpoint(partial):
    return (partial / "params").is_dir() and any(p.name.isdigit() for p in (partial / "params").iterdir())


def _one_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("jaxdeform: interrupted; "), err
    return lines[0]


@pytest.mark.parametrize("sig, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupt_before_a_checkpoint_leaves_nothing(seq_dir, tmp_path, sig, status):
    out = tmp_path / "run"
    partial = crun.partial_folder(out)
    rc, _, err = _interrupt(_train_cmd(seq_dir, out), sig, partial.exists)
    assert rc == status, err
    assert "nothing was written" in _one_line(err)
    assert list(tmp_path.iterdir()) == []  # neither the run nor its partial folder


def test_sigterm_keeps_the_checkpoint_and_resume_is_bit_identical(seq_dir, tmp_path):
    reference = tmp_path / "reference"
    done = subprocess.run(_train_cmd(seq_dir, reference), capture_output=True, text=True, env=_env())
    assert done.returncode == 0, done.stderr

    out = tmp_path / "run"
    partial = crun.partial_folder(out)
    rc, _, err = _interrupt(_train_cmd(seq_dir, out), signal.SIGTERM, lambda: _has_checkpoint(partial))
    assert rc == 143, err
    line = _one_line(err)
    assert "checkpoint kept" in line and str(partial) in line and "--resume" in line
    assert partial.is_dir() and not out.exists()

    resumed = subprocess.run(_train_cmd(seq_dir, out, "--resume"), capture_output=True, text=True, env=_env())
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stdout and not partial.exists()
    np.testing.assert_array_equal(np.load(out / "history.npy"), np.load(reference / "history.npy"))
    a, b = crun.load(out), crun.load(reference)
    import jax
    from flax import nnx

    for x, y in zip(jax.tree.leaves(nnx.state(a.model)), jax.tree.leaves(nnx.state(b.model)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_resume_refuses_a_partial_fit_of_other_settings(seq_dir, tmp_path):
    out = tmp_path / "run"
    partial = crun.partial_folder(out)
    rc, _, err = _interrupt(_train_cmd(seq_dir, out), signal.SIGINT, lambda: _has_checkpoint(partial))
    assert rc == 130, err
    cmd = _train_cmd(seq_dir, out, "--resume", "--seed", "7")
    done = subprocess.run(cmd, capture_output=True, text=True, env=_env())
    assert done.returncode == 2
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "other settings (seed)" in lines[0], done.stderr
    assert partial.is_dir() and not out.exists()  # the kept fit is untouched


def test_long_commands_say_what_they_wait_for_on_a_terminal(seq_dir, tmp_path):
    """On a terminal, acap encode shows a live status line on stderr from its start, then one for its encoding,
    each ended with the time taken; --quiet and a captured stderr print none (the one-line error contract)."""
    import pty

    def run(*extra):
        out = tmp_path / f"f{len(extra)}.npz"
        cmd = [sys.executable, "-m", "jaxdeform", "acap", "encode", str(seq_dir), "--reference"]
        cmd += [str(seq_dir / "f0.obj"), "--out", str(out), *extra]
        leader, follower = pty.openpty()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=follower, text=True, env=_env())
        os.close(follower)
        chunks = []
        while True:
            try:
                data = os.read(leader, 4096)
            except OSError:  # the terminal closed with the process
                break
            if not data:
                break
            chunks.append(data)
        proc.wait(timeout=240)
        os.close(leader)
        assert proc.returncode == 0
        return b"".join(chunks).decode()

    shown = [ln.split("\r\x1b[K")[-1] for ln in run().replace("\r\n", "\n").split("\n")]  # as a terminal shows it
    said = [ln for ln in shown if ln.strip()]
    assert said[0].startswith("jaxdeform: acap encode..."), said  # from the start: JAX's import, the reading
    assert said[-1].startswith("jaxdeform: encoding 12 frames x 128 vertices") and len(said) == 2, said
    assert all(re.search(r" \d+\.\d s$", line) for line in said), said  # each ended with the time taken
    assert [ln for ln in run("--quiet").splitlines() if ln.strip()] == []
    captured = subprocess.run(
        [sys.executable, "-m", "jaxdeform", "acap", "encode", str(seq_dir), "--reference", str(seq_dir / "f0.obj")]
        + ["--out", str(tmp_path / "c.npz")],
        capture_output=True,
        text=True,
        env=_env(),
    )
    assert captured.returncode == 0 and captured.stderr == ""


CLOTH_STEPS = 1000  # checkpoints every 100 steps


def test_cloth_train_resumes_bit_identical(tmp_path):
    """cloth train killed by SIGINT after a checkpoint keeps it; --resume ends with the losses and parameters of
    an uninterrupted training."""
    from test_cloth_cli import pair, write

    from jaxdeform.cloth.run import Run

    data = tmp_path / "data"
    write(data, [pair(k) for k in range(3)])

    def cmd(out, *extra):
        args = ["cloth", "train", str(data), "--out", str(out), "--steps", str(CLOTH_STEPS), "--quiet", *extra]
        return [sys.executable, "-m", "jaxdeform", *args]

    done = subprocess.run(cmd(tmp_path / "reference"), capture_output=True, text=True, env=_env())
    assert done.returncode == 0, done.stderr
    out = tmp_path / "run"
    partial = crun.partial_folder(out)

    def ready():
        return (partial / "checkpoints").is_dir() and any(p.name.isdigit() for p in (partial / "checkpoints").iterdir())

    rc, _, err = _interrupt(cmd(out), signal.SIGINT, ready)
    assert rc == 130, err
    assert "checkpoint kept" in _one_line(err) and partial.is_dir() and not out.exists()
    resumed = subprocess.run(cmd(out, "--resume"), capture_output=True, text=True, env=_env())
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stdout and not partial.exists()
    assert not (out / "checkpoints").exists()
    a, b = Run.load(out), Run.load(tmp_path / "reference")
    assert a.record["final_loss"] == b.record["final_loss"]
    import jax
    from flax import nnx

    for x, y in zip(jax.tree.leaves(nnx.state(a.model)), jax.tree.leaves(nnx.state(b.model)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


class Terminal(io.StringIO):
    """A captured stderr that says it is a terminal (what the status lines draw on)."""

    def isatty(self):
        return True


def test_the_status_line_counts_seconds_and_ends_before_other_output(monkeypatch, capsys):
    """common.waiting (cli/feedback.py) on a terminal: the line is redrawn once per TICK with the seconds elapsed, ended (a newline)
    before ``say`` prints on stdout, and not drawn again after; off the terminal or with --quiet it draws nothing."""
    import argparse

    from jaxdeform.cli import common, feedback

    monkeypatch.setattr(feedback, "TICK", 0.05)
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    with common.waiting(argparse.Namespace(quiet=False), "working...") as say:
        time.sleep(0.4)
        say("first line of the work's own output")
        drawn = term.getvalue()
        time.sleep(0.2)
    assert term.getvalue() == drawn  # nothing drawn after say ended the line
    frames = drawn.split("\r\x1b[K")[1:]
    assert len(frames) >= 4 and all(f.startswith("jaxdeform: working... ") for f in frames), frames
    assert frames[-1].endswith(" s\n") and not any(f.endswith("\n") for f in frames[:-1])
    assert capsys.readouterr().out == "first line of the work's own output\n"
    for args, stderr in (
        (argparse.Namespace(quiet=True), Terminal()),
        (argparse.Namespace(quiet=False), io.StringIO()),
    ):
        monkeypatch.setattr(sys, "stderr", stderr)
        with common.waiting(args, "working..."):
            time.sleep(0.1)
        assert stderr.getvalue() == ""


def test_the_session_status_line_ends_before_any_other_output(monkeypatch):
    """feedback.session: the command's status line runs from its start and is ended before the first write to
    stdout or stderr by anything else; the streams are restored afterwards."""
    import argparse

    from jaxdeform.cli import feedback

    monkeypatch.setattr(feedback, "TICK", 0.05)
    term, out = Terminal(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", term)
    monkeypatch.setattr(sys, "stdout", out)
    with feedback.session(argparse.Namespace(quiet=False), "acap encode..."):
        time.sleep(0.3)
        print("the result")
        drawn = term.getvalue()
        time.sleep(0.2)
        print("a warning", file=sys.stderr)
    assert sys.stdout is out and sys.stderr is term
    frames = drawn.split("\r\x1b[K")[1:]
    assert len(frames) >= 3 and all(f.startswith("jaxdeform: acap encode... ") for f in frames), frames
    assert frames[-1].endswith(" s\n") and out.getvalue() == "the result\n"
    assert term.getvalue() == drawn + "a warning\n"


def test_the_session_redraws_open_progress_bars(monkeypatch):
    """A bar whose step is long is redrawn once per TICK within a session (its elapsed time moves)."""
    import argparse

    from tqdm.auto import tqdm

    from jaxdeform.cli import feedback

    monkeypatch.setattr(feedback, "TICK", 0.05)
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    with feedback.session(argparse.Namespace(quiet=False), "cloth simulate..."):
        bar = tqdm(total=2, desc="slow step", file=sys.stderr, mininterval=0)
        time.sleep(0.5)  # one long step
        drawn = term.getvalue().count("slow step")
        bar.update(1)
        bar.close()
    assert drawn >= 4, term.getvalue()


def test_the_session_shows_its_line_again_after_idle_output_gaps(monkeypatch):
    """With no bar open and nothing written for IDLE seconds, the command's line comes back (counting from the
    command's start), and is ended again by the next output; feedback.settle (a server) ends that for good."""
    import argparse

    from jaxdeform.cli import feedback

    monkeypatch.setattr(feedback, "TICK", 0.05)
    monkeypatch.setattr(feedback, "IDLE", 0.2)
    term, out = Terminal(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", term)
    monkeypatch.setattr(sys, "stdout", out)
    with feedback.session(argparse.Namespace(quiet=False), "cloth train..."):
        print("features done")
        time.sleep(0.6)  # a gap without output: the line is back
        print("training")
        shown = term.getvalue()
        feedback.settle()
        time.sleep(0.6)
    lines = [ln.split("\r\x1b[K")[-1] for ln in shown.split("\n") if ln]
    assert len(lines) == 2 and all(ln.startswith("jaxdeform: cloth train... ") for ln in lines), lines
    assert float(lines[1].split()[-2]) >= 0.6  # the second counts from the command's start
    assert term.getvalue() == shown  # settled: nothing more
