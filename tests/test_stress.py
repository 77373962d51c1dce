"""The randomized liveness stress test: generated sorting floors are what they claim (holes, one-way aisles, parking,
1-3 entries and exits, every exit reachable, the same floor from the same seed), and a short run of each is
counted from the sorting report. ``benchmarks/stress_sorter.py`` runs 200 seeds and prints the table."""

from __future__ import annotations

from collections import deque

import numpy as np

from virtual_vehicle.analysis.stress import bays_needed, random_floor, stress

_AGAINST = {">": (0, -1), "<": (0, 1), "^": (1, 0), "v": (-1, 0)}


def _cells_reach(rows: list[str], start: str, goal: str) -> bool:
    """Cell by cell (not parcel-sized): whether the cells marked ``goal`` are reached from those marked ``start``
    over cells, never stepping onto or off a cell against its arrow."""
    H, W = len(rows), len(rows[0])
    seen = {(r, c) for r in range(H) for c in range(W) if rows[r][c] == start}
    queue = deque(seen)
    while queue:
        r, c = queue.popleft()
        if rows[r][c] == goal:
            return True
        for move in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            nr, nc = r + move[0], c + move[1]
            if (0 <= nr < H and 0 <= nc < W and (nr, nc) not in seen and rows[nr][nc] != "."
                    and _AGAINST.get(rows[r][c]) != move and _AGAINST.get(rows[nr][nc]) != move):
                seen.add((nr, nc))
                queue.append((nr, nc))
    return False


def test_generated_floors_are_varied_reachable_and_the_same_from_the_same_seed():
    floors = [random_floor(seed) for seed in range(40)]
    assert random_floor(7).table == floors[7].table and random_floor(8).table != floors[7].table
    seen = {"hole": 0, "arrow": 0, "parking": 0}
    counts = set()
    for f in floors:
        text = "".join(f.rows)
        seen["hole"] += "." in text
        seen["arrow"] += any(a in text for a in "<>^v")
        seen["parking"] += "P" in text
        exits = sorted({ch for ch in text if ch.isdigit()})
        counts.add((f.features["entries"], len(exits)))
        assert 1 <= f.features["entries"] <= 3 and 1 <= len(exits) <= 3 and "E" in text
        assert all(_cells_reach(f.rows, "E", k) for k in exits), f.seed
        assert all(p["destination"] < len(exits) for p in f.table["parcels"])
        if "P" in text:  # parking bays come with a sequenced stream the bays can hold
            seq = [p["sequence"] for p in sorted(f.table["parcels"], key=lambda p: p["t_start"])]
            assert sorted(seq) == list(range(len(seq)))
            assert bays_needed(seq) <= text.count("P"), (f.seed, seq)
    assert min(seen.values()) >= 4, seen
    assert len(counts) >= 5, counts
    setup = floors[0].scenario().build()
    config = setup.control.config
    assert np.asarray(config["entry"]).any() and np.asarray(config["exit"]).max() >= 0


def test_a_short_stress_run_counts_what_the_sorting_reports_find():
    rows = stress([1, 2, 3], parcels=6, duration=10.0)
    assert [r["seed"] for r in rows] == [1, 2, 3]
    for r in rows:
        placed = r["correct"] + r["misrouted"] + r["lost"] + r["on_array"] + r["waiting"]
        assert placed == 6, r
        assert r["collisions"] == 0 and r["misrouted"] == 0, r
        assert len(r["why"]) == r["deadlocks"] + r["waits"]
        assert all(line.startswith(f"seed {r['seed']}: ") and " near " in line for line in r["why"])
    assert sum(r["correct"] for r in rows) >= 6


def test_the_bays_a_sequenced_stream_needs_are_those_waiting_at_once():
    assert bays_needed([0, 1, 2, 3]) == 0
    assert bays_needed([3, 2, 1, 0]) == 3  # all but the last wait
    assert bays_needed([1, 0, 3, 2]) == 1
    assert bays_needed([2, 3, 0, 1]) == 2


def test_a_parcel_does_not_pass_close_beside_a_parked_one():
    """Seed 132's floor with the sequence the generator once drew (eight parcels, one bay): the first parcel parks,
    the second heads east one cell row above it; its body reaches past the centres it covers, and it used to brush
    the parked one at 7.3 s. A held cell beside a parked vehicle now gives no free run, so it
    stops short."""
    from virtual_vehicle.run.sim import run
    from virtual_vehicle.run.tasks import sorting_report

    floor = random_floor(132)
    for parcel, number in zip(floor.table["parcels"], [7, 4, 0, 2, 1, 3, 5, 6]):
        parcel["sequence"] = number
    floor.table["duration"] = 8.0
    report = sorting_report(run(floor.scenario().build()))
    assert report["collisions"] == 0 and report["misrouted"] == 0, report
    assert report["on_array"] >= 3  # the parked parcel, the one that stopped short and the one due


def test_the_side_rule_costs_the_junction_no_delivery():
    """The side rule holds a younger parcel back only beside a parked one: held beside any older vehicle too (the
    rule's first form), sorting_junction delivered 12 in its bundled 40 s instead of 13."""
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import run
    from virtual_vehicle.run.tasks import sorting_report

    report = sorting_report(run(load_scenario("sorting_junction")[0].build()))
    assert report["collisions"] == 0 and report["misrouted"] == 0, report
    assert report["correct"] >= 13, report
