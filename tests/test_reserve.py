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


def test_a_parcel_already_nearer_than_the_gap_to_a_standing_one_still_plans():
    """Found on facility_40x40 with every entry saturated: a parcel that finds no plan stands, reserved where it
    stands for the whole window; an older parcel within ``gap`` cells of it then found no plan either (every step's
    region, waiting included, grown by ``gap`` met it), stood too, and the next one behind it: three parcels stood
    from 4 s on (6 delivered in 20 s). A parcel nearer than ``gap`` to one planned before keeps at least the
    spacing it has: it plans, east to its exit here, never nearer to the standing parcel than it started."""
    from virtual_vehicle.cells.sorting.reserve import ReservationRouter

    n_side, gap, window = 12, 3, 8
    router = ReservationRouter(pitch=0.1, speed=0.3, gap=gap, window=window)
    cols, rows = np.meshgrid(np.arange(n_side), np.arange(n_side))
    router._layout(np.column_stack([cols.ravel(), rows.ravel()]) * 0.1)
    exit_id = np.where(cols.ravel() == n_side - 1, 0, -1)  # the east column is exit 0's lane, out through port 0
    router._maps(np.ones(n_side * n_side, dtype=bool), {"exit": exit_id})
    maps = router._footprint_maps(0, 0, 2, 2)
    reserved = np.zeros((window + 1, n_side, n_side), dtype=bool)
    router._reserve(reserved, (5, 2), [], 2, 2)  # standing on columns 2-3; the parcel below on 5-6: one cell free
    moves = router._plan((5, 5), 2, 2, maps, 0, reserved)
    assert moves is not None and moves[0] == 0  # (on the parent: None, so it stood)
    r, c = 5, 5
    for t, q in enumerate(moves):
        r, c = (r + (0, 1, 0, -1)[q], c + (1, 0, -1, 0)[q]) if q >= 0 else (r, c)
        rows_, cols_ = router._region(r, c, r, c, 2, 2, 0)  # its footprint stays off the other's lit cells
        assert not reserved[t + 1, rows_, cols_].any()
    alone = np.zeros_like(reserved)
    assert router._plan((5, 5), 2, 2, maps, 0, alone) == moves  # what it plans with the map to itself


def test_parcels_whose_lit_cells_join_keep_their_own_records():
    """One computer sees parcels as groups of lit cells. Two parcels that came so near that their lit cells joined
    made one group, which kept only the record most of its cells had: on facility_40x40 saturated a parcel for exit 2
    joined one for exit 1 at 10 s and was carried out of exit 1 by the central sorter (and one by the router). Now
    the group is shared: each vehicle keeps its cells, a newly lit cell between them goes to the one it is reached
    from first, and a group of one vehicle's cells, or of none, is as before."""
    from virtual_vehicle.cells.sorting.seen import parcels_seen

    n = 8  # a row of cells, port 0 east, port 2 west; cell 6 not lit, cell 7 lit alone
    neighbor = np.full((n, 4), -1)
    neighbor[:-1, 0] = np.arange(1, n)
    neighbor[1:, 2] = np.arange(n - 1)
    connected = neighbor >= 0
    lit = np.array([1, 1, 1, 1, 1, 1, 0, 1], dtype=bool)
    before = np.array([5, 5, -1, 9, 9, 9, -1, -1])  # vehicle 5 on 0-1, vehicle 9 on 3-5, cell 2 newly lit
    seen = {vid: cells.tolist() for vid, cells in parcels_seen(lit, connected, neighbor, before)}
    assert seen == {5: [0, 1, 2], 9: [3, 4, 5], -1: [7]}
    before = np.array([5, 5, 5, 5, -1, -1, -1, -1])  # one vehicle's cells: the group is its own, newly lit ones too
    seen = {vid: cells.tolist() for vid, cells in parcels_seen(lit, connected, neighbor, before)}
    assert seen == {5: [0, 1, 2, 3, 4, 5], -1: [7]}


def test_a_parcel_far_from_its_exit_plans_toward_it():
    """Windowed A*: a plan covers ``window`` steps and is judged at its end by the distance left to the exit. That
    distance was capped at the window, so every plan ending farther away than a window looked alike and a parcel far
    from its exit took the first found, east before north, west and south: on facility_40x40 parcels for the north
    exits rode round the east rim and one tipped off through another exit's lane. Alone on a 4 x 40 aisle whose west
    end is its exit lane, a parcel 30 cells away plans every step of its window west, and one a window away does
    too."""
    from virtual_vehicle.cells.sorting.reserve import ReservationRouter

    rows, cols, window = 4, 40, 8
    router = ReservationRouter(pitch=0.1, speed=0.3, gap=2, window=window)
    c, r = np.meshgrid(np.arange(cols), np.arange(rows))
    router._layout(np.column_stack([c.ravel(), r.ravel()]) * 0.1)
    router._maps(np.ones(rows * cols, dtype=bool), {"exit": np.where(c.ravel() == 0, 0, -1)})
    maps = router._footprint_maps(0, 2, 2, 2)  # out through port 2, west
    free = np.zeros((window + 1, rows, cols), dtype=bool)
    for start in ((1, cols - 4), (1, window + 2)):
        assert maps[3][start] > window
        assert router._plan(start, 2, 2, maps, 2, free) == [2] * window


def test_the_router_keeps_room_to_stop_before_the_array_s_edge():
    """Found on facility_40x40 saturated: the router rode parcels north along the west edge toward the top rows and
    east along the bottom rows toward the east edge, stopping them only once their footprint reached the edge; the
    wheels run on for ~0.15 s after they are told to stop, and at 1.1 m/s two parcels in 20 s (seven in 30 s once the
    cells ahead were spun up) rode off the array. A parcel now moves toward the edge or a hole only with room to
    stop beyond its footprint (the cells it runs on at its speed, at most ``gap``: all 3 here), in its plans and at
    every tick, unless the edge there is its exit's way out."""
    from virtual_vehicle.cells.sorting.reserve import ReservationRouter

    assert ReservationRouter(pitch=0.1, speed=1.1, gap=5).room == 4  # runs on 0.41 m, its centre a cell behind
    assert ReservationRouter(pitch=0.1, speed=0.3, gap=2).room == 0  # 0.06 m: as before

    n_side, gap = 12, 3
    router = ReservationRouter(pitch=0.1, speed=1.1, gap=gap, window=8)
    cols, rows = np.meshgrid(np.arange(n_side), np.arange(n_side))
    router._layout(np.column_stack([cols.ravel(), rows.ravel()]) * 0.1)
    exit_id = np.where((cols.ravel() == n_side - 1) & (rows.ravel() < 4), 0, -1)  # east column, rows 0-3: out east
    exit_port = np.where(exit_id == 0, 0, -1)
    router._maps(np.ones(n_side * n_side, dtype=bool), {"exit": exit_id})
    room = router._footprint_maps(0, 0, 2, 2)[4]
    connected = router.neighbor >= 0
    n = n_side * n_side

    def clear(r0, c0, q):  # a 2 x 2 footprint at rows r0.., columns c0.., its lit cells the footprint alone
        cells = np.array([(r0 + i) * n_side + c0 + j for i in range(2) for j in range(2)])
        core = np.zeros(n, dtype=bool)
        core[cells] = True
        owner = np.full(n, -1)
        owner[cells] = 7
        return router._clear(cells, core, q, 7, owner, np.full(n, -1), 0, exit_id, exit_port, connected)

    assert clear(8, 5, 1) is None and not room[1][8, 5]  # north: rows 10 and 11, then the edge
    assert clear(7, 5, 1) is not None and room[1][7, 5]  # rows 9-11: room enough
    assert clear(8, 5, 0) is not None and room[0][8, 5]  # east, along the top rows: the edge is beside it
    assert clear(5, 8, 0) is None and not room[0][5, 8]  # east toward a part of the edge that is no exit
    assert clear(0, 8, 0) is not None and room[0][0, 8]  # east toward its exit lane's open side
    plan = router._plan((5, 2), 2, 2, router._footprint_maps(0, 0, 2, 2), 0, np.zeros((9, n_side, n_side), bool))
    r, c = 5, 2
    for q in plan:  # on its way to the exit it never comes nearer to the edge than its room
        r, c = (r + (0, 1, 0, -1)[q], c + (1, 0, -1, 0)[q]) if q >= 0 else (r, c)
        assert r <= n_side - 2 - gap and (c <= n_side - 2 - gap or r < 4)


def test_a_lone_parcel_rides_at_the_wheels_speed_on_the_industrial_drive():
    """The router turned on only the cells under a parcel; on the industrial drive (150 ms response, 2.5 m/s^2) a
    cell a parcel rides onto at 1.1 m/s is still speeding up, and parcels rode at ~0.65 m/s on facility_40x40. The
    free cells a parcel holds ahead of it now turn with it, so it rides at the wheels' speed."""
    rows = ["o" * 30 + "00"] * 6
    rows[2:4] = ["EEE" + "o" * 27 + "00"] * 2
    sc = parse_scenario({"name": "aisle", "duration": 6.0, "output_dt": 0.02,
                         "array": {"kind": "map", "pitch": 0.1, "map": "\n".join(rows)},
                         "control": {"program": "reserve", "speed": 1.1, "gap": 5},
                         "wheels": {"profile": "industrial", "period": 0.01},
                         "friction": {"law": "stick_slip"},
                         "parcels": [{"name": "p", "length": 0.25, "width": 0.22, "mass": 2.0, "mu": 0.6,
                                      "mu_static": 0.7, "x": 0.15, "y": 0.3, "t_start": 0.0, "destination": 0}]})
    result = run(sc.build())
    report = sorting_report(result)
    assert report["correct"] == 1 and report["collisions"] == 0 and report["lost"] == 0, report
    tr = result.parcels[0].trajectory
    speed = np.hypot(tr.states[:, 3], tr.states[:, 4])
    assert speed.max() > 0.95 * 1.1  # (before: 0.82 m/s at most)


def test_a_moving_parcel_reserves_the_room_it_holds_at_every_tick():
    """A plan and the check at every tick must ask for the same room, or an older parcel's plan says go while a
    younger one waits where the older one's tick-level run ahead meets it, each for the other (on facility_40x40,
    with the room reserved only as wide as the footprint, two parcels stood so from 4.75 s on). What the check claims
    ahead of every lit cell of a moving parcel lies inside what its plan reserves for that step."""
    from virtual_vehicle.cells.sorting.reserve import ReservationRouter

    n_side, gap = 16, 3
    router = ReservationRouter(pitch=0.1, speed=0.3, gap=gap, window=4)
    cols, rows = np.meshgrid(np.arange(n_side), np.arange(n_side))
    router._layout(np.column_stack([cols.ravel(), rows.ravel()]) * 0.1)
    n = n_side * n_side
    core = np.zeros(n, dtype=bool)
    core[[6 * n_side + 6, 6 * n_side + 7, 7 * n_side + 6, 7 * n_side + 7]] = True  # footprint: rows 6-7, cols 6-7
    lit = np.flatnonzero((np.abs(rows.ravel() - 6.5) < 2) & (np.abs(cols.ravel() - 6.5) < 2))  # a cell around it
    owner = np.full(n, -1)
    owner[lit] = 3
    for q in range(4):
        claim = router._clear(lit, core, q, 3, owner, np.full(n, -1), 0, np.full(n, -1), np.full(n, -1),
                              router.neighbor >= 0)
        assert claim is not None and len(claim) == 4 * gap
        reserved = np.zeros((5, n_side, n_side), dtype=bool)
        router._reserve(reserved, (6, 6), [q], 2, 2)
        assert reserved[0].ravel()[claim].all(), q


def test_of_equally_short_plans_the_router_keeps_the_parcel_s_heading_and_turns_once():
    """A turn costs the wheels' response (~0.15 s on the industrial drive, longer than a step), so where plans tie
    the one with fewer turns wins, and the parcel's current heading counts for its first move: a parcel 6 rows below
    and 8 columns west of its exit lane, riding north, plans north then east; riding east, east then north."""
    from virtual_vehicle.cells.sorting.reserve import ReservationRouter

    n_side, window = 12, 16
    router = ReservationRouter(pitch=0.1, speed=0.3, gap=2, window=window)
    cols, rows = np.meshgrid(np.arange(n_side), np.arange(n_side))
    router._layout(np.column_stack([cols.ravel(), rows.ravel()]) * 0.1)
    exit_id = np.where((cols.ravel() == n_side - 1) & (rows.ravel() >= 8), 0, -1)  # east column, rows 8-11
    router._maps(np.ones(n_side * n_side, dtype=bool), {"exit": exit_id})
    maps = router._footprint_maps(0, 0, 2, 2)
    free = np.zeros((window + 1, n_side, n_side), dtype=bool)
    north_first = router._plan((2, 2), 2, 2, maps, 0, free, heading=1)
    east_first = router._plan((2, 2), 2, 2, maps, 0, free, heading=0)
    assert north_first == [1] * 6 + [0] * 10
    assert east_first == [0] * 8 + [1] * 6 + [0] * 2
