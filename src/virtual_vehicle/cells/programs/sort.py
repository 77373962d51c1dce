"""Program ``"sort"``: the Virtual Vehicle sorter (:mod:`virtual_vehicle.cells.sorting`): parcels read at an entry
ride to the exit their label names, in sequence where they carry a number; its options, builder, task report and the
entries and exits the pictures draw. Units: m, s, m/s, parcels per hour."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
import shapely
from pydantic import Field

from virtual_vehicle.cells.programs.base import (BuildContext, ControlSetup, FieldError, Markers, Point,
                                                 ProgramOptions, setup_for)

Outline = Annotated[list[Point], Field(min_length=3)]


class SortOptions(ProgramOptions):
    """``program = "sort"``: the Virtual Vehicle (:mod:`virtual_vehicle.cells.sorting`): cells inside ``entries``
    outlines read each arriving parcel's ``destination``, cells inside ``exits[k]`` are exit k (a lane reaching the
    edge; parcels leave through the side most of its cells have open); parcels ride at ``speed`` (m/s) keeping
    ``gap`` free cells ahead, sharing decisions over ``reach`` hops. Parcels with a ``sequence`` number leave in that
    order: one whose number is not yet due parks where one of its carrying cells is a parking cell (inside a
    ``parking`` outline, or ``P`` on a map) and waits there (at most three exits then). Without outlines the entries
    (``E``), exits (``0``..``3``) and parking cells come from an ``[array]`` map. ``central`` = true runs the same
    policies on one central computer instead (:class:`~virtual_vehicle.cells.sorting.CentralSorter`), for
    comparison. A cell sends on a link only when what it says there changed, and everything every ``heartbeat``
    (s; 0: every tick), which repairs a lost sentence: traffic follows activity, not the number of cells. Without
    ``heartbeat``: 1 s, or, on a wire so slow that one-second heartbeats would take more than a tenth of a cell's
    line, long enough to keep them to that tenth (5.25 s at 9600 baud;
    :func:`~virtual_vehicle.cells.sorting.rules.heartbeat_seconds`). A parcel
    on the array that stands still longer than ``wait_bound`` (s) is reported as stalled (see :func:`stalls`)."""

    program: Literal["sort"]
    speed: Annotated[float, Field(gt=0, le=1e3)] = 0.2
    exits: Annotated[list[Outline], Field(max_length=4)] = []
    entries: list[Outline] = []
    parking: list[Outline] = []
    gap: Annotated[int, Field(ge=1, le=50)] = 2
    reach: Annotated[int, Field(ge=1, le=62)] = 8
    central: bool = False
    heartbeat: Annotated[float, Field(ge=0, le=60)] | None = None
    wait_bound: Annotated[float, Field(gt=0, le=1e6)] = 10.0

    def top_speed(self) -> float:
        """The parcels' riding speed (m/s): the fastest the wheels run."""
        return self.speed



Options = SortOptions
"""The ``[control]`` table of this program."""

def _inside(outline, cells, where: str) -> np.ndarray:
    poly = shapely.Polygon(np.asarray(outline, dtype=float))
    if not poly.is_valid or poly.area <= 0:
        raise FieldError(where, "is not a simple polygon with positive area")
    inside = shapely.covers(poly, shapely.points(cells.positions))
    if not inside.any():
        raise FieldError(where, "contains no cell")
    return inside


def build(options: SortOptions, ctx: BuildContext) -> ControlSetup:
    """Each cell is told whether it is an entry, a parking cell, which exit it belongs to and its way out, the port
    a one-way cell forbids, and a unique installation number; the parcels' labels are checked against the exits."""
    from virtual_vehicle.cells.sorting import PARK, Sorter
    from virtual_vehicle.cells.network.wire import WireParams
    from virtual_vehicle.cells.sorting.rules import heartbeat_seconds, lane_hold_ticks, lead_cells, tick_of
    from virtual_vehicle.model import layout

    c, cells, topo, marks = options, ctx.cells, ctx.topology, ctx.marks
    if (not c.exits or not c.entries) and not marks:
        raise FieldError("control", "program 'sort' needs exits = [outline, ...] and entries = [outline, ...] "
                         "(outlines [[x, y], ...] in m), or an [array] map that marks them")
    kinds = np.unique(cells.ports[~cells.belts])
    if len(kinds) > 1 or kinds[0] not in (4, 6):
        raise FieldError("control.program", "the sorter runs on one lattice, square (four ports a cell) or "
                         "hexagonal (six), not on an array that mixes them")
    hexagonal = kinds[0] == 6
    if hexagonal and c.central:
        raise FieldError("control.central", "the central sorter runs on square lattices (four ports a cell); on a "
                         "hexagonal lattice run the distributed one (central = false)")
    if hexagonal and c.reach > 30:
        raise FieldError("control.reach", f"on a hexagonal lattice reach is at most 30 hops (got {c.reach})")
    exit_id = np.full(cells.n, -1, dtype=np.int64)
    if c.exits:
        for k, outline in enumerate(c.exits):
            inside = _inside(outline, cells, f"control.exits[{k}]")
            exit_id[inside & (exit_id < 0)] = k
        n_exits = len(c.exits)
    else:  # from the map
        n_exits = 0
        while str(n_exits) in marks:
            exit_id[marks[str(n_exits)]] = n_exits
            n_exits += 1
        if n_exits == 0 or any(str(k) in marks for k in range(n_exits, 4)):
            raise FieldError("array.map", "program 'sort' needs exits: mark them 0, 1, ... in order on the map, "
                             "or give control.exits")
    exit_port = np.full(cells.n, -1, dtype=np.int64)
    for k in range(n_exits):
        region = np.flatnonzero(exit_id == k)
        # sides of the region's cells with no neighbour installed, by port (a dead neighbour is no way out)
        free = (topo.neighbor[region] < 0).sum(axis=0)
        where = f"control.exits[{k}]" if c.exits else f"array.map (exit {k})"
        if free.max() == 0:
            raise FieldError(where, "an exit must reach the edge of the array (parcels leave "
                             "through a side with no neighbour)")
        if np.sum(free == free.max()) > 1:
            raise FieldError(where, "the way out is ambiguous (the exit touches two edges as much; "
                             "keep it off the corner" + ("; on a hexagonal lattice an exit leaves where the rows "
                                                         "end, through an edge along wheel 0's axis" if hexagonal
                                                         else "") + ")")
        exit_port[region] = int(np.argmax(free))  # the way out: the side most of its cells have open
    entry = np.zeros(cells.n, dtype=bool)
    for k, outline in enumerate(c.entries):
        entry |= _inside(outline, cells, f"control.entries[{k}]")
    park = np.zeros(cells.n, dtype=bool)
    for k, outline in enumerate(c.parking):
        park |= _inside(outline, cells, f"control.parking[{k}]")
    if not c.parking:
        park = marks.get("P", park)
    if park.any() and n_exits > PARK:
        raise FieldError("control.parking", f"with parking cells a sorter has at most {PARK} exits (the "
                         "fourth gradient leads to the parking cells)")
    if not c.entries:
        entry = marks.get("E", entry)
        if not entry.any():
            raise FieldError("array.map", "program 'sort' needs entries: mark entry cells E on the map, or give "
                             "control.entries")
    forbid = np.full(cells.n, -1, dtype=np.int64)  # one-way cells: the port a parcel may not move toward
    for arrow, against in layout.ONE_WAY.items():
        forbid[marks.get(arrow, np.zeros(cells.n, bool))] = against
    config = {"exit": exit_id, "exit_port": exit_port, "entry": entry, "park": park, "forbid": forbid,
              "inner": _inner(topo),  # a silent neighbour there is dead, not the edge
              "sides": _sides(topo, cells, ctx.sensors),  # the sensor each cell shares a point with a neighbour at
              "entry_no": np.arange(1, cells.n + 1, dtype=np.int64),  # installation numbers: unique vehicle ids
              "clearance": (c.gap + 1) * cells.pitch}  # the loader waits for this much room around a new parcel
    if c.central:
        from virtual_vehicle.cells.sorting import CentralSorter

        program = CentralSorter(topo, c.speed, c.gap, period=c.period)
    else:
        # over the wire a sentence takes time in proportion to its bytes: send only the words that changed, and
        # ask as far ahead as the vehicle travels while its run of held cells is told back
        wire = c.delivery == "wire"
        byte = WireParams.bits_per_byte / c.wire.baud if wire else 0.0  # (the scenario sets no framing)
        # and beat no more often than keeps the heartbeats to a tenth of the line
        beat = c.heartbeat if c.heartbeat is not None else heartbeat_seconds(int(kinds[0]),
                                                                               Sorter.schema.sentence_bytes, byte)
        program = Sorter(c.speed, c.gap, c.reach, max_age=c.max_age, period=c.period, pitch=cells.pitch,
                         heartbeat=beat, partial=wire and tick_of(beat, c.period) > 1,
                         lead=min(lead_cells(c.speed, cells.pitch, c.gap, c.period, int(kinds[0]), byte),
                                  62 - c.gap),
                         lane_hold=lane_hold_ticks(c.reach, c.period, int(kinds[0]), byte))
    for i, p in enumerate(ctx.parcels):
        if p.destination is not None and p.destination >= n_exits:
            raise FieldError(f"parcels[{i}].destination", f"exit {p.destination} does not exist (the scenario has "
                             f"{n_exits} exits, 0..{n_exits - 1})")
    _check_sequence(ctx.parcels, park)
    return setup_for(c, ctx, program, config)


def _inner(topo) -> np.ndarray:
    """(n, P) the ports of each cell that lead to an installed neighbour with another cell installed beyond it the
    same way (known at installation): a parcel may pass over that neighbour if it is dead (:mod:`~virtual_vehicle.
    cells.sorting`), where a dead cell on the array's edge would let it drive off the array."""
    nb = topo.neighbor
    inner = nb >= 0
    for q in range(nb.shape[1]):
        ahead = nb[:, q]
        inner[:, q] &= (ahead >= 0) & (nb[np.maximum(ahead, 0), q] >= 0)
    return inner


def _sides(topo, cells, sensors) -> np.ndarray:
    """(n, P) the sensor of each cell at the point it shares with the neighbour on each port (the midpoint of their
    centres: with the default sensors, the edge midpoint on that side), -1 where it has none there or no neighbour
    (known at installation): lit, the body over it covers the neighbour too (:mod:`~virtual_vehicle.cells.sorting`,
    vehicle tracking)."""
    nb = topo.neighbor
    n, P = nb.shape
    pos = cells.positions
    points = sensors.points  # (n, S, 2) m
    sides = np.full((n, P), -1, dtype=np.int64)
    for q in range(P):
        mid = (pos + pos[np.maximum(nb[:, q], 0)]) / 2
        off = np.linalg.norm(points - mid[:, None, :], axis=2)  # (n, S)
        s = np.argmin(off, axis=1)
        at = (nb[:, q] >= 0) & (off[np.arange(n), s] < 1e-3 * cells.pitch)
        sides[at, q] = s[at]
    return sides


def _check_sequence(parcels, park: np.ndarray) -> None:
    """Sequence numbers, where given, must be 0, 1, 2, ... (each once), on labelled parcels, with parking."""
    numbered = [(i, p) for i, p in enumerate(parcels) if p.sequence is not None]
    if not numbered:
        return
    for i, p in numbered:
        if p.destination is None:
            raise FieldError(f"parcels[{i}].sequence", "a sequence number goes with a destination (the label "
                             "carries both)")
    got = sorted(p.sequence for _, p in numbered)
    if got != list(range(len(got))):
        missing = sorted(set(range(len(got))) - set(got))
        raise FieldError(f"parcels[{numbered[0][0]}].sequence", "sequence numbers must be 0, 1, 2, ... each once "
                         f"over the parcels that have one (missing {missing[:5]}): a number never delivered would "
                         "hold the rest forever")
    if not park.any():
        raise FieldError("control.parking", "parcels with sequence numbers need parking cells (P on the map, or "
                         "control.parking outlines) to wait on")


def report(result) -> dict:
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
    net = result.stats.get("network", {})
    out = sorted((r["entered_at_s"] + r["delivery_time_s"], r["sequence"]) for r in rows
                 if r["sequence"] is not None and r["outcome"] == "delivered")
    order = [q for _, q in out]
    inversions = sum(a > b for k, a in enumerate(order) for b in order[k + 1:])
    delays = [r["entered_at_s"] - r["due_s"] for r in rows if r["entered_at_s"] is not None]
    correct = sum(r["correct"] for r in rows)
    count = {k: sum(r["outcome"] == k for r in rows) for k in ("delivered", "lost", "on_array", "waiting")}
    out = {
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
        "sentences_per_s": net["sentences_sent"] / sc.duration if "sentences_sent" in net else None,
        "stalls": stalls(result, rows),
    }
    if sc.arrivals == "saturate":
        out["saturation"] = saturation(result, rows)
    return out


def saturation(result, rows: list[dict] | None = None) -> dict:
    """Saturation throughput of a run whose entries were fed as fast as they accept (``arrivals = "saturate"``),
    per entry (a place where parcels are put on) against the kinematic bound ``speed / (length + gap pitches)``: one
    entry cannot pass parcels faster than the wheels carry a parcel's length and the gap kept behind it.

    Rates are steady-state, between the first and the last event counted: ``fed_per_hour`` from the times parcels
    were put on, ``delivered_per_hour`` from the times the entry's parcels left through their right exit ((count -
    1) / (last - first), None below two). ``length_m`` is the mean length of the entry's parcels; ``fraction`` is
    delivered / bound. ``total`` sums the entries. Units: parcels per hour, m, m/s."""
    setup = result.setup
    sc = setup.scenario
    speed, gap = sc.control.top_speed(), sc.control.gap * setup.cells.pitch
    if rows is None:
        rows = report(result)["parcels"]

    def rate(times):
        times = sorted(times)
        return (len(times) - 1) / (times[-1] - times[0]) * 3600.0 if len(times) > 1 and times[-1] > times[0] else None

    places: dict = {}
    for k, (p, row) in enumerate(zip(sc.parcels, rows)):
        places.setdefault((round(p.x, 9), round(p.y, 9)), []).append(k)
    entries = []
    for (x, y), members in places.items():
        fed = [rows[k]["entered_at_s"] for k in members if rows[k]["entered_at_s"] is not None]
        out = [rows[k]["entered_at_s"] + rows[k]["delivery_time_s"] for k in members if rows[k]["correct"]]
        length = float(np.mean([_length(result.parcels[k].spec) for k in members]))
        bound = speed / (length + gap) * 3600.0
        delivered = rate(out)
        entries.append({"x": x, "y": y, "fed": len(fed), "delivered": len(out), "fed_per_hour": rate(fed),
                        "delivered_per_hour": delivered, "length_m": length, "bound_per_hour": bound,
                        "fraction": None if delivered is None else delivered / bound})
    measured = [e["delivered_per_hour"] for e in entries]
    total = {"delivered_per_hour": sum(measured) if None not in measured else None,
             "bound_per_hour": sum(e["bound_per_hour"] for e in entries)}
    total["fraction"] = None if total["delivered_per_hour"] is None else \
        total["delivered_per_hour"] / total["bound_per_hour"]
    return {"speed_m_s": speed, "gap_m": gap, "entries": entries, "total": total}


def _length(spec) -> float:
    """A parcel's length (m): the longer side of its outline's bounding box in its own frame."""
    x0, y0, x1, y1 = spec.polygon.bounds
    return max(x1 - x0, y1 - y0)


def stalls(result, rows: list[dict] | None = None) -> list[dict]:
    """The run's deadlocks and the parcels that stood still on the array longer than the scenario's ``wait_bound``
    (s): a stall is found either way, and named once.

    - ``"deadlock"``: parcels whose vehicles wait on each other in a cycle of holds at the run's end
      (:mod:`virtual_vehicle.cells.sorting.holds`: each is held up by a cell another carries or holds, or is not due
      before another), all standing still at the end for longer than a back-off takes (``gap + 1`` pitches at the
      sorter's speed): no rule of the sorter breaks such a cycle, so it is reported without waiting for the bound.
      ``cells``: the cells the deadlocked vehicles carry or hold.
    - ``"waiting"``: parcels not in a deadlock that stood still longer than ``wait_bound``, grouped when their stands
      overlap in time within ``gap + 2`` pitches of each other (outline to outline): a dead end, a missing bay, a
      route that never opens, or a queue behind one of those. ``cells``: the cells under them (centres covered).

    Each names its ``parcels``, ``t_s`` when the last of them stopped and ``waited_s`` how long all of them stood
    still together (until they moved again or the run ended). Judged at the trajectory's samples; standing still:
    the centre within a quarter pitch of where it stopped. A program whose cells keep no holds the sorter's way (the
    central sorter, the reservation router) has no hold graph: there the waiting parcels of a group of two or more
    are called a deadlock, one alone waiting. ``rows``: the report's per-parcel rows (computed when not given)."""
    setup = result.setup
    sc, cells = setup.scenario, setup.cells
    ctl = sc.control
    if rows is None:
        rows = report(result)["parcels"]
    pitch = cells.pitch
    eps = 0.25 * pitch
    stands = []  # (parcel index, t0, t1, state at t0)
    last = {}  # parcel index -> (t0, t1) of the stand it ends the run in
    for k, (pr, row) in enumerate(zip(result.parcels, rows)):
        if row["entered_at_s"] is None:
            continue
        tr = pr.trajectory
        t_end = tr.t_end if row["delivery_time_s"] is None else row["entered_at_s"] + row["delivery_time_s"]
        keep = (tr.times >= row["entered_at_s"]) & (tr.times <= t_end)
        times, states = tr.times[keep], tr.states[keep]
        a = 0
        for j in range(1, len(times) + 1):
            if j == len(times) or np.hypot(*(states[j, :2] - states[a, :2])) > eps:
                if times[j - 1] - times[a] > ctl.wait_bound:
                    stands.append((k, float(times[a]), float(times[j - 1]), states[a]))
                if j == len(times) and row["outcome"] == "on_array":
                    last[k] = (float(times[a]), float(times[j - 1]))
                a = j
    out = []
    standing = {result.parcels[k].spec.name: (result.parcels[k].spec, result.parcels[k].trajectory.states[-1],
                                               t0, t1) for k, (t0, t1) in last.items()}
    found = deadlocks(getattr(result, "program_state", None), getattr(result, "topology", None), ctl, cells,
                      standing)
    if found is not None:
        for names, held, t0, t1 in found:
            out.append({"kind": "deadlock", "parcels": names, "cells": held, "t_s": t0, "waited_s": t1 - t0})
        inside = {n for names, *_ in found for n in names}
        stands = [m for m in stands if result.parcels[m[0]].spec.name not in inside]
    # parcels standing at the same time near each other wait together: connected groups
    reach = (ctl.gap + 2) * pitch
    polys = [shapely.Polygon(result.parcels[k].spec.world_polygon(st).exterior.coords) for k, _, _, st in stands]
    group = list(range(len(stands)))

    def root(u):
        while group[u] != u:
            u = group[u]
        return u

    for u, (ku, a0, a1, _) in enumerate(stands):
        for v, (kv, b0, b1, _) in enumerate(stands[:u]):
            near = polys[u].distance(polys[v]) <= reach
            if ku != kv and near and max(a0, b0) < min(a1, b1):
                group[root(u)] = root(v)
    for g in sorted({root(u) for u in range(len(stands))}):
        members = [stands[u] for u in range(len(stands)) if root(u) == g]
        names = sorted({result.parcels[k].spec.name for k, *_ in members})
        under = set()
        for u in range(len(stands)):
            if root(u) == g:
                under |= set(np.flatnonzero(shapely.covers(polys[u], shapely.points(cells.positions))).tolist())
        t0 = max(m[1] for m in members)
        t1 = min(m[2] for m in members) if len(names) > 1 else members[0][2]
        kind = "deadlock" if found is None and len(names) > 1 else "waiting"
        out.append({"kind": kind, "parcels": names, "cells": sorted(under), "t_s": t0, "waited_s": max(t1 - t0, 0.0)})
    return out


def deadlocks(state, topology, control, cells, standing: dict) -> list[tuple] | None:
    """(parcel names, cells held, t0, t1) of each cycle of holds in the sorter's cell ``state`` (with its links
    ``topology``) whose parcels all stand still, for longer than a back-off takes (``gap + 1`` pitches at the
    ``control``'s speed); ``standing``: parcel name -> (spec, pose, t0, t1) of each parcel on the array standing
    still from t0 to t1 (s), pose its (x, y, theta). None when ``state`` is not the distributed sorter's (another
    program keeps no holds)."""
    from virtual_vehicle.cells.sorting import holds

    if not isinstance(state, dict) or topology is None or not {"vid", "hold", "dir", "stop", "park"} <= set(state):
        return None
    edges = holds.waits_for(state, topology.neighbor, topology.alive, control.gap, control.reach)
    vid = np.asarray(state["vid"])
    owner = {}  # vehicle id -> the standing parcel whose outline covers most of its cells
    for name, (spec, pose, _, _) in standing.items():
        poly = shapely.Polygon(spec.world_polygon(pose).exterior.coords)
        ids = vid[shapely.covers(poly, shapely.points(cells.positions))]
        ids = ids[ids >= 0]
        if len(ids):
            values, counts = np.unique(ids, return_counts=True)
            owner.setdefault(int(values[np.argmax(counts)]), name)
    settle = (control.gap + 1) * cells.pitch / control.top_speed()  # the longest a back-off moves a parcel away
    out = []
    for members in holds.cycles(edges):
        names = [owner.get(v) for v in members]
        if None in names:  # a member moves (or is not on the array): no standing cycle
            continue
        t0 = max(standing[n][2] for n in names)
        t1 = min(standing[n][3] for n in names)
        if t1 - t0 > settle:
            out.append((sorted(names), holds.held_cells(state, members), t0, t1))
    return out


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


SUMMARY = "sorting"
"""The run summary's block holding :func:`report` (per-parcel rows merged into the summary's parcels)."""
COMPARED = (("correct", "delivered to the right exit"), ("misrouted", "misrouted"), ("lost", "lost"),
            ("collisions", "collisions"), ("throughput_per_hour", "parcels per hour"),
            ("delivery_time_mean_s", "mean delivery time (s)"), ("delivery_time_max_s", "longest delivery time (s)"),
            ("entry_delay_mean_s", "mean wait at the entry (s)"), ("on_array", "still on the array"),
            ("waiting", "never put on"), ("order_inversions", "pairs left out of sequence"),
            ("sentences_per_s", "sentences sent per second"))
"""(report key, label) of what ``virtual-vehicle compare`` puts side by side."""
CENTRAL = True
"""``central = true`` runs the same policies on one central computer."""
LABELS = True
"""The cells at an entry read each parcel's label: its ``destination`` and ``sequence``."""


def markers(setup) -> Markers:
    """The entries (exit index -1) and exits: the ``[control] entries`` / ``exits`` outlines when the scenario
    gives them, else (marks on a map) the bounding box of each entry's and exit's cells, a pitch wide around their
    centres; and each parcel's destination."""
    ctl = setup.scenario.control
    destinations = [p.destination for p in setup.scenario.parcels]
    lanes = []
    if ctl.entries or ctl.exits:
        for k, poly in enumerate(ctl.entries):
            lanes.append(("entry" if len(ctl.entries) == 1 else f"entry {k}", -1, np.asarray(poly, float)))
        for k, poly in enumerate(ctl.exits):
            lanes.append((f"exit {k}", k, np.asarray(poly, float)))
        return Markers(lanes=lanes, destinations=destinations)
    cfg = setup.control.config
    P, h = setup.cells.positions, setup.cells.pitch / 2
    groups = [("entry", -1, np.asarray(cfg["entry"], bool))]
    exits = np.asarray(cfg["exit"])
    groups += [(f"exit {k}", k, exits == k) for k in range(int(exits.max()) + 1)]
    for label, k, mask in groups:
        if mask.any():
            (x0, y0), (x1, y1) = P[mask].min(axis=0) - h, P[mask].max(axis=0) + h
            lanes.append((label, k, np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])))
    return Markers(lanes=lanes, destinations=destinations)
