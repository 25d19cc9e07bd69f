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

    def __init__(self, text: str):
        self.text, self.t0 = f"{PROG}: {text}", time.perf_counter()
        self.done = threading.Event()
        self.lock = threading.Lock()
        self._write(f"{self.text} 0 s")
        self.thread = threading.Thread(target=self._tick, daemon=True)
        self.thread.start()

    def _write(self, line: str, end: str = "") -> None:
        sys.stderr.write(f"\r\x1b[K{line}{end}")
        sys.stderr.flush()

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


@contextlib.contextmanager
def waiting(args: argparse.Namespace, text: str | None):
    """A live status line ``jaxdeform: <text> N s`` on stderr for the block's wait, when stderr is a terminal (a
    captured stderr keeps the one-line error contract) and ``--quiet`` is not given. The line counts the seconds
    once per :data:`TICK` and ends with the time taken when the block ends or when the yielded ``say`` first
    prints. ``text`` None: no status line.

    **Yields:** ``say(line)``: prints ``line`` on stdout (the status line ended first); pass it as a ``log`` to
    library calls whose own output should end the wait (a training's first line).
    """
    live = text is not None and not getattr(args, "quiet", False) and sys.stderr.isatty()
    ticker = _Ticker(text) if live else None

    def say(line: str) -> None:
        if ticker is not None:
            ticker.stop()
        print(line, flush=True)

    try:
        yield say
    finally:
        if ticker is not None:
            ticker.stop()
