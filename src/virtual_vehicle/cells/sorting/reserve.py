"""A central reservation router, the upper bound the distributed sorter is measured against (the DynoPath idea:
time-expanded reservations over the cell graph). Units: SI (m, s, m/s); time in the plans counts *steps*, the
ticks a parcel takes to ride one pitch at ``speed``.

One computer sees every cell's sensors. Each parcel is the group of cells it lights, as for
:class:`~virtual_vehicle.cells.sorting.CentralSorter`; its *footprint* is the rectangle of cells whose centre it
covers (sensor 0). Every step the router plans again, parcel by parcel, oldest first (prioritized planning, windowed
cooperative A*, Silver 2005): a parcel's plan is a sequence of moves (one pitch through a port, or wait) over the
next ``window`` steps, found by A* in (row, column, step) against a reservation table that holds, for every step,
what the parcels planned before it need in that step: the footprint it sweeps and, while it moves through port q,
the ``gap`` cells beyond it on side q as wide as its lit cells, its room to stop (what the check at every tick keeps
free). A move or a wait is allowed only if the footprint it sweeps, grown by two cells on every side (its lit cells
reach a cell past the covered centres, and one more keeps two parcels' lit cells from joining) and on the side it
moves toward to ``gap`` cells, meets none of that. Only the side a parcel moves toward keeps the whole gap, as the
kinematic bound counts it: streams may pass side by side and cross nearer (on ``facility_40x40``, whose gap is 5
cells, a gap on every side left room for few parcels on the floor; the check at every tick below may hold a parcel a
little longer than its plan). A parcel that already stands nearer to a parcel planned before it keeps at least the
spacing it has (its margin is cut to that): else not even waiting would be allowed, it would find no plan and stand,
reserved where it stands, and the parcels near it after it, and so on. Nor does a plan move a parcel toward the
array's edge or a hole with fewer cells beyond its footprint than it runs on after its wheels are told to stop
(``room``, at most ``gap``), unless that edge is its exit's open side (on the industrial drive parcels rode off the
array). The heuristic is the exact distance on the empty map (breadth-first over the footprint's positions, one-way
arrows, the array's holes and that room respected), so a parcel alone rides a shortest path; a plan is judged at the
window's end by the whole distance left (capped at the window, every plan of a parcel farther away would look
alike); where plans tie, the deeper, then the one with fewer turns, then straight on (a turn costs the wheels'
response, longer than a step). A parcel is at its goal once its front line (its row or column of cells nearest the
exit's open side) lies in its exit lane; from there it rides straight out. The map is read from the links at every
plan: a dead or cut-off cell is a hole, so plans go around faults as soon as they appear.

Why it does not deadlock: priority is age, one total order that every plan uses. The oldest parcel plans against
the map alone, so its plan leads toward its exit whenever the map has a way. A younger parcel plans against the
older ones' reservations, which may run through the place it stands: its only plans then are those that get out of
the way in time (backing off along an aisle met head on, stepping aside into free rows), so no two parcels ever
plan to wait for each other; the oldest leaves, and the next is oldest. Where a younger parcel has no room to get
out of the way (boxed in, or on a one-way aisle pointing at the older one) it finds no plan; planning then starts
over with it standing where it is for the whole window, and the older ones plan around it or wait for it. That is
the case the order alone does not cover: two parcels each standing in the only way of the other stay where they
are (reported as stalls). Between plans every parcel rides its plan's current move only while ``gap`` cells ahead
of every cell it lights are free of other parcels (checked at every tick, as the central sorter does) and its room to
stop is on the array, so a parcel behind or ahead of its plan (wheels and parcels take time to speed up) never
collides nor rides off. The free cells it holds ahead turn with it: a cell a parcel rides onto is up to speed (on the
industrial drive, whose wheels take ~0.6 s to reach 1.1 m/s, parcels that only turned the cells under them rode at
~0.65 m/s). The router does not sequence parcels (no parking).
"""

from __future__ import annotations

import heapq
from collections import deque

import numpy as np

from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.sorting.rules import NONE, decode_goal, drive, tick_of, vehicle_id
from virtual_vehicle.cells.sorting.seen import parcels_seen

STOP_RESPONSE, STOP_DECELERATION = 0.15, 2.5
"""The drive a parcel's room to stop is judged by (s, m/s^2): the industrial profile's wheels run on ~0.15 s after
they are told to stop, then slow at up to 2.5 m/s^2 (:data:`~virtual_vehicle.cells.hardware.PROFILES`)."""

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
        stop = self.speed * STOP_RESPONSE + self.speed ** 2 / (2 * STOP_DECELERATION)  # m
        # cells kept before an edge: the run-on less the cell its centre of mass lies behind its footprint's front
        self.room = min(self.gap, max(0, int(np.ceil(stop / self.pitch - 1e-9)) - 1))
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
        anchor, anchors with room to stop beyond each side (:meth:`_room`)) for an h x w footprint heading out of
        exit ``goal`` through ``out_port``; distances by breadth-first search backwards from the goal anchors, over
        moves that keep that room."""
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
            room = self._room(goal, out_port, h, w)
            dist = np.full(valid.shape, np.iinfo(np.int64).max, dtype=np.int64)
            todo = deque(zip(*np.nonzero(at_goal)))
            for r, c in todo:
                dist[r, c] = 0
            while todo:
                r, c = todo.popleft()
                for q in range(4):  # a predecessor moves through q into (r, c)
                    pr, pc = r - DR[q], c - DC[q]
                    if (0 <= pr < valid.shape[0] and 0 <= pc < valid.shape[1] and valid[pr, pc] and room[q][r, c]
                            and not banned[q][pr, pc] and dist[pr, pc] > dist[r, c] + 1):
                        dist[pr, pc] = dist[r, c] + 1
                        todo.append((pr, pc))
            out = (valid, at_goal, banned, dist, room)
        self._cache[key] = out
        return out

    def _room(self, goal, out_port, h, w):
        """For each port q, the anchors where the ``room`` rows or columns just beyond an h x w footprint's side q
        are all cells to ride on, or the open side of exit ``goal``'s lane (``out_port``): a parcel moves toward the
        array's edge or a hole only while it has room to stop before it (``room``: the cells a parcel at ``speed``
        runs on after its wheels are told to stop, :data:`STOP_RESPONSE` and :data:`STOP_DECELERATION`, less the cell
        its centre of mass lies behind the footprint's front, which must stay on the array; at most ``gap``: 4 at
        1.1 m/s on 10 cm cells, none at 0.3 m/s), except out of its own exit; :meth:`_clear` keeps the same room at
        every tick."""
        R, C = self.shape
        g = self.room
        if g == 0:
            return [np.ones((R - h + 1, C - w + 1), dtype=bool)] * 4
        open_ = np.zeros((R + 2 * g, C + 2 * g), dtype=bool)
        open_[g:g + R, g:g + C] = self._use
        if out_port >= 0:
            lane_r, lane_c = np.nonzero(self._exit == goal)
            for k in range(1, g + 1):  # beyond the lane's open side, off the array
                rr, cc = lane_r + k * DR[out_port], lane_c + k * DC[out_port]
                off = (rr < 0) | (rr >= R) | (cc < 0) | (cc >= C)
                open_[rr[off] + g, cc[off] + g] = True
        rows, cols = np.arange(R - h + 1)[:, None] + g, np.arange(C - w + 1)[None, :] + g
        across, along = self._fits(open_, h, g), self._fits(open_, g, w)  # beside an east/west, a north/south side
        return [across[rows, cols + w], along[rows + h, cols], across[rows, cols - g], along[rows - g, cols]]

    # --- planning -------------------------------------------------------------------------------------------------
    def _region(self, r, c, nr, nc, h, w, grow, q=NONE, ahead=0):
        """Slices of the grid the footprint sweeps moving from anchor (r, c) to (nr, nc), grown by ``grow`` on every
        side and, moving through port ``q``, by ``ahead`` more cells on the side it moves to."""
        R, C = self.shape
        r0, r1 = min(r, nr) - grow, max(r, nr) + h + grow
        c0, c1 = min(c, nc) - grow, max(c, nc) + w + grow
        if q >= 0:
            r0, r1 = r0 - ahead * (DR[q] < 0), r1 + ahead * (DR[q] > 0)
            c0, c1 = c0 - ahead * (DC[q] < 0), c1 + ahead * (DC[q] > 0)
        return slice(max(r0, 0), max(min(r1, R), 0)), slice(max(c0, 0), max(min(c1, C), 0))

    def _zone(self, r, c, nr, nc, h, w, q):
        """Slices of the grid a parcel moving through port q from anchor (r, c) to (nr, nc) keeps free to stop in:
        the ``gap`` rows or columns beyond the footprint it sweeps on side q, as wide as its lit cells (a cell more
        on either side), as :meth:`_clear` keeps them at every tick."""
        R, C = self.shape
        r0, r1 = min(r, nr) - 1, max(r, nr) + h + 1
        c0, c1 = min(c, nc) - 1, max(c, nc) + w + 1
        if DR[q]:
            r0, r1 = (r1 - 1, r1 - 1 + self.gap) if DR[q] > 0 else (r0 + 1 - self.gap, r0 + 1)
        else:
            c0, c1 = (c1 - 1, c1 - 1 + self.gap) if DC[q] > 0 else (c0 + 1 - self.gap, c0 + 1)
        return slice(max(r0, 0), max(min(r1, R), 0)), slice(max(c0, 0), max(min(c1, C), 0))

    def _plan(self, start, h, w, maps, out_port, reserved, heading=NONE):
        """Moves (port, or -1 to wait) for ``window`` steps from anchor ``start``: A* in (row, column, step) against
        ``reserved`` (W + 1, R, C), deeper first where plans tie, then the fewer turns (a change of the port moved
        through; ``heading``, the port the parcel rides through now, counts for the first move), then straight on:
        the wheels take ~0.15 s to turn a parcel, longer than a step, so a staircase would crawl. None when no plan
        keeps clear of the reservations (not even waiting)."""
        W, gap = self.window, self.gap
        valid, at_goal, banned, dist, room = maps
        inf = np.iinfo(np.int64).max
        r0, c0 = start
        if at_goal[r0, c0]:  # in its lane: out through the open side, reserving the cells it sweeps
            return [out_port] * W
        margin = 2  # its lit cells (a cell past the footprint) and one free cell between them and another's body
        while margin > 0 and reserved[(0, *self._region(r0, c0, r0, c0, h, w, margin))].any():
            margin -= 1  # already nearer to a parcel planned before: it keeps at least the spacing it has
        heap = [(int(dist[r0, c0]), 0, 0, 0, (r0, c0, 0))]  # f, -step (deeper first), turns, order, node
        parent = {(r0, c0, 0): None}
        head = {(r0, c0, 0): heading}  # the port each node was reached through (a wait keeps it)
        closed = set()
        count = 0
        while heap:
            _, _, turns, _, node = heapq.heappop(heap)
            if node in closed:
                continue
            closed.add(node)
            r, c, t = node
            if t == W or at_goal[r, c]:
                moves = []
                while parent[node] is not None:
                    node, q = parent[node]
                    moves.append(q)
                moves.reverse()
                return moves + [out_port] * (W - len(moves))
            d = head[node]
            for q in (d, *(p for p in (0, 1, 2, 3) if p != d), -1) if d >= 0 else (0, 1, 2, 3, -1):
                if q >= 0:
                    nr, nc = r + DR[q], c + DC[q]
                    if (banned[q][r, c] or not (0 <= nr < valid.shape[0] and 0 <= nc < valid.shape[1])
                            or not valid[nr, nc] or not room[q][nr, nc] or dist[nr, nc] == inf):
                        continue
                else:
                    nr, nc = r, c
                rows, cols = self._region(r, c, nr, nc, h, w, margin, q, max(gap - margin, 0))
                if reserved[t, rows, cols].any():
                    continue
                child = (nr, nc, t + 1)
                if child in parent:
                    continue
                parent[child] = (node, q)
                head[child] = d if q < 0 else q
                count += 1
                turned = turns + (0 <= d != q >= 0)
                heapq.heappush(heap, (t + 1 + int(dist[nr, nc]), -(t + 1), turned, count, child))
        return None

    def _reserve(self, reserved, start, moves, h, w):
        """Mark in ``reserved`` what the parcel needs at every step of ``moves``: the footprint it sweeps and, moving
        through port q, its room to stop ahead (:meth:`_zone`)."""
        r, c = start
        for t, q in enumerate(moves):
            nr, nc = (r + DR[q], c + DC[q]) if q >= 0 else (r, c)
            reserved[(t, *self._region(r, c, nr, nc, h, w, 0))] = True
            if q >= 0:
                reserved[(t, *self._zone(r, c, nr, nc, h, w, q))] = True
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
                    moves = self._plan((r, c), h, w, maps, out_port, reserved, vehicles[vid].get("heading", NONE))
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
            wheels[claim, axis] = sign * self.speed  # the free cells it holds ahead are up to speed when it comes
            v["heading"] = q
        records = {vid: {"goal": v["goal"], "plan": v["plan"], "since": v["since"], "heading": v.get("heading", NONE)}
                   for vid, v in vehicles.items()}
        return ({"owner": owner, "vehicles": records, "plans": plans}, Mailbox.empty(self.schema, n, P), wheels)

    def _clear(self, cells, core, q, vid, owner, held, goal, exit_id, exit_port, connected):
        """The cells ahead the vehicle holds when it may ride through port q now (``gap`` free cells ahead of every
        front cell, or the way out of its exit lane), else None. Nor may it ride toward the array's edge or a hole
        nearer than ``room`` cells ahead of its footprint (the cells whose centre it covers), unless that is its
        exit's way out: its wheels run on after they are told to stop (:meth:`_room`, as the plans keep)."""
        nb = self.neighbor
        member = np.zeros(len(owner), dtype=bool)
        member[cells] = True
        depth = self.gap
        for c in cells[core[cells]]:
            if nb[c, q] >= 0 and core[nb[c, q]]:
                continue  # not a front cell of the footprint
            run = c
            for _ in range(self.room):
                if not connected[run, q]:
                    if exit_id[run] == goal and exit_port[run] == q:
                        break
                    return None  # the edge or a hole within its stopping room, not its exit's way out
                run = nb[run, q]
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
