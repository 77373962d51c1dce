"""The central reservation router (program "reserve"): it delivers every parcel to its exit without collisions or
misroutes on small maps, including parcels that meet head on, plans around dead cells that appear during a run,
and stands beside the distributed sorter in ``compare``."""

import numpy as np
import pytest

from virtual_vehicle.config.scenario import FaultEvent, load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def junction(duration=24.0, parcels=7, **control):
    sc, _ = load_scenario("sorting_junction")
    ctl = sc.control.model_dump() | {"program": "reserve", **control}
    data = sc.model_dump(mode="json", exclude_defaults=True) | {"duration": duration, "control": ctl}
    data["parcels"] = data["parcels"][:parcels]
    return parse_scenario(data)


def assert_clean(result, delivered):
    report = sorting_report(result)
    assert report["collisions"] == 0 and report["misrouted"] == 0 and report["lost"] == 0, report
    assert result.summary()["plant"]["undetected_overlaps"] == 0
    assert report["correct"] == delivered, {k: report[k] for k in ("correct", "on_array", "waiting", "stalls")}
    return report


def test_the_router_delivers_the_junction_stream():
    result = run(junction().build())
    report = sorting_report(result)
    assert report["collisions"] == 0 and report["misrouted"] == 0 and report["lost"] == 0
    assert report["correct"] >= 5  # as the distributed sorter in the same 24 s
    assert not report["stalls"]


def head_on_lane(parcels_each_side=3, one_way=False):
    """The sorter's head-on case (docs/distributed-control.md): an aisle fed from both ends, a lane leaving north
    from its middle; every parcel goes to that lane, so the first from each side meet head on in front of it."""
    lane = "." * 11 + "{}" + "." * 11
    aisle, inner = "o" * 26, "EEE" + "o" * 20 + "EEE"
    rows = [lane.format("0000")] * 2 + [lane.format("oooo")] * 3 + [aisle, inner, inner, aisle]
    parcels = []
    for k in range(parcels_each_side):
        for side, x in (("w", 0.13), ("e", 2.47)):
            parcels.append({"name": f"{side}{k}", "length": 0.25, "width": 0.22, "mass": 1.0, "mu": 2.0, "x": x,
                            "y": 0.15, "t_start": 2.0 * k, "destination": 0})
    return parse_scenario({"name": "head_on_lane", "duration": 24.0, "output_dt": 0.05,
                           "array": {"kind": "map", "pitch": 0.1, "map": "\n".join(rows)},
                           "control": {"program": "reserve", "speed": 0.3, "wait_bound": 4.0},
                           "friction": {"law": "viscous"}, "parcels": parcels})


def test_parcels_met_head_on_are_all_delivered():
    assert_clean(run(head_on_lane().build()), delivered=6)


def hall_crossing():
    """Two streams cross a 24 x 16 hall in opposite directions: from the west entry (middle rows) to exit 1 low on
    the east edge, and from the east entry (the same rows) to exit 0 high on the west edge; they start facing each
    other on the same rows."""
    rows = [["o"] * 24 for _ in range(16)]  # rows[k]: k cells up from the bottom
    for k in (6, 7, 8):
        rows[k][1] = rows[k][2] = rows[k][21] = rows[k][22] = "E"
    for k in (12, 13, 14):
        rows[k][0] = "0"
    for k in (0, 1, 2):
        rows[k][23] = "1"
    parcels = []
    for k in range(3):
        parcels.append({"name": f"east{k}", "length": 0.25, "width": 0.22, "mass": 1.0, "mu": 2.0, "x": 0.2,
                        "y": 0.7, "t_start": 3.0 * k, "destination": 1})
        parcels.append({"name": f"west{k}", "length": 0.25, "width": 0.22, "mass": 1.0, "mu": 2.0, "x": 2.2,
                        "y": 0.7, "t_start": 3.0 * k, "destination": 0})
    return parse_scenario({"name": "hall_crossing", "duration": 26.0, "output_dt": 0.05,
                           "array": {"kind": "map", "pitch": 0.1,
                                     "map": "\n".join("".join(row) for row in reversed(rows))},
                           "control": {"program": "reserve", "speed": 0.3},
                           "friction": {"law": "viscous"}, "parcels": parcels})


def test_parcels_pass_each_other_head_on_in_a_hall():
    """The parcels of one stream plan around those of the other, whose path runs head on into theirs."""
    assert_clean(run(hall_crossing().build()), delivered=6)


def test_the_router_plans_around_cells_that_die_during_the_run():
    """A wall of cells dies across the main corridor at 1 s: plans are made again on the map as it is, and no parcel
    centre crosses the wall afterwards."""
    sc = junction(duration=30.0, parcels=4)
    cells = sc.build().cells
    x, y = cells.positions.T
    wall = np.flatnonzero((np.abs(x - 1.0) < 1e-9) & (y > 0.25) & (y < 0.85)).tolist()
    sc = sc.model_copy(update={"faults": sc.faults.model_copy(update={"events": [FaultEvent(t=1.0,
                                                                                             dead_cells=wall)]})})
    result = run(sc.build())
    report = sorting_report(result)
    assert report["collisions"] == 0 and report["misrouted"] == 0 and report["lost"] == 0
    assert report["correct"] >= 3
    for pr in result.parcels:
        path = pr.trajectory.states[pr.trajectory.times > 1.5]
        assert not ((np.abs(path[:, 0] - 1.0) < 0.05) & (path[:, 1] > 0.3) & (path[:, 1] < 0.8)).any()


def test_the_router_does_not_sequence():
    sc, _ = load_scenario("reorder_stream")
    data = sc.model_dump(mode="json", exclude_defaults=True)
    data["control"]["program"] = "reserve"
    with pytest.raises(ScenarioError, match="sequence|park"):
        parse_scenario(data).build()


def test_compare_puts_the_router_beside_the_distributed_sorter():
    from virtual_vehicle.analysis.compare import compare

    sc, _ = load_scenario("sorting_junction")
    both = compare(sc.model_copy(update={"duration": 12.0, "parcels": sc.parcels[:5]}))
    assert set(both) == {"distributed", "central", "reserve"}
    for mode, r in both.items():
        assert r["collisions"] == 0 and r["misrouted"] == 0 and r["lost"] == 0, (mode, r)
    assert both["reserve"]["correct"] >= 2
