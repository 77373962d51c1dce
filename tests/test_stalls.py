"""The sorter's runs name their stalls (``sorting.stalls``): parcels whose vehicles wait on each other in a cycle of
holds as a deadlock (found from the cells' state, whatever the wait bound), parcels standing past the scenario's
bound otherwise as waiting; a healthy run names none."""

from __future__ import annotations

from virtual_vehicle.analysis.stress import random_floor
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


def test_a_cycle_of_holds_is_a_deadlock_before_the_wait_bound():
    """Stress floor 140: the due parcel (p01) stands from 13.7 s waiting on two cells just ahead of it that still
    say the late p00's id, p00 itself being seven rows north (why the two keep it is not traced), and p00 waits on
    the due number: a cycle of holds, named by its holds. The rules broke the cycles of floors 104 and 59
    this test used before (59: a parked parcel now gives way)."""
    table = random_floor(140).table
    table["duration"] = 16.0
    table["control"]["wait_bound"] = 100.0  # longer than the run: only the cycle of holds can name it
    report = sorting_report(run(parse_scenario(table).build()))
    deadlocks = [s for s in report["stalls"] if s["kind"] == "deadlock"]
    assert [s["parcels"] for s in deadlocks] == [["p00", "p01"]], report["stalls"]
    assert deadlocks[0]["waited_s"] > 1.0 and len(deadlocks[0]["cells"]) >= 4  # the cells both carry or hold


def test_a_healthy_sorting_run_names_no_stalls():
    sc, _ = load_scenario("sorting_junction")
    report = sorting_report(run(sc.model_copy(update={"duration": 12.0}).build()))
    assert report["correct"] >= 2 and report["stalls"] == []
    assert 0 < report["sentences_per_s"] < 288 * 4 * 100 / 10  # far below every port every tick
