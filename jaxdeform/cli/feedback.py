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
#: seconds without output (and no progress bar open) after which a command's status line is shown again
IDLE = 2.0


class _Ticker:
    """A status line on a terminal's stderr that shows the seconds elapsed until :meth:`stop`."""

    def __init__(self, text: str, stream, t0: float | None = None):
        self.text, self.stream = f"{PROG}: {text}", stream
        self.t0 = time.perf_counter() if t0 is None else t0
        self.done = threading.Event()
        self.lock = threading.Lock()
        self._write(f"{self.text} {time.perf_counter() - self.t0:.0f} s")
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
        self.lock = threading.RLock()
        self.last = time.perf_counter()  # when anything else was last written (a session's streams set it)

    def now(self, text: str | None, t0: float | None = None) -> None:
        """Start the status line of the next wait (``text`` None: none), ending the current one; ``t0``: the
        clock the line counts from (default: now)."""
        with self.lock:
            self.stop()
            live = self.live and text is not None
            self.ticker = _Ticker(text, self.stream or sys.stderr, t0) if live else None

    def stop(self) -> None:
        """End the current status line, if any."""
        with self.lock:
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
            self._waiting.last = time.perf_counter()
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
    ends the status line, so lines never mix. Open progress bars are redrawn once per :data:`TICK`; with none open
    and nothing written for :data:`IDLE` seconds, the command's line is shown again.
    """
    global _SESSION
    out, err = sys.stdout, sys.stderr
    w = Waiting(not getattr(args, "quiet", False) and err.isatty(), stream=err)
    sys.stdout, sys.stderr = _EndingStatus(out, w), _EndingStatus(err, w)
    _SESSION = w
    done = threading.Event()
    if w.live:
        threading.Thread(target=_watch, args=(w, text, done), daemon=True).start()
    w.now(text)
    try:
        yield w
    finally:
        done.set()
        w.stop()
        sys.stdout, sys.stderr, _SESSION = out, err, None


def _open_bars() -> list:
    """The open, enabled tqdm progress bars of the process (none where tqdm was never imported)."""
    std = sys.modules.get("tqdm.std")
    bars = list(getattr(std.tqdm, "_instances", ())) if std is not None else []
    return [bar for bar in bars if not getattr(bar, "disable", True)]


def _watch(w: Waiting, text: str, done: threading.Event) -> None:
    """Until ``done``, once per :data:`TICK`: redraw every open progress bar (a bar whose steps are long still
    shows its elapsed time moving), or, with no bar open and nothing written for :data:`IDLE` seconds, show the
    command's status line ``text`` again, counting from the command's start."""
    start = time.perf_counter()
    while not done.wait(TICK):
        bars = _open_bars()
        for bar in bars:
            with contextlib.suppress(Exception):  # a bar closed meanwhile
                bar.refresh()
        with w.lock:
            idle = time.perf_counter() - w.last > IDLE
            if not bars and w.ticker is None and idle and not done.is_set():
                w.now(text, t0=start)


def settle() -> None:
    """From here the running command waits on its user (a server), not on work: no more status lines."""
    if _SESSION is not None:
        with _SESSION.lock:
            _SESSION.stop()
            _SESSION.live = False


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
