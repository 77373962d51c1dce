"""Task metrics: what a run achieved, in the terms a sorting hall is judged by.

Units: s, m, parcels per hour.
"""

from __future__ import annotations

import numpy as np


def sorting_report(result) -> dict:
    """Outcome of every parcel of a sorting run and the run's totals.

    A parcel is ``"delivered"`` when it left the array (tipped off the edge) with its centre of mass within 1.5
    pitches of a cell of an exit lane, which is the exit it reached; ``"correct"`` when that exit is its
    destination. ``"lost"``: it left the array anywhere else; ``"on_array"``: still there at the end;
    ``"waiting"``: never put on (its place at the entry never came free). Delivery time runs from being put on the
    array to leaving it. ``collisions`` counts pairs of parcels that started pushing each other (must be 0).
    ``throughput_per_hour`` counts correct deliveries. With sequence numbers, ``order_inversions`` counts the pairs of
    delivered parcels that left in the wrong order (must be 0); None when no parcel with a sequence number left.

    With plain conveyor belts, a parcel leaves the array when it last rests on no cell of the array (only on belts,
    or on nothing), judged at the trajectory's samples: handed to an exit belt by an exit lane, it is delivered
    there, whether or not it later falls off the belt's far end.
    """
    setup = result.setup
    sc = setup.scenario
    cells = setup.cells
    exit_id = np.asarray(setup.control.config["exit"])
    exit_cells = np.flatnonzero(exit_id >= 0)
    belts = cells.belts.any()
    rows = []
    for pr, entry in zip(result.parcels, sc.parcels):
        tr = pr.trajectory
        row = {"name": pr.spec.name, "destination": entry.destination, "sequence": entry.sequence,
               "due_s": entry.t_start,
               "entered_at_s": pr.entered_at, "outcome": "on_array", "exit": None, "correct": False,
               "delivery_time_s": None, "collisions": sum(1 for e in tr.events if e.kind == "contact")}
        left = _left_the_cells(setup, pr) if belts and pr.entered_at is not None else None
        if pr.entered_at is None:
            row["outcome"] = "waiting"
        elif left is not None:
            t_left, k = left
            if k >= 0:
                row.update(outcome="delivered", exit=k, delivery_time_s=float(t_left - pr.entered_at))
                row["correct"] = row["exit"] == entry.destination
            else:
                row["outcome"] = "lost"
        elif tr.status == "tipped" and not belts:
            d = np.hypot(*(cells.positions[exit_cells] - tr.states[-1, :2]).T)
            k = int(np.argmin(d)) if len(d) else -1
            if k >= 0 and d[k] <= 1.5 * cells.pitch:
                row.update(outcome="delivered", exit=int(exit_id[exit_cells[k]]),
                           delivery_time_s=float(tr.t_end - pr.entered_at))
                row["correct"] = row["exit"] == entry.destination
            else:
                row["outcome"] = "lost"
        elif tr.status == "tipped":  # fell off a belt without ever reaching the cells
            row["outcome"] = "lost"
        rows.append(row)
    times = [r["delivery_time_s"] for r in rows if r["delivery_time_s"] is not None]
    out = sorted((r["entered_at_s"] + r["delivery_time_s"], r["sequence"]) for r in rows
                 if r["sequence"] is not None and r["outcome"] == "delivered")
    order = [q for _, q in out]
    inversions = sum(a > b for k, a in enumerate(order) for b in order[k + 1:])
    delays = [r["entered_at_s"] - r["due_s"] for r in rows if r["entered_at_s"] is not None]
    correct = sum(r["correct"] for r in rows)
    count = {k: sum(r["outcome"] == k for r in rows) for k in ("delivered", "lost", "on_array", "waiting")}
    return {
        "parcels": rows,
        **count,
        "correct": correct,
        "misrouted": count["delivered"] - correct,
        "collisions": int(result.stats.get("plant", {}).get("parcel_contacts", 0)),
        "throughput_per_hour": correct / sc.duration * 3600.0,
        "delivery_time_mean_s": float(np.mean(times)) if times else None,
        "delivery_time_max_s": float(np.max(times)) if times else None,
        "entry_delay_mean_s": float(np.mean(delays)) if delays else None,
        "order_inversions": inversions if order else None,
    }


def _left_the_cells(setup, pr):
    """(time s, exit) at which parcel result ``pr`` last came off the array's cells (resting on belts only, or
    tipped), judged at its trajectory's samples: the exit is that of the last cells it rested on (-1 if none of them
    belongs to an exit lane). None if it is still on the cells at the end."""
    from virtual_vehicle.model.parcel import supporting_cells

    layer = setup.contact_layer
    exit_of = np.where(setup.cells.belts, -2, np.asarray(setup.control.config["exit"]))[layer.cell_of]
    tr = pr.trajectory
    last, under = None, None
    for k, y in enumerate(tr.states):
        ids = exit_of[supporting_cells(pr.spec, y, layer.positions, layer.tree)]
        on_cells = ids[ids > -2]
        if len(on_cells) and not (tr.status == "tipped" and k == len(tr.states) - 1):
            last, under = k, on_cells
    if last is None or last == len(tr.states) - 1:
        return None
    lanes = under[under >= 0]
    return float(tr.times[last + 1]), int(np.bincount(lanes).argmax()) if len(lanes) else -1


def pose_report(result) -> dict:
    """Outcome of every parcel of a pose run (program ``"pose"``: to a target pose, along waypoints, or turned in
    place) and the run's totals.

    Per parcel: the final error (mm, degrees; the heading wrapped to the outline's rotational symmetry), the time it
    settled within 5 mm and 2 degrees of its target for good (None if it never did), and with waypoints the largest
    distance (mm) of its centre of mass from the path start -> waypoints -> target. Totals: how many settled, the mean
    and largest final errors and settling times, ``throughput_per_hour`` (settled parcels per hour of the run), and
    ``collisions`` (pairs of parcels that started pushing each other: must be 0).
    """
    from virtual_vehicle.cells.control import path_deviation, pose_error, settled_at

    sc = result.setup.scenario
    ways = sc.control.waypoints or [[] for _ in result.parcels]
    rows = []
    for pr, target, way in zip(result.parcels, sc.control.targets, ways):
        tr = pr.trajectory
        dist, ang = pose_error(pr.spec, tr.states[-1], target)
        row = {"name": pr.spec.name, "target": dict(zip(("x", "y", "theta"), target)), "final_error_mm": dist * 1e3,
               "final_error_deg": float(np.degrees(ang)),
               "settled_within_5mm_2deg_at_s": settled_at(pr.spec, tr.times, tr.states, target)}
        if way:
            row["max_path_deviation_mm"] = path_deviation(tr.states, [tr.states[0, :3], *way, target]) * 1e3
        rows.append(row)
    settled = [r["settled_within_5mm_2deg_at_s"] for r in rows if r["settled_within_5mm_2deg_at_s"] is not None]
    paths = [r["max_path_deviation_mm"] for r in rows if "max_path_deviation_mm" in r]
    return {
        "parcels": rows,
        "settled": len(settled),
        "collisions": int(result.stats.get("plant", {}).get("parcel_contacts", 0)),
        "throughput_per_hour": len(settled) / sc.duration * 3600.0,
        "final_error_mean_mm": float(np.mean([r["final_error_mm"] for r in rows])),
        "final_error_max_mm": float(np.max([r["final_error_mm"] for r in rows])),
        "final_error_mean_deg": float(np.mean([r["final_error_deg"] for r in rows])),
        "final_error_max_deg": float(np.max([r["final_error_deg"] for r in rows])),
        "settle_time_mean_s": float(np.mean(settled)) if settled else None,
        "settle_time_max_s": float(np.max(settled)) if settled else None,
        "max_path_deviation_mm": float(np.max(paths)) if paths else None,
    }


REPORTS = {"sort": sorting_report, "pose": pose_report}
"""Task reports by program: what :func:`compare` puts side by side."""


