"""The central counterpart of the distributed sorter (:class:`CentralSorter`), for side-by-side comparison: the
same rules (:mod:`virtual_vehicle.cells.sorting.rules`) applied by one computer with global knowledge. Units: SI."""

from __future__ import annotations

import numpy as np

from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.sorting.rules import (MAX_EXITS, NONE, PARK, back_off_ticks, decode_goal, drive, due,
                                                 hop_cost, tick_of, vehicle_id)
from virtual_vehicle.cells.sorting.seen import parcels_seen


class CentralSorter:
    """The central counterpart of :class:`Sorter`, for side-by-side comparison: one computer that sees every cell's
    sensors at once, with no network delay, applies the same policies globally each tick.

    It finds parcels as connected groups of lit cells, keeps their records (id = arrival tick, goal = the label
    read at an entry), routes each by shortest-path distances to its exit (Dijkstra on the cell graph, edge cells
    costing ``1 + edge_cost`` as in the cells' gradients; a parcel goes the way that brings the cells carrying it
    closest to the exit on average), never moves a parcel over the edge or a dead cell except
    out of its exit lane, moves it sideways into the lane at its exit, and grants cells ahead to the oldest parcel
    first, ``gap + 1`` deep (a parcel moves when ``gap`` are free ahead of every front cell).

    Sequencing and one-way cells as the cells do: the number due next rises when a sequenced parcel leaves through
    its exit; a parcel not yet due heads (shortest path) for a parking cell whose centre is free and parks on it;
    shortest paths avoid parked parcels and the cells beside them, and never run against a one-way arrow. A parcel
    blocked head on by an older one that cannot move either backs off for as long as ``gap + 1`` cells take.

    Config and inputs as for :class:`Sorter`, plus the topology (neighbours and live links) given at construction.
    """

    schema = Schema(())

    def __init__(self, topology, speed: float, gap: int = 2, edge_cost: int = 3, period: float = 0.01):
        self.topo = topology
        self.speed = float(speed)
        self.gap = int(gap)
        self.edge_cost = int(edge_cost)
        self.period = float(period)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        if ports != 4:
            raise ValueError("the central sorter runs on square lattices (four ports a cell)")
        exit_id = np.asarray(config["exit"])
        self.forbid = np.asarray(config.get("forbid", np.full(n, NONE)), dtype=np.int64)
        dist = self._distances([exit_id == e for e in range(MAX_EXITS)], exit_id, np.zeros(n, bool))
        return {"dist": dist, "vehicles": {}, "owner": np.full(n, NONE, dtype=np.int64), "next": 0}

    def _distances(self, sources, exit_id, blocked) -> np.ndarray:
        """(len(sources), n) weighted hop distances to each mask of source cells (edge cells cost ``1 +
        edge_cost``, as in the cells' gradients), never through a ``blocked`` cell (a parked parcel's) nor against
        a one-way cell's arrow."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        topo = self.topo
        n = len(exit_id)
        conn = topo.connected
        cost = hop_cost(conn.all(axis=1), exit_id, self.edge_cost).astype(float)
        a, p = np.nonzero(conn & ~blocked[:, None] & (np.arange(conn.shape[1])[None, :] != self.forbid[:, None]))
        b = topo.neighbor[a, p]
        keep = ~blocked[b]
        a, b = a[keep], b[keep]
        graph = coo_matrix((cost[a], (b, a)), shape=(n, n)).tocsr()  # stepping from b into a costs a's cost
        dist = np.full((len(sources), n), np.inf)
        for e, src in enumerate(sources):
            src = np.flatnonzero(src)
            if len(src):
                dist[e] = dijkstra(graph, indices=src, min_only=True)
        return dist

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
        topo, cfg = self.topo, inputs.config
        n, P = inputs.connected.shape
        lit = np.asarray(inputs.sensors, dtype=bool).any(axis=1) & topo.alive
        core = np.asarray(inputs.sensors, dtype=bool)[:, 0] & topo.alive
        exit_id = np.asarray(cfg["exit"])
        exit_port = np.asarray(cfg["exit_port"])
        entry = np.asarray(cfg["entry"], dtype=bool)
        labels = np.full(n, NONE) if inputs.labels is None else np.asarray(inputs.labels)
        vehicles = {}
        owner = np.full(n, NONE, dtype=np.int64)
        tick = tick_of(inputs.t, self.period)
        for vid, blob in parcels_seen(lit, inputs.connected, topo.neighbor, state["owner"]):
            record = state["vehicles"].get(vid) if vid >= 0 else None
            if record is None:
                lab = labels[blob[entry[blob] & (labels[blob] >= 0)]]
                if not len(lab):
                    continue  # an unknown parcel: nobody drives it
                vid = vehicle_id(tick, int(blob.min()))
                record = {"goal": int(lab[0]), "dir": NONE}
            vehicles[vid] = {**record, "cells": blob}
            owner[blob] = vid
        wheels = np.zeros((n, 2))
        held = np.full(n, NONE, dtype=np.int64)  # the vehicle each cell is held for this tick
        # sequencing, as the cells do: a parcel whose number is not yet due heads for a free parking cell and parks
        # where a cell carrying it is one; other parcels route around parked ones
        park_cell = np.asarray(cfg.get("park", np.zeros(n, bool)), dtype=bool)
        nxt = state.get("next", 0)
        blocked = np.zeros(n, dtype=bool)
        moving = np.zeros(n, dtype=bool)
        for vid, v in vehicles.items():
            goal_exit, seq = (int(x) for x in decode_goal(v["goal"]))
            v["turn"] = due(seq, nxt)
            v["parked"] = not v["turn"] and bool(np.any(park_cell[v["cells"]] & core[v["cells"]]))
            (blocked if v["parked"] else moving)[v["cells"]] = True
        nb = self.topo.neighbor  # and the cells beside a parked parcel: a gap of one cell is too narrow for a parcel
        blocked |= ((nb >= 0) & blocked[np.maximum(nb, 0)] & inputs.connected).any(axis=1) & ~moving
        dist = state["dist"]
        if park_cell.any():
            dist = self._distances([exit_id == e for e in range(PARK)] + [park_cell & ~core], exit_id, blocked)
        for vid in sorted(vehicles):
            v = vehicles[vid]
            if v["parked"]:
                v["dir"] = NONE
                continue
            cells = v["cells"]
            goal_exit, seq = (int(x) for x in decode_goal(v["goal"]))
            target = goal_exit if v["turn"] else -99  # no exit while it must wait
            body = cells[core[cells]] if core[cells].any() else cells
            direction = self._direction(dist[goal_exit if v["turn"] else PARK], cells, body, target, exit_id,
                                        exit_port, inputs, v["dir"])
            v["dir"] = direction
            if direction < 0:
                continue
            if v.get("back", 0) > 0:  # backing away from an older parcel met head on
                v["back"] -= 1
                direction = v["back_dir"]
            go, claim, blocker = self._ahead(cells, body, direction, vid, owner, held, target, exit_id, exit_port,
                                             inputs)
            other = vehicles.get(blocker)
            if (not go and other is not None and blocker < vid and other["dir"] == (direction + 2) % 4
                    and not other.get("moving", False) and not np.any(self.forbid[body] == (direction + 2) % 4)):
                # head on with an older parcel that cannot move either: give way, back off far enough for its gap
                back = (direction + 2) % 4
                v["back"], v["back_dir"] = self._back_ticks(cfg), back
                direction = back
                go, claim, _ = self._ahead(cells, body, back, vid, owner, held, target, exit_id, exit_port, inputs)
            v["dir"], v["moving"] = direction, go
            if go:
                held[claim] = vid
                axis, sign = drive(direction)
                wheels[cells, axis] = sign * self.speed
                out = (exit_id[cells] == target) & (exit_port[cells] == direction) & ~inputs.connected[cells, direction]
                if seq >= 0 and out.any():  # it leaves through its exit: the next number is due
                    nxt = max(nxt, seq + 1)
        return ({"dist": state["dist"], "vehicles": {k: {"goal": v["goal"], "dir": v["dir"], "back": v.get("back", 0),
                                                          "back_dir": v.get("back_dir", NONE)}
                                                      for k, v in vehicles.items()}, "owner": owner, "next": nxt},
                Mailbox.empty(self.schema, n, P), wheels)

    def _direction(self, dist, cells, body, goal, exit_id, exit_port, inputs, current):
        topo = self.topo
        lane = body[exit_id[body] == goal]
        if len(lane):  # as the cells do: out once nothing beside a lane cell, across the way out, is off the lane
            out = int(exit_port[lane[0]])
            member = np.zeros(len(dist), dtype=bool)
            member[body] = True
            for q in ((out + 1) % 4, (out + 3) % 4):
                nb = topo.neighbor[lane, q]
                if np.any((nb >= 0) & member[np.maximum(nb, 0)] & (exit_id[np.maximum(nb, 0)] != goal)):
                    return (q + 2) % 4  # away from the part still beside the lane
            return out
        best, best_score = NONE, np.inf
        for q in range(4):
            if not inputs.connected[body, q].all() or np.any(self.forbid[body] == q):
                continue  # a cell carrying the parcel has no neighbour that way, or a one-way arrow: closed
            score = float(np.mean(dist[topo.neighbor[body, q]]))  # where the carrying cells would be, on average
            if not np.isfinite(score):
                continue
            score = (score, q != current, q)
            if best < 0 or score < best_score:
                best, best_score = q, score
        return best

    def _back_ticks(self, cfg) -> int:
        """Ticks a parcel backs off for: long enough to clear the gap and one more cell (config ``clearance``)."""
        return back_off_ticks(float(cfg.get("clearance", 0.3)), self.speed, self.period)

    def _ahead(self, cells, body, q, vid, owner, held, goal, exit_id, exit_port, inputs):
        """Whether the vehicle may move toward port q, the cells it then holds, and the vehicle in its way (None)."""
        topo = self.topo
        member = np.zeros(len(owner), dtype=bool)
        member[cells] = True
        claim = []
        for c in cells:
            nb = topo.neighbor[c, q]
            if nb >= 0 and member[nb]:
                continue  # not a front cell
            if not inputs.connected[c, q]:
                if exit_id[c] == goal and exit_port[c] == q:
                    continue  # leaving through its exit
                if c in body:
                    return False, [], None
                continue  # only its edge hangs over
            run = c
            for depth in range(self.gap + 1):
                nxt = topo.neighbor[run, q] if inputs.connected[run, q] else -1
                if nxt < 0:
                    break
                if (owner[nxt] >= 0 and owner[nxt] != vid) or held[nxt] >= 0:
                    if depth < self.gap:
                        return False, [], int(owner[nxt] if owner[nxt] >= 0 else held[nxt])
                    break
                claim.append(nxt)
                run = nxt
        return True, claim, None
