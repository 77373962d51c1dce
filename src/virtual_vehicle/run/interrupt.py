"""Ctrl-C (SIGINT) and SIGTERM that cannot be lost while a long job runs.

Python turns SIGINT into a KeyboardInterrupt raised wherever the main thread happens to be. When that is inside a
finaliser (a library object's ``__del__``, a weakref callback), the exception is printed as "Exception ignored" and
dropped, and the job runs on as if nothing had happened; when a child process (ffmpeg) dies of the same signal
first, the job sees a broken pipe instead of the interrupt. :class:`Interrupts` records every such signal in a flag
as well as raising, so a job can ask :attr:`Interrupts.seen` at its own checkpoints and treat any error that follows
a signal as the interrupt it is; the "Exception ignored" report of a swallowed interrupt is not printed (the job
reports the interrupt itself).
"""

from __future__ import annotations

import signal
import sys
import threading

__all__ = ["Interrupts", "without_sigint"]


class Interrupts:
    """While entered (on the main thread), SIGINT and, with ``terminate=True``, SIGTERM set :attr:`seen` and raise
    KeyboardInterrupt, and a KeyboardInterrupt dropped by a finaliser is not reported; the previous handlers come
    back on exit. Off the main thread (where Python cannot handle
    signals) it does nothing and :attr:`seen` stays False.

    >>> with Interrupts() as stop:
    ...     stop.seen
    False
    """

    def __init__(self, terminate: bool = False):
        self.seen = False
        self._signals = (signal.SIGINT, signal.SIGTERM) if terminate else (signal.SIGINT,)
        self._previous: dict[int, object] = {}
        self._hook = None

    def _handler(self, signum, frame):
        self.seen = True
        raise KeyboardInterrupt

    def _unraisable(self, unraisable) -> None:
        if not (self.seen and isinstance(unraisable.exc_value, KeyboardInterrupt)):
            self._hook(unraisable)

    def __enter__(self) -> "Interrupts":
        if threading.current_thread() is threading.main_thread():
            for sig in self._signals:
                if signal.getsignal(sig) is not signal.SIG_IGN:  # a signal ignored on purpose stays ignored
                    self._previous[sig] = signal.signal(sig, self._handler)
            self._hook, sys.unraisablehook = sys.unraisablehook, self._unraisable
        return self

    def check(self) -> None:
        """Raise KeyboardInterrupt if a signal came since entering (its own raise may have been swallowed)."""
        if self.seen:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, signal.SIG_DFL if previous is None else previous)  # None: a handler set outside Python
        self._previous.clear()
        if self._hook is not None:
            sys.unraisablehook, self._hook = self._hook, None


class without_sigint:
    """While entered on the main thread, SIGINT is ignored; child processes started inside inherit that and are
    left alone by a terminal's Ctrl-C (which reaches the whole process group), so the job that started them stops
    them itself. Off the main thread it does nothing."""

    def __enter__(self) -> "without_sigint":
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
