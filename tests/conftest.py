"""Shared test helpers, and the hypothesis settings of every run."""

import atexit
import os
import shutil
import signal
import tempfile

import numpy as np
import pytest
from hypothesis import assume, settings

from virtual_vehicle.engine import dynamics
from virtual_vehicle.engine.dynamics import ParcelModel
from virtual_vehicle.errors import TippingError
from virtual_vehicle.physics import laws

# Every run draws the same examples on any machine: derandomized (examples follow from each test's name), no example
# database (a failure found once cannot make later runs differ, and no .hypothesis/ folder is written), the failing
# example printed as a reproduce blob, no deadline (timings vary between machines and numba's first compile).
# Registered and loaded here, before any test module is imported, so every @settings(...) in tests/ inherits it.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True, deadline=None)
settings.load_profile("ci")
# Hypothesis still caches the constants it reads from our modules under ./.hypothesis/; a run writes nothing into
# the checkout, so that cache lives in a folder of this run's own (unless HYPOTHESIS_STORAGE_DIRECTORY is set).
if "HYPOTHESIS_STORAGE_DIRECTORY" not in os.environ:
    os.environ["HYPOTHESIS_STORAGE_DIRECTORY"] = _storage = tempfile.mkdtemp(prefix="hypothesis-")
    atexit.register(shutil.rmtree, _storage, ignore_errors=True)
# A run started as a background job of a non-interactive shell (`make test &`, nohup) inherits SIGINT ignored, and so
# would every child it starts: the tests of what Ctrl-C does to the commands then see nothing. A terminal's run has
# Python's handler; give every run that, so that its children start with SIGINT at its default, as under a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")  # session scope: hypothesis tests may use it
def segment_at():
    """``segment_at(cells, spec, x, y, th)``: (model, piece, event-engine segment, state) of parcel ``spec`` at rest
    at pose (x, y, th) on still wheels under the Coulomb law; the hypothesis example is dropped where it tips."""
    def make(cells, spec, x, y, th):
        m = ParcelModel(cells, spec, np.zeros((cells.n, 2)), laws.CoulombLaw())
        y0 = np.array([x, y, th, 0.0, 0.0, 0.0])
        try:
            piece = m.piece_at(y0)
        except TippingError:  # e.g. the L's centre of mass sits near its inner corner
            assume(False)
        return m, piece, dynamics._Segment(m, piece, y0), y0

    return make
