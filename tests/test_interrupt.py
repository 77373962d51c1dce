"""Ctrl-C that cannot be lost (run.interrupt): the two ways a long job used to miss it."""

import os
import signal
import subprocess
import sys

import pytest

from virtual_vehicle.run.interrupt import Interrupts, without_sigint


def test_a_ctrl_c_whose_exception_a_finaliser_swallows_is_still_seen_and_not_reported_twice():
    class Finalised:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)  # arrives while a finaliser runs: its KeyboardInterrupt is dropped
            sum(range(10_000))

    before, reported = signal.getsignal(signal.SIGINT), []
    hook, sys.unraisablehook = sys.unraisablehook, reported.append
    try:
        with Interrupts() as stop:
            obj = Finalised()
            del obj  # the job runs on, unaware, as a Dask sweep once did
            assert stop.seen
            with pytest.raises(KeyboardInterrupt):
                stop.check()
        assert sys.unraisablehook == reported.append and reported == []  # nothing printed as "Exception ignored"
        obj = Finalised()
        del obj  # outside, Python's own handler: the interrupt is dropped with only that report to show for it
        assert [type(r.exc_value) for r in reported] == [KeyboardInterrupt]
    finally:
        sys.unraisablehook = hook
    assert signal.getsignal(signal.SIGINT) is before


def test_sigterm_interrupts_only_when_asked_and_handlers_come_back():
    before = signal.getsignal(signal.SIGTERM)
    with Interrupts(terminate=True) as stop:
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)
            sum(range(10_000))
        assert stop.seen
    assert signal.getsignal(signal.SIGTERM) is before
    with Interrupts() as stop:
        assert signal.getsignal(signal.SIGTERM) is before
    assert not stop.seen


def test_a_child_started_without_sigint_ignores_a_terminals_ctrl_c():
    code = "import signal; print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN)"
    with without_sigint():
        inside = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    outside = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert (inside.strip(), outside.strip()) == ("True", "False")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
