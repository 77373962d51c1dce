"""Shared test helpers."""

import numpy as np
import pytest
from hypothesis import assume

from virtual_vehicle import dynamics, friction
from virtual_vehicle.dynamics import ParcelModel
from virtual_vehicle.errors import TippingError


@pytest.fixture(scope="session")  # session scope: hypothesis tests may use it
def segment_at():
    """``segment_at(cells, spec, x, y, th)``: (model, piece, event-engine segment, state) of parcel ``spec`` at rest
    at pose (x, y, th) on still wheels under the Coulomb law; the hypothesis example is dropped where it tips."""
    def make(cells, spec, x, y, th):
        m = ParcelModel(cells, spec, np.zeros((cells.n, 2)), friction.CoulombLaw())
        y0 = np.array([x, y, th, 0.0, 0.0, 0.0])
        try:
            piece = m.piece_at(y0)
        except TippingError:  # e.g. the L's centre of mass sits near its inner corner
            assume(False)
        return m, piece, dynamics._Segment(m, piece, y0), y0

    return make
