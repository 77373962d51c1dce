"""The sorter's liveness (issue 33): the meetings that used to end in a cycle of holds on the stress floors now
deliver. Each floor is a generated stress floor (:func:`~virtual_vehicle.analysis.stress.random_floor`) with only the
two parcels of the cycle it formed there, started as they met: alone they still formed it before a standing vehicle
gave way to an older one asking for a cell it carries (see :mod:`virtual_vehicle.cells.sorting`)."""

from __future__ import annotations

import copy

import pytest

from virtual_vehicle.analysis.stress import random_floor, stress
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def pair(seed: int, names: tuple[str, str], duration: float) -> dict:
    """The stress floor of ``seed`` with only the parcels ``names``, the first of them put on at 0 s (the others
    as much later as in the stream), run for ``duration`` s."""
    table = copy.deepcopy(random_floor(seed).table)
    table["parcels"] = [p for p in table["parcels"] if p["name"] in names]
    t0 = min(p["t_start"] for p in table["parcels"])
    for p in table["parcels"]:
        p["t_start"] = round(p["t_start"] - t0, 3)
    table["duration"] = duration
    return table


@pytest.mark.parametrize("seed, names", [
    (7, ("p01", "p02")),  # an older parcel going north to an exit on the north edge, a younger one crossing east
    (0, ("p01", "p02")),  # the same beside a one-way band going north, at the exit lane's corner
])
def test_a_younger_parcel_standing_across_an_older_ones_way_gives_way(seed, names):
    """Each stood on the other's way: the younger's body on the cells the older asks for, the older's holds on
    the younger's way. The younger, asked for a cell it carries by an older vehicle, steps away and both leave."""
    report = sorting_report(run(parse_scenario(pair(seed, names, 12.0)).build()))
    assert report["correct"] == 2, report
    assert report["collisions"] == report["misrouted"] == report["lost"] == 0
    assert report["stalls"] == []


@pytest.mark.parametrize("seed, names", [
    (15, ("p01", "p02")),  # the younger at the entry's north-west corner, the older coming north from below
    (183, ("p01", "p02")),  # the same beside a `>` band
])
def test_a_younger_parcel_backed_against_the_edge_steps_aside_into_the_older_ones_holds(seed, names):
    """The younger, asked by the older for a cell it carries, has the edge behind it and steps aside: its only open
    side is where the older's chain of holds runs, and those cells were held for the older (the oldest asking), so
    it stood, giving way for ever, and the older waited on it. A vehicle giving way now gets a cell before any
    other: both are delivered, neither waits."""
    report = sorting_report(run(parse_scenario(pair(seed, names, 10.0)).build()))
    assert report["correct"] == 2, report
    assert report["collisions"] == report["misrouted"] == report["lost"] == 0
    assert report["stalls"] == []


def test_a_late_parcel_asked_by_the_due_one_and_a_younger_late_one_gives_way_to_the_due_one():
    """Stress floors 104 and 106: a late parcel (not due) on its way to the parking bay through the exit lane is
    asked by the due parcel (older, from the east or south) and by a younger late parcel from the entry (west). Its
    cells gave way to whichever asked them, the two back-offs pointed opposite ways and the vehicle kept its own
    direction, into the due one's holds: a cycle of holds from 13 s on. It now gives way to the older asker."""
    rows = stress([104, 106], duration=16.0)
    assert [r["deadlocks"] for r in rows] == [0, 0], [r["why"] for r in rows]
    assert all(r["collisions"] == r["misrouted"] == r["lost"] == 0 for r in rows)


def test_the_stress_floors_that_deadlocked_deliver_without_a_deadlock():
    """Seeds 0 and 7 formed a cycle of holds within 8 s (a younger parcel crossing an older one's way, as above);
    a 9 s run of each now forms none."""
    rows = stress([0, 7], duration=9.0)
    assert [r["deadlocks"] for r in rows] == [0, 0], [r["why"] for r in rows]
    assert all(r["collisions"] == r["misrouted"] == r["lost"] == 0 for r in rows)


def test_a_parked_parcel_on_the_due_ones_way_gives_way():
    """Stress floors 59 and 96: a late parcel parked in a bay whose body covers the only way the due parcel has
    (59: south round holes and the edge; 96: east along a `v` band it may not leave northward). The due one waited
    on the parked one's cells, the parked one on the due number: a cycle of holds from 4.9 s (59) and 7.1 s (96),
    0 delivered. A parked vehicle now gives way, as the late one it is, and comes back to a bay after."""
    rows = stress([59, 96], duration=12.0)
    assert [r["deadlocks"] for r in rows] == [0, 0], [r["why"] for r in rows]
    assert all(r["collisions"] == r["misrouted"] == r["lost"] == 0 for r in rows)


def test_cells_seeing_only_an_edge_do_not_keep_a_gone_vehicle_between_them():
    """Stress floor 140: the late p00 gave way north past two cells that went on seeing an edge of the due p01
    behind it; each heard the other say p00's id, so the rule that clears a lone cell holding a gone vehicle never
    fired, p01 waited on them and p00 on the due number: a cycle of holds from 13.7 s, 0 delivered in 16 s. A cell
    that sees only an edge now keeps its vehicle only while a neighbour across a lit shared point carries it, and
    takes that neighbour's otherwise: the floor delivers, without a deadlock."""
    rows = stress([140], duration=16.0)
    assert rows[0]["deadlocks"] == 0 and rows[0]["correct"] >= 1, rows[0]["why"]
    assert rows[0]["collisions"] == rows[0]["misrouted"] == rows[0]["lost"] == 0
