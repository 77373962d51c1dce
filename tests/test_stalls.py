"""The sorter's runs name their stalls (``sorting.stalls``): parcels whose vehicles wait on each other in a cycle of
holds as a deadlock (found from the cells' state, whatever the wait bound), parcels standing past the scenario's
bound otherwise as waiting; a healthy run names none."""

from __future__ import annotations

from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def one_way_head_on() -> dict:
    """An aisle drawn one-way from both ends toward an exit lane leaving north from its middle, entries at both
    ends: the first parcel from each side meets the other head on beside the lane and neither may back off against
    its arrows."""
    lane = "." * 11 + "{}" + "." * 11
    aisle = ">" * 13 + "<" * 13
    inner = "EEE" + ">" * 10 + "<" * 10 + "EEE"
    rows = [lane.format("0000")] * 2 + [lane.format("oooo")] * 3 + [aisle, inner, inner, aisle]
    parcels = [{"name": name, "length": 0.25, "width": 0.22, "mass": 1.0, "mu": 2.0, "x": x, "y": 0.15,
                "t_start": 0.0, "destination": 0} for name, x in (("west", 0.13), ("east", 2.47))]
    return {"name": "one_way_head_on", "duration": 14.0, "output_dt": 0.05,
            "array": {"kind": "map", "pitch": 0.1, "map": "\n".join(rows)},
            "control": {"program": "sort", "period": 0.01, "speed": 0.3, "gap": 2, "wait_bound": 4.0},
            "friction": {"law": "viscous"}, "parcels": parcels}


def test_parcels_meeting_head_on_on_one_way_aisles_give_way_instead_of_deadlocking():
    """They used to form a cycle of holds (neither may back off against its arrows); the younger now steps aside."""
    report = sorting_report(run(parse_scenario(one_way_head_on()).build()))
    assert report["correct"] == 2 and report["stalls"] == [], report
    assert report["collisions"] == report["misrouted"] == 0


def boxed_head_on() -> dict:
    """A corridor exactly one parcel wide (the array's north and south edges), two parcels put on facing each
    other, each bound for the exit beyond the other; behind each the corridor goes on one cell row wide, so that the
    gradients lead through but a parcel cannot back into it. Neither can pass the other, and neither can give way:
    each is boxed in on every side but the other's, asks the other back, and both stand (the gap the sorting
    package's notes name). Pitch 0.125 m (exact in binary): at 0.1 m a cell beside the narrow row could link
    diagonally to it, by the rounding of its bearing, and the parcel backed into it (before a cell on the boundary
    of two ports' sectors belonged to neither)."""
    wall = "00" + "..." + "EEE" + "oo" + "EEE" + "..." + "11"
    mid = "00" + "ooo" + "EEE" + "oo" + "EEE" + "ooo" + "11"
    parcels = [{"name": name, "length": 0.3, "width": 0.3, "mass": 1.0, "mu": 2.0, "x": x, "y": 0.125,
                "t_start": 0.0, "destination": goal} for name, x, goal in (("p00", 0.75, 1), ("p01", 1.375, 0))]
    return {"name": "boxed_head_on", "duration": 8.0, "output_dt": 0.05,
            "array": {"kind": "map", "pitch": 0.125, "map": "\n".join([wall, mid, wall])},
            "control": {"program": "sort", "period": 0.01, "speed": 0.3, "gap": 2,
                        "wait_bound": 100.0},  # longer than the run: only the cycle of holds can name it
            "friction": {"law": "viscous"}, "parcels": parcels}


def test_a_cycle_of_holds_is_a_deadlock_before_the_wait_bound():
    """Two parcels boxed in head on (above): each waits on the other's cells, a cycle of holds that no rule
    breaks, named by its holds long before the wait bound. (Stress floor 140, the case this test took before,
    delivers now: the two cells that kept the gone parcel's id no longer do, see tests/test_liveness.py.)"""
    report = sorting_report(run(parse_scenario(boxed_head_on()).build()))
    deadlocks = [s for s in report["stalls"] if s["kind"] == "deadlock"]
    assert [s["parcels"] for s in deadlocks] == [["p00", "p01"]], report["stalls"]
    assert deadlocks[0]["waited_s"] > 1.0 and len(deadlocks[0]["cells"]) >= 4  # the cells both carry or hold
    assert report["collisions"] == report["misrouted"] == report["lost"] == 0


def test_a_healthy_sorting_run_names_no_stalls():
    sc, _ = load_scenario("sorting_junction")
    report = sorting_report(run(sc.model_copy(update={"duration": 12.0}).build()))
    assert report["correct"] >= 2 and report["stalls"] == []
    assert 0 < report["sentences_per_s"] < 288 * 4 * 100 / 10  # far below every port every tick
