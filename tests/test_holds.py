"""The sorter's wait-for graph (:mod:`virtual_vehicle.cells.sorting.holds`): who waits on whom, read from the cells'
state, and its cycles (the deadlocks the run's report names)."""

from __future__ import annotations

import numpy as np

from virtual_vehicle.cells.sorting import Sorter, encode_goal
from virtual_vehicle.cells.sorting.holds import cycles, held_cells, waits_for

GAP, REACH = 2, 8


def _row(n: int):
    """A row of ``n`` cells, port 0 east (+x) and port 2 west, no neighbours north or south; a fresh state."""
    neighbor = np.full((n, 4), -1)
    neighbor[:-1, 0] = np.arange(1, n)
    neighbor[1:, 2] = np.arange(n - 1)
    state = Sorter(0.3, gap=GAP, reach=REACH).init(n, 4, {})
    return neighbor, np.ones(n, bool), state


def _vehicle(state, cells, vid, direction, *, stopped=True, goal=0):
    for c in cells:
        state["vid"][c], state["goal"][c], state["dir"][c] = vid, goal, direction
        state["stop"][c] = 0 if stopped else 255


def test_two_vehicles_each_holding_the_cell_the_other_needs_are_a_cycle():
    neighbor, alive, state = _row(8)
    _vehicle(state, [0, 1], 10, 0)  # heads east, its front cell 1
    _vehicle(state, [5, 6], 20, 2)  # heads west, its front cell 5
    state["hold"][2], state["hold"][3], state["hold"][4] = 20, 10, 10  # each holds a cell in the other's way
    edges = waits_for(state, neighbor, alive, GAP, REACH)
    assert {(v, w) for v, w, _ in edges} == {(10, 20), (20, 10)}
    assert (10, 20, 2) in edges and (20, 10, 4) in edges  # where each is held up
    assert cycles(edges) == [[10, 20]]
    assert held_cells(state, [10, 20]) == [0, 1, 2, 3, 4, 5, 6]


def test_a_moving_vehicle_or_a_queue_behind_a_dead_cell_is_no_cycle():
    neighbor, alive, state = _row(8)
    _vehicle(state, [0, 1], 10, 0)
    _vehicle(state, [5, 6], 20, 2, stopped=False)  # it backs off or moves on: it waits on nobody
    state["hold"][2], state["hold"][3], state["hold"][4] = 20, 10, 10
    assert cycles(waits_for(state, neighbor, alive, GAP, REACH)) == []
    neighbor, alive, state = _row(8)
    _vehicle(state, [0, 1], 10, 0)  # behind the next one
    _vehicle(state, [3, 4], 20, 0)  # before a dead cell: waits on the floor
    alive[5] = False
    edges = waits_for(state, neighbor, alive, GAP, REACH)
    assert [(v, w) for v, w, _ in edges] == [(10, 20)] and cycles(edges) == []


def test_a_parked_vehicle_waits_on_the_one_due_and_closes_a_cycle_when_that_one_stands_behind_it():
    neighbor, alive, state = _row(8)
    _vehicle(state, [4, 5], 30, 0, goal=encode_goal(0, 1))  # sequence 1: not due while 0 is
    state["park"][4] = state["park"][5] = 0  # parked
    _vehicle(state, [0, 1], 40, 0, goal=encode_goal(0, 0))  # sequence 0, due, stands behind it
    state["hold"][2] = state["hold"][3] = 40
    edges = waits_for(state, neighbor, alive, GAP, REACH)
    assert (30, 40, -1) in edges and (40, 30, 4) in edges
    assert cycles(edges) == [[30, 40]]


def test_cycles_are_the_strongly_connected_sets_of_two_or_more():
    edges = [(1, 2, 0), (2, 3, 0), (3, 1, 0), (3, 4, 0), (4, 5, 0), (5, 4, 0), (6, 1, 0), (7, 7, 0)]
    assert cycles(edges) == [[1, 2, 3], [4, 5]]
    assert cycles([]) == []
