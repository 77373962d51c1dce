"""A central reservation router, the upper bound the distributed sorter is measured against (the DynoPath idea:
time-expanded reservations over the cell graph). Units: SI (m, s, m/s); time in the plans counts *steps*, the
ticks a parcel takes to ride one pitch at ``speed``.

One computer sees every cell's sensors. Each parcel is the group of cells it lights, as for
:class:`~virtual_vehicle.cells.sorting.CentralSorter`; its *footprint* is the rectangle of cells whose centre it
covers (sensor 0). Every step the router plans again, parcel by parcel, oldest first (prioritized planning, windowed
cooperative A*, Silver 2005): a parcel's plan is a sequence of moves (one pitch through a port, or wait) over the
next ``window`` steps, found by A* in (row, column, step) against a reservation table that holds, for every step,
the cells the parcels planned before it sweep in that step. A move or a wait is allowed only if the footprint it
sweeps, grown by ``gap`` cells on every side, meets none of those cells (the plan's spacing; the lit cells reach up
to a cell past the covered centres, so the check at every tick below may hold a parcel a little longer than its
plan). A parcel that already stands nearer than ``gap`` to a parcel planned before it keeps at least the spacing it
has (its growth is cut to that): with the full growth not even waiting would be allowed, it would find no plan and
stand, reserved where it stands, and the parcels near it after it, and so on. The heuristic is the exact distance on
the empty map (breadth-first over the footprint's positions, one-way arrows and the array's holes respected), so a
parcel alone rides a shortest path; a plan is judged at the window's end by the whole distance left (capped at the
window, every plan of a parcel farther away would look alike). A parcel is at its goal once its front line (its row
or column of cells nearest the exit's open side) lies in its exit lane; from there it rides straight out. The map is
read from the links at every plan: a dead or cut-off cell is a hole, so plans go around faults as soon as they
appear.

Why it does not deadlock: priority is age, one total order that every plan uses. The oldest parcel plans against
the map alone, so its plan leads toward its exit whenever the map has a way. A younger parcel plans against the
older ones' reservations, which may run through the place it stands: its only plans then are those that get out of
the way in time (backing off along an aisle met head on, stepping aside into free rows), so no two parcels ever
plan to wait for each other; the oldest leaves, and the next is oldest. Where a younger parcel has no room to get
out of the way (boxed in, or on a one-way aisle pointing at the older one) it finds no plan; planning then starts
over with it standing where it is for the whole window, and the older ones plan around it or wait for it. That is
the case the order alone does not cover: two parcels each standing in the only way of the other stay where they
are (reported as stalls). Between plans every parcel rides its plan's current move only while ``gap`` cells ahead
of every cell it lights are free of other parcels (checked at every tick, as the central sorter does), so a parcel
behind or ahead of its plan (wheels and parcels take time to speed up) never collides. The router does not
sequence parcels (no parking).
"""

from __future__ import annotations

import heapq
from collections import deque

import numpy as np

from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.sorting.rules import NONE, decode_goal, drive, tick_of, vehicle_id
from virtual_vehicle.cells.sorting.seen import parcels_seen

DR = (0, 1, 0, -1)  # row change of a move through port q (rows run along +y)
DC = (1, 0, -1, 0)  # column change (columns run along +x)


class ReservationRouter:
    """The central reservation router (see the module) on a square lattice of ``pitch`` (m): parcels ridden at
    ``speed`` (m/s) keeping ``gap`` free cells between them, plans ``window`` steps deep, a tick every ``period``
    (s). Config and inputs as for :class:`~virtual_vehicle.cells.sorting.CentralSorter` (``exit``, ``exit_port``,
    ``entry``, ``forbid``, ``entry_no``), plus each cell's ``position`` (n, 2; m)."""

    schema = Schema(())

    def __init__(self, pitch: float, speed: float, gap: int = 2, window: int = 16, period: float = 0.01):
        if window < 1 or gap < 1 or speed <= 0 or period <= 0 or pitch <= 0:
            raise ValueError("the reservation router needs window >= 1, gap >= 1 and positive speed, period, pitch")
        self.pitch, self.speed, self.gap = float(pitch), float(speed), int(gap)
        self.window, self.period = int(window), float(period)
        self.step_ticks = max(1, int(np.ceil(pitch / (self.speed * self.period) - 1e-9)))
        self._cache: dict = {}
        self._cache_key = self._layout_key = None

    def init(self, n, ports, config):
        """Fresh state: no parcels, no plans (see :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        return {"owner": np.full(n, NONE, dtype=np.int64), "vehicles": {}, "plans": 0}

    def _layout(self, positions):
        """Each cell's lattice row and column and its neighbour through each port, from the cells' ``position``
        (config, m): the central computer knows where every cell is installed."""
        key = positions.tobytes()
        if key == self._layout_key:
            return
        pos = np.asarray(positions, dtype=float)
        self.col = np.rint((pos[:, 0] - pos[:, 0].min()) / self.pitch).astype(np.int64)
        self.row = np.rint((pos[:, 1] - pos[:, 1].min()) / self.pitch).astype(np.int64)
        self.shape = (int(self.row.max()) + 1, int(self.col.max()) + 1)
        at = np.full((self.shape[0] + 2, self.shape[1] + 2), NONE, dtype=np.int64)  # a border of no cells
        at[self.row + 1, self.col + 1] = np.arange(len(pos))
        self.neighbor = np.stack([at[self.row + 1 + DR[q], self.col + 1 + DC[q]] for q in range(4)], axis=1)
        self._layout_key, self._cache_key = key, None

    # --- the map --------------------------------------------------------------------------------------------------
    def _grid(self, values, fill):
        g = np.full(self.shape, fill, dtype=np.asarray(values).dtype)
        g[self.row, self.col] = values
        return g

    def _maps(self, usable, cfg):
        """The static maps the plans read, made again when the usable cells change: usable, exit and forbidden
        ports by grid position, and a cache of footprint maps by (goal, height, width)."""
        key = usable.tobytes()
        if key != self._cache_key:
            self._cache, self._cache_key = {}, key
            self._use = self._grid(usable, False)
            self._exit = self._grid(np.asarray(cfg["exit"], dtype=np.int64), -1)
            self._forbid = self._grid(np.asarray(cfg.get("forbid", np.full(len(usable), NONE)), dtype=np.int64), -1)
        return self._use

    @staticmethod
    def _fits(mask, h, w):
        """(R - h + 1, C - w + 1): whether an h x w rectangle anchored (lowest row, column) there is all ``mask``."""
        s = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype=np.int64)
        s[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0), axis=1)
        total = s[h:, w:] - s[:-h, w:] - s[h:, :-w] + s[:-h, :-w]
        return total == h * w

    def _front_in_lane(self, goal, out_port, h, w):
        """Anchors of an h x w footprint whose front line, the row or column of cells nearest the exit's way out
        ``out_port``, lies in exit ``goal``'s lane: from there it rides straight out, its other cells following the
        front through the lane (however short the lane is against the footprint)."""
        lane = self._exit == goal
        if out_port in (1, 3):  # the front is a row of w cells
            line = self._fits(lane, 1, w)
            rows = slice(h - 1, None) if out_port == 1 else slice(0, line.shape[0] - h + 1)
            return line[rows, :]
        line = self._fits(lane, h, 1)
        cols = slice(w - 1, None) if out_port == 0 else slice(0, line.shape[1] - w + 1)
        return line[:, cols]

    def _footprint_maps(self, goal, out_port, h, w):
        """(valid anchors, goal anchors, anchors whose rectangle forbids each port, distance in moves to a goal
        anchor) for an h x w footprint heading out of exit ``goal`` through ``out_port``; distances by breadth-first
        search backwards from the goal anchors."""
        key = (goal, out_port, h, w)
        if key in self._cache:
            return self._cache[key]
        R, C = self.shape
        if h > R or w > C:
            out = None
        else:
            valid = self._fits(self._use, h, w)
            at_goal = self._front_in_lane(goal, out_port, h, w) & valid
            banned = [~self._fits(self._forbid != q, h, w) for q in range(4)]
            dist = np.full(valid.shape, np.iinfo(np.int64).max, dtype=np.int64)
            todo = deque(zip(*np.nonzero(at_goal)))
            for r, c in todo:
                dist[r, c] = 0
            while todo:
                r, c = todo.popleft()
                for q in range(4):  # a predecessor moves through q into (r, c)
                    pr, pc = r - DR[q], c - DC[q]
                    if (0 <= pr < valid.shape[0] and 0 <= pc < valid.shape[1] and valid[pr, pc]
                            and not banned[q][pr, pc] and dist[pr, pc] > dist[r, c] + 1):
                        dist[pr, pc] = dist[r, c] + 1
                        todo.append((pr, pc))
            out = (valid, at_goal, banned, dist)
        self._cache[key] = out
        return out

    # --- planning -------------------------------------------------------------------------------------------------
    def _region(self, r, c, nr, nc, h, w, grow):
        """Slices of the grid the footprint sweeps moving from anchor (r, c) to (nr, nc), grown by ``grow``."""
        R, C = self.shape
        return (slice(max(min(r, nr) - grow, 0), max(min(max(r, nr) + h + grow, R), 0)),
                slice(max(min(c, nc) - grow, 0), max(min(max(c, nc) + w + grow, C), 0)))

    def _plan(self, start, h, w, maps, out_port, reserved):
        """Moves (port, or -1 to wait) for ``window`` steps from anchor ``start``: A* in (row, column, step) against
        ``reserved`` (W + 1, R, C). None when no plan keeps clear of the reservations (not even waiting)."""
        W, gap = self.window, self.gap
        valid, at_goal, banned, dist = maps
        inf = np.iinfo(np.int64).max
        r0, c0 = start
        if at_goal[r0, c0]:  # in its lane: out through the open side, reserving the cells it sweeps
            return [out_port] * W
        while gap > 0 and reserved[(0, *self._region(r0, c0, r0, c0, h, w, gap))].any():
            gap -= 1  # already nearer than gap to a parcel planned before: it keeps at least the spacing it has
        heap = [(int(dist[r0, c0]), 0, 0, 0, r0, c0)]  # f, -step (deeper first), order, step, row, col
        parent = {(r0, c0, 0): None}
        closed = set()
        count = 0
        while heap:
            _, _, _, t, r, c = heapq.heappop(heap)
            if (r, c, t) in closed:
                continue
            closed.add((r, c, t))
            if t == W or at_goal[r, c]:
                moves, node = [], (r, c, t)
                while parent[node] is not None:
                    node, q = parent[node]
                    moves.append(q)
                moves.reverse()
                return moves + [out_port] * (W - len(moves))
            for q in (0, 1, 2, 3, -1):
                if q >= 0:
                    nr, nc = r + DR[q], c + DC[q]
                    if (banned[q][r, c] or not (0 <= nr < valid.shape[0] and 0 <= nc < valid.shape[1])
                            or not valid[nr, nc] or dist[nr, nc] == inf):
                        continue
                else:
                    nr, nc = r, c
                rows, cols = self._region(r, c, nr, nc, h, w, gap)
                if reserved[t, rows, cols].any():
                    continue
                node = (nr, nc, t + 1)
                if node in parent:
                    continue
                parent[node] = ((r, c, t), q)
                count += 1
                heapq.heappush(heap, (t + 1 + int(dist[nr, nc]), -(t + 1), count, t + 1, nr, nc))
        return None

    def _reserve(self, reserved, start, moves, h, w):
        """Mark in ``reserved`` the cells the footprint sweeps at every step of ``moves``."""
        r, c = start
        for t, q in enumerate(moves):
            nr, nc = (r + DR[q], c + DC[q]) if q >= 0 else (r, c)
            rows, cols = self._region(r, c, nr, nc, h, w, 0)
            reserved[t, rows, cols] = True
            r, c = nr, nc
        rows, cols = self._region(r, c, r, c, h, w, 0)
        reserved[len(moves):, rows, cols] = True

    def _plan_all(self, vehicles, core, usable, cfg, exit_port_of):
        """Plans for every vehicle, oldest first, against the reservations of those planned before it. A vehicle
        that finds no plan (a younger one with no room to get out of an older one's way) stands: planning starts
        again with it reserved where it stands for the whole window, so the older ones plan around it or wait."""
        self._maps(usable, cfg)
        rects = {}
        for vid, v in vehicles.items():
            body = v["cells"][core[v["cells"]]]
            if not len(body):
                body = v["cells"]
            rows, cols = self.row[body], self.col[body]
            rects[vid] = (int(rows.min()), int(cols.min()), int(np.ptp(rows)) + 1, int(np.ptp(cols)) + 1)
        standing = set()
        while True:
            reserved = np.zeros((self.window + 1, *self.shape), dtype=bool)
            for vid in standing:
                r, c, h, w = rects[vid]
                self._reserve(reserved, (r, c), [], h, w)
            plans, failed = {}, None
            for vid in sorted(vehicles):
                if vid in standing:
                    plans[vid] = [NONE] * self.window
                    continue
                r, c, h, w = rects[vid]
                goal = int(decode_goal(vehicles[vid]["goal"])[0])
                out_port = exit_port_of.get(goal, NONE)
                maps = self._footprint_maps(goal, out_port, h, w) if out_port >= 0 else None
                if maps is None or not maps[0][r, c]:
                    moves = [NONE] * self.window  # no footprint of this shape fits its exit: it stands
                else:
                    moves = self._plan((r, c), h, w, maps, out_port, reserved)
                    if moves is None:
                        failed = vid
                        break
                self._reserve(reserved, (r, c), moves, h, w)
                plans[vid] = moves
            if failed is None:
                break
            standing.add(failed)
        for vid, moves in plans.items():
            vehicles[vid]["plan"] = [int(q) for q in moves]

    # --- the tick -------------------------------------------------------------------------------------------------
    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, no sentences (one central computer), and the (n, 2)
        wheel speeds (m/s along each drive direction); see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
        cfg = inputs.config
        self._layout(np.asarray(cfg["position"], dtype=float))
        n, P = inputs.connected.shape
        sensors = np.asarray(inputs.sensors, dtype=bool)
        usable = inputs.connected.any(axis=1)  # a dead cell has no live link
        lit = sensors.any(axis=1) & usable
        core = sensors[:, 0] & usable
        exit_id = np.asarray(cfg["exit"])
        exit_port = np.asarray(cfg["exit_port"])
        entry = np.asarray(cfg["entry"], dtype=bool)
        labels = np.full(n, NONE) if inputs.labels is None else np.asarray(inputs.labels)
        tick = tick_of(inputs.t, self.period)
        # parcels: connected groups of lit cells, each keeping its record
        records = state["vehicles"]
        vehicles, owner = {}, np.full(n, NONE, dtype=np.int64)
        for vid, blob in parcels_seen(lit, inputs.connected, self.neighbor, state["owner"]):
            record = records.get(vid) if vid >= 0 else None
            if record is None:
                lab = labels[blob[entry[blob] & (labels[blob] >= 0)]]
                if not len(lab):
                    continue  # an unknown parcel: nobody drives it
                vid = vehicle_id(tick, int(np.asarray(cfg["entry_no"])[blob].min()))
                record = {"goal": int(lab[0]), "plan": [], "since": tick}
            vehicles[vid] = {**record, "cells": blob}
            owner[blob] = vid
        plans = state["plans"]
        if tick % self.step_ticks == 0 or any(not v["plan"] for v in vehicles.values()):
            ports = {int(exit_id[i]): int(exit_port[i]) for i in np.flatnonzero(exit_id >= 0)}
            self._plan_all(vehicles, core, usable, cfg, ports)
            for v in vehicles.values():
                v["since"] = tick
            plans += 1
        wheels = np.zeros((n, 2))
        held = np.full(n, NONE, dtype=np.int64)
        for vid in sorted(vehicles):
            v = vehicles[vid]
            k = (tick - v["since"]) // self.step_ticks
            q = v["plan"][k] if k < len(v["plan"]) else NONE
            if q < 0:
                continue
            goal = int(decode_goal(v["goal"])[0])
            claim = self._clear(v["cells"], core, q, vid, owner, held, goal, exit_id, exit_port, inputs.connected)
            if claim is None:
                continue
            held[claim] = vid
            axis, sign = drive(q)
            wheels[v["cells"], axis] = sign * self.speed
        records = {vid: {"goal": v["goal"], "plan": v["plan"], "since": v["since"]} for vid, v in vehicles.items()}
        return ({"owner": owner, "vehicles": records, "plans": plans}, Mailbox.empty(self.schema, n, P), wheels)

    def _clear(self, cells, core, q, vid, owner, held, goal, exit_id, exit_port, connected):
        """The cells ahead the vehicle holds when it may ride through port q now (``gap`` free cells ahead of every
        front cell, or the way out of its exit lane), else None."""
        nb = self.neighbor
        member = np.zeros(len(owner), dtype=bool)
        member[cells] = True
        depth = self.gap
        claim = []
        for c in cells:
            if nb[c, q] >= 0 and member[nb[c, q]]:
                continue  # not a front cell
            if not connected[c, q]:
                if exit_id[c] == goal and exit_port[c] == q:
                    continue  # leaving through its exit
                if core[c]:
                    return None  # the edge or a hole: closed
                continue  # only its edge hangs over
            run = c
            for _ in range(depth):
                nxt = nb[run, q] if connected[run, q] else NONE
                if nxt < 0:
                    break
                if (owner[nxt] >= 0 and owner[nxt] != vid) or held[nxt] >= 0:
                    return None
                claim.append(nxt)
                run = nxt
        return claim
