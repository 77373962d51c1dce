"""The distributed sorter's vehicle tracking where a lost sentence leaves a cell a stale vehicle id (issue 33, 10 %
sentence loss): the compiled step and its array statement (tests/sorter_oracle.py) alike."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.sorting import Sorter
from sorter_oracle import stepped_by_arrays

GONE, NEW = 3078265, 3291258  # vehicle ids: the tick each was made, times 1024, plus the entry cell's number


def _step_middle(compiled: bool, centre: bool, beside: int):
    """Three cells in a row; the middle one carries vehicle GONE (goal 2) and sees a parcel, at its centre or only at
    an edge; its west neighbour says NEW (goal 0), its east one ``beside`` (goal 2). The middle cell's (vid, goal)
    after one step."""
    n, P = 3, 4
    program = Sorter(0.3) if compiled else stepped_by_arrays(Sorter(0.3))
    state = program.init(n, P, {})
    state["vid"][1], state["goal"][1] = GONE, 2
    inbox = Mailbox.empty(program.schema, n, P)
    inbox.present[1] = True
    for word, value in (("vid", -1), ("goal", -1), ("hold", -1), ("req", -1)):
        inbox.values[word][1] = value
    inbox.values["key"][1] = 1 << 20  # no direction
    inbox.values["vid"][1, 2], inbox.values["goal"][1, 2] = NEW, 0  # port 2: west
    inbox.values["vid"][1, 0], inbox.values["goal"][1, 0] = beside, 2  # port 0: east
    sensors = np.zeros((n, 5), bool)
    sensors[1, 0] = centre
    sensors[1, 1] = True  # an edge sensor
    new, _, _ = program.step(state, CellInputs(0.0, sensors, inbox, np.ones((n, P), bool), {}, None))
    return int(new["vid"][1]), int(new["goal"][1])


@pytest.mark.parametrize("compiled", [True, False])
def test_a_cell_seeing_an_edge_drops_a_vehicle_no_neighbour_carries_for_the_one_beside(compiled):
    """Seed 2 of the junction at 10 % loss: the cell east of the entry carried the id of a parcel delivered 5 s
    before, lit only by the next parcel's edge; that older id stood the new parcel at the entry for the rest of the
    run (12 of 18 delivered in 60 s). Such a cell takes the vehicle its neighbour carries."""
    assert _step_middle(compiled, centre=False, beside=-1) == (NEW, 0)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_cell_keeps_its_vehicle_while_a_neighbour_carries_it_or_its_centre_is_covered(compiled):
    """The rule touches only a vehicle nobody else carries under a cell that sees an edge: a cell whose neighbour
    says its vehicle, or whose centre is covered, never changes vehicle while it sees one."""
    assert _step_middle(compiled, centre=False, beside=GONE) == (GONE, 2)
    assert _step_middle(compiled, centre=True, beside=-1) == (GONE, 2)
