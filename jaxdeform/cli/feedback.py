"""Feedback during a command's waits: a live status line on a terminal (re-exported by ``common``)."""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time

#: the program name every line of the command line starts with
PROG = "jaxdeform"


#: seconds between two updates of a live status line
TICK = 1.0


class _Ticker:
    """A status line on a terminal's stderr that shows the seconds elapsed until :meth:`stop`."""

    def __init__(self, text: str, stream):
        self.text, self.t0, self.stream = f"{PROG}: {text}", time.perf_counter(), stream
        self.done = threading.Event()
        self.lock = threading.Lock()
        self._write(f"{self.text} 0 s")
        self.thread = threading.Thread(target=self._tick, daemon=True)
        self.thread.start()

    def _write(self, line: str, end: str = "") -> None:
        self.stream.write(f"\r\x1b[K{line}{end}")
        self.stream.flush()

    def _tick(self) -> None:
        while not self.done.wait(TICK):
            with self.lock:
                if not self.done.is_set():
                    self._write(f"{self.text} {time.perf_counter() - self.t0:.0f} s")

    def stop(self) -> None:
        """End the line with the time taken (once; later calls do nothing)."""
        with self.lock:
            if self.done.is_set():
                return
            self.done.set()
            self._write(f"{self.text} {time.perf_counter() - self.t0:.1f} s", "\n")


class Waiting:
    """What :func:`waiting` yields: the status line of a command's current wait, on a terminal.

    ``now(text)`` ends the current line (with its time) and starts one for the next wait; calling the object
    with a line ends the status line, then prints the line (on stdout, or ``file``).
    """

    def __init__(self, live: bool, stream=None):
        self.live, self.ticker, self.stream = live, None, stream

    def now(self, text: str | None) -> None:
        """Start the status line of the next wait (``text`` None: none), ending the current one."""
        self.stop()
        self.ticker = _Ticker(text, self.stream or sys.stderr) if self.live and text is not None else None

    def stop(self) -> None:
        """End the current status line, if any."""
        if self.ticker is not None:
            self.ticker.stop()
            self.ticker = None

    def __call__(self, line: str, file=None) -> None:
        self.stop()
        print(line, file=file or sys.stdout, flush=True)


class _EndingStatus:
    """A text stream that ends the session's status line before anything else is written to it."""

    def __init__(self, stream, waiting: Waiting):
        self._stream, self._waiting = stream, waiting

    def write(self, text: str) -> int:
        if text:
            self._waiting.stop()
        return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


#: the status of the command running in this process (:func:`session`), None outside one
_SESSION: Waiting | None = None


@contextlib.contextmanager
def session(args: argparse.Namespace, text: str):
    """The status line of a whole command: ``jaxdeform: <text> N s`` from its start (JAX's import included) until
    the command writes anything, on a terminal's stderr, unless ``--quiet``. Within it, :func:`waiting` shows the
    command's own waits; any other output on stdout or stderr (results, warnings, progress bars, errors) first
    ends the status line, so lines never mix; open progress bars are redrawn once per :data:`TICK`.
    """
    global _SESSION
    out, err = sys.stdout, sys.stderr
    w = Waiting(not getattr(args, "quiet", False) and err.isatty(), stream=err)
    sys.stdout, sys.stderr = _EndingStatus(out, w), _EndingStatus(err, w)
    _SESSION = w
    done = threading.Event()
    if w.live:
        threading.Thread(target=_refresh_bars, args=(done,), daemon=True).start()
    w.now(text)
    try:
        yield w
    finally:
        done.set()
        w.stop()
        sys.stdout, sys.stderr, _SESSION = out, err, None


def _refresh_bars(done: threading.Event) -> None:
    """Redraw every open tqdm progress bar once per :data:`TICK` until ``done``, so that a bar whose steps are
    long (a simulated sequence, a training chunk) still shows its elapsed time moving."""
    while not done.wait(TICK):
        std = sys.modules.get("tqdm.std")
        if std is None:
            continue
        for bar in list(getattr(std.tqdm, "_instances", ())):
            if not getattr(bar, "disable", True) and not done.is_set():
                with contextlib.suppress(Exception):  # a bar closed meanwhile
                    bar.refresh()


@contextlib.contextmanager
def waiting(args: argparse.Namespace, text: str | None):
    """Live status lines ``jaxdeform: <text> N s`` on stderr for the block's waits, when stderr is a terminal (a
    captured stderr keeps the one-line error contract) and ``--quiet`` is not given. A line counts the seconds
    once per :data:`TICK` and ends with the time taken when its wait ends. ``text`` None: no line until
    ``now``.

    **Yields:** a :class:`Waiting`: ``now(text)`` for the next wait; ``say(line)`` prints ``line`` after ending
    the status line (pass it as a ``log`` to library calls whose own output ends the wait, a training's first
    line).
    """
    w = _SESSION or Waiting(not getattr(args, "quiet", False) and sys.stderr.isatty())
    w.now(text)
    try:
        yield w
    finally:
        w.stop()
