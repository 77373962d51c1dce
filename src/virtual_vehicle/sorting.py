"""The Virtual Vehicle as a distributed cell program: parcels sorted to exits by local decisions only (paper
Section 1 and Figure 2: each parcel moves as if it rode its own vehicle, made of whichever cells are under it).

Units: SI (m/s for wheel speeds). Every rule below reads only the cell's own sensors, state and configuration and
what its neighbours said last tick (:mod:`virtual_vehicle.network.programs` contract, checked by
:func:`~virtual_vehicle.network.programs.check_program`).

- *Routing*: one hop-distance gradient per exit (distance vector; a cell on the array's edge counts
  ``1 + edge_cost`` hops, so parcels travel inside the array and meet the edge only at their exit). A parcel
  descends the gradient of its goal exit, so it finds its exit, and a detour around dead cells, without any cell
  knowing the map.
- *Virtual vehicle tracking*: at an entry cell a new parcel gets an id (the tick it arrived, so smaller ids are
  older vehicles) and the goal its label gives (a barcode reader at the entry: ``labels``); the cells of a new
  parcel settle on the smallest of the ids the entry cells made. A cell that starts seeing a parcel adopts the
  record (id, goal) of a neighbour whose vehicle is moving into it (else the smallest id heard); elsewhere a cell
  never changes vehicle while it sees one. Cells under one vehicle agree on its direction: every cell proposes
  (its distance to the goal, the port toward its closest neighbour); the smallest proposal (the front cell's)
  spreads through the vehicle within ``reach`` hops (hop-limited, so what a departed cell said is soon forgotten),
  the current direction preferred on a tie so the vehicle does not dither.
- *Traffic*: a vehicle moves only along cells it holds. Each front cell (whose neighbour ahead is not under the
  same vehicle) asks that neighbour; an empty cell grants itself to the asking vehicle (the oldest when several
  ask, every tick: the older parcel goes first at a merge, and a younger one yields even a cell it held, so two
  vehicles never wait for each other) and passes the request on, ``gap + 1`` cells deep. A held cell reports back
  how many held cells run ahead of it; a vehicle moves when the run ahead of every front cell is at least ``gap``
  long (or leads off the array at its exit), else all its cells stop. Stopping and going spread through the
  vehicle like its direction. Parcels therefore keep ``gap`` free cells between them and do not collide.
- *Exits*: a cell of the goal's exit lane drives the vehicle out through the lane's open side once the vehicle lies
  within the lane (no cell beside it, across the way out, is under the vehicle without belonging to the lane);
  until then such cells move the vehicle sideways into the lane. Nowhere else may a vehicle move over the edge: a
  front cell with no neighbour ahead stops it.
"""

from __future__ import annotations

import numpy as np

from .network.messages import Mailbox, Schema
from .network.programs import UNREACHABLE, CellInputs
from .network.sentence import WordType

MAX_EXITS = 4
_NONE = -1
_BIG = 1 << 20  # above any direction key
_HUGE = 1 << 40  # above any vehicle id
_ENTRY = -2  # the "ex" word of an entry cell


def _weighted_gradient(dist_in, present, is_source, cost, cap: int = UNREACHABLE):
    """Distance-vector step with a per-cell cost (hops): a source is at 0, any other cell at its cost plus the
    smallest distance it trusts from a neighbour, capped (unreachable)."""
    heard = np.where(present, dist_in.astype(np.int64), cap)
    best = heard.min(axis=1) if heard.shape[1] else np.full(len(is_source), cap)
    return np.where(is_source, 0, np.minimum(best + cost, cap)).astype(np.int64)


def _key(dist, same, port, hops):
    """Direction proposals ordered by distance to the goal, then keeping the current direction, then port."""
    return ((dist * 2 + (1 - same)) * 8 + port) * 64 + hops


class Sorter:
    """Distributed sorting program (see the module notes).

    Args:
        speed: wheel surface speed of a moving vehicle, m/s.
        gap: free cells a vehicle keeps ahead of it.
        reach: hops over which a vehicle's cells share direction and stop/go (at least its size in cells).
        max_age: ticks a neighbour's words are trusted after it was last heard (0 on ideal rounds).
        edge_cost: extra hops a cell on the edge of the array (not an exit) counts in the gradients.
        period: the control period (s): a vehicle's id is the tick it was made (times 1024, plus its entry cell's
            installation number modulo 1024), so smaller ids are older vehicles.

    Sensor 0 of every cell must be its centre (the default layout): a cell whose centre is covered carries the
    parcel; the others only see its edge.

    Config (per cell): ``exit`` exit id or -1; ``exit_port`` the way out of the array for an exit cell (the
    side through which its exit lane leaves);
    ``entry`` bool; ``entry_no`` an entry cell's installation number. Inputs: ``labels`` (goal exit read at entry
    cells, -1 for none).
    """

    schema = Schema.of(d0=(1, WordType.U8), d1=(2, WordType.U8), d2=(3, WordType.U8), d3=(4, WordType.U8),
                       vid=(5, WordType.I32), goal=(6, WordType.I16), key=(7, WordType.I32),
                       stop=(8, WordType.U8), req=(9, WordType.I32), rdep=(10, WordType.U8),
                       hold=(11, WordType.I32), ack=(12, WordType.U8), ex=(13, WordType.I16),
                       blk=(14, WordType.I32))

    def __init__(self, speed: float, gap: int = 2, reach: int = 8, max_age: int = 0, edge_cost: int = 3,
                 period: float = 0.01):
        if not speed > 0:
            raise ValueError("speed must be positive (m/s)")
        if not 1 <= reach <= 62:
            raise ValueError("reach must be 1..62 hops")
        self.speed = float(speed)
        self.gap = int(gap)
        self.reach = int(reach)
        self.max_age = int(max_age)
        self.edge_cost = int(edge_cost)
        self.period = float(period)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.network.programs.CellProgram`)."""
        if ports != 4:
            raise ValueError("the sorter runs on square lattices (four ports a cell)")
        P = ports
        return {"dist": np.full((n, MAX_EXITS), UNREACHABLE, dtype=np.int64),
                "heard": {f.name: np.zeros((n, P), dtype=np.int64) for f in self.schema.fields},
                "age": np.full((n, P), np.iinfo(np.int32).max, dtype=np.int64),
                "vid": np.full(n, _NONE, dtype=np.int64), "goal": np.full(n, _NONE, dtype=np.int64),
                "dir": np.full(n, _NONE, dtype=np.int64), "key": np.full(n, _BIG, dtype=np.int64),
                "stop": np.full(n, 255, dtype=np.int64), "hold": np.full(n, _NONE, dtype=np.int64),
                "hdep": np.zeros(n, dtype=np.int64), "hport": np.full(n, _NONE, dtype=np.int64),
                "ack": np.zeros(n, dtype=np.int64)}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.network.programs.CellProgram`."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        cfg = inputs.config
        exit_id = np.asarray(cfg.get("exit", np.full(n, _NONE)), dtype=np.int64)
        exit_port = np.asarray(cfg.get("exit_port", np.full(n, _NONE)), dtype=np.int64)
        entry = np.asarray(cfg.get("entry", np.zeros(n, bool)), dtype=bool)
        entry_no = np.asarray(cfg.get("entry_no", np.zeros(n)), dtype=np.int64)
        labels = np.full(n, _NONE) if getattr(inputs, "labels", None) is None else np.asarray(inputs.labels)
        rows = np.arange(n)
        # -- what the neighbours said (last heard, trusted while fresh)
        heard = {k: np.where(inbox.present, inbox.values[k].astype(np.int64), v) for k, v in state["heard"].items()}
        age = np.where(inbox.present, 0, np.minimum(state["age"] + 1, np.iinfo(np.int32).max))
        trusted = (age <= self.max_age) & inputs.connected
        # -- routing: one gradient per exit
        # A cell at the edge of the array (a side with no neighbour) costs more, so parcels travel inside it and
        # meet the edge only at their exit.
        cost = np.where(inputs.connected.all(axis=1) | (exit_id >= 0), 1, 1 + self.edge_cost)
        dist = np.stack([_weighted_gradient(heard[f"d{e}"], trusted, exit_id == e, cost) for e in range(MAX_EXITS)],
                        axis=1)
        # -- tracking
        lit = np.asarray(inputs.sensors, dtype=bool).any(axis=1)
        vid, goal = state["vid"].copy(), state["goal"].copy()
        vid[~lit] = _NONE
        goal[~lit] = _NONE
        # A cell that starts seeing a parcel takes the record of a neighbour whose vehicle is moving into it (else
        # the smallest id around). At the entry one new parcel may get several ids in its first tick: cells next to
        # entry cells settle on the smallest id those hold. Elsewhere a cell never changes vehicle while it sees one.
        toward = (heard["key"] < _BIG) & ((heard["key"] // 64) % 8 == (np.arange(P)[None, :] + 2) % 4)
        has = trusted & (heard["vid"] >= 0)
        score = np.where(has, np.where(toward, 0, _HUGE) + heard["vid"], 2 * _HUGE)
        pick = np.argmin(score, axis=1)
        found = score[rows, pick] < 2 * _HUGE
        best_vid = heard["vid"][rows, pick]
        nb_entry = np.where(has & (heard["ex"] == _ENTRY), heard["vid"], _HUGE)
        entry_min = nb_entry.min(axis=1) if P else np.full(n, _HUGE)
        adopt = lit & (vid < 0) & found
        vid[adopt] = best_vid[adopt]
        goal[adopt] = heard["goal"][rows, pick][adopt]
        merge = lit & (vid >= 0) & (entry_min < vid)
        if merge.any():
            k = np.argmin(nb_entry, axis=1)
            vid[merge] = entry_min[merge]
            goal[merge] = heard["goal"][rows, k][merge]
        fresh = lit & (vid < 0) & entry & (labels >= 0)
        # ids order vehicles by age (the tick they were made), which is the priority at a merge
        tick = int(round(inputs.t / self.period)) if self.period else 0
        vid[fresh] = tick * 1024 + entry_no[fresh] % 1024
        goal[fresh] = labels[fresh]
        on = lit & (vid >= 0) & (goal >= 0) & (goal < MAX_EXITS)
        same_nb = trusted & (heard["vid"] == vid[:, None]) & on[:, None]
        # -- direction: own proposal, then the smallest heard from the same vehicle (hop-limited)
        g = np.clip(goal, 0, MAX_EXITS - 1)
        nb_d = np.stack([heard[f"d{e}"] for e in range(MAX_EXITS)], axis=-1)[rows, :, g]  # (n, P)
        # At its exit a vehicle leaves through the edge once it lies within the exit's band: no cell beside an exit
        # cell (across the way out) is under the same vehicle without being part of that exit. Until then the exit
        # cells that see such a neighbour move the vehicle away from it, into the band. These proposals come first
        # (distance 0: into the band; 1: out), then the gradient's (the chosen neighbour's distance + 3).
        side = np.stack([(exit_port + 1) % 4, (exit_port + 3) % 4], axis=1)
        mine = on & (exit_id == goal) & (exit_port >= 0)
        into_band = np.full(n, _NONE)
        for c in range(2):
            sp = side[:, c]
            beside = mine & same_nb[rows, sp] & (heard["ex"][rows, sp] != goal)
            into_band = np.where(beside & (into_band < 0), (sp + 2) % 4, into_band)
        at_exit = mine & (into_band < 0)
        # The vehicle is a body, not a point: a side on which any cell carrying it (centre sensor lit) has no
        # neighbour (the array's edge, a dead cell, a cut link) is closed to the whole vehicle (spread hop-limited,
        # like stopping), except the way out at its exit. Each cell proposes its open side toward the neighbour
        # nearest the goal, ranked by that neighbour's distance: the front's proposals win, and a vehicle that
        # cannot go on sidesteps.
        core = on & np.asarray(inputs.sensors, dtype=bool)[:, 0]  # the cell carries the parcel (centre sensor lit)
        own_block = core[:, None] & ~inputs.connected
        own_block &= ~(at_exit[:, None] & (np.arange(P)[None, :] == exit_port[:, None]))
        nb_block = np.stack([(heard["blk"] >> (6 * q)) & 63 for q in range(P)], axis=-1)  # (n, from port, side)
        relayed = np.where(same_nb[:, :, None] & (nb_block < self.reach), nb_block + 1, 63).min(axis=1)
        block = np.where(own_block, 0, relayed)
        block = np.where(on[:, None], block, 63)
        open_side = trusted & (block > self.reach)
        cand = np.where(open_side, nb_d, _BIG)
        port = np.argmin(cand, axis=1)
        movable = cand[rows, port] < UNREACHABLE
        prop_port = np.where(into_band >= 0, into_band, np.where(at_exit, exit_port, np.where(movable, port, _NONE)))
        prop_d = np.where(into_band >= 0, 0, np.where(at_exit, 1, cand[rows, port] + 3))
        own_key = np.where(on & (prop_port >= 0), _key(prop_d, prop_port == state["dir"], np.maximum(prop_port, 0), 0),
                           _BIG)
        nb_key = np.where(same_nb, heard["key"], _BIG)
        nb_key = np.where(nb_key % 64 < self.reach, nb_key + 1, _BIG)  # one more hop; forget beyond reach
        key = np.minimum(own_key, nb_key.min(axis=1)) if P else own_key
        key = np.where(on, key, _BIG)
        direction = np.where(key < _BIG, (key // 64) % 8, _NONE)
        # -- traffic: requests ahead, holds, acknowledgements
        ahead_ok_port = (direction >= 0)
        dp = np.maximum(direction, 0)
        ahead_is_mine = same_nb[rows, dp] & ahead_ok_port
        front = on & ahead_ok_port & ~ahead_is_mine
        # leaving the array: only out of an exit cell of the goal (anywhere else the edge stops the vehicle)
        off_array = front & ~inputs.connected[rows, dp] & (exit_id == goal) & (dp == exit_port)
        # requests that arrived: from a neighbour's front cell or a held cell passing it on
        req = np.where(inbox.present & trusted & (inbox.values["req"] >= 0), inbox.values["req"].astype(np.int64),
                       _HUGE)  # requests are events: only what arrived this tick
        choice = np.argmin(req, axis=1)  # the oldest vehicle asking (smallest id) gets the cell, always
        new_hold = np.where(req[rows, choice] < _HUGE, req[rows, choice], _NONE)
        hport = np.where(new_hold >= 0, choice, _NONE)
        hdep = np.where(new_hold >= 0, inbox.values["rdep"].astype(np.int64)[rows, np.maximum(hport, 0)], 0)
        new_hold = np.where(lit, _NONE, new_hold)  # a cell under a parcel is that parcel's, not anyone's to hold
        hport = np.where(new_hold >= 0, hport, _NONE)
        # acknowledgement: how many held cells run ahead from here (the whole chain when it reaches the edge)
        L = self.gap + 1  # one cell of look-ahead beyond the gap keeps a moving vehicle's chain ahead of it
        fwd = (hport + 2) % 4
        fp = np.maximum(fwd, 0)
        succ = (new_hold >= 0) & trusted[rows, fp] & (heard["hold"][rows, fp] == new_hold)
        edge = (new_hold >= 0) & ~inputs.connected[rows, fp]
        ack = np.where(new_hold >= 0, np.where(edge, L, np.minimum(L, 1 + np.where(succ, heard["ack"][rows, fp], 0))),
                       0)
        # a front cell may go when the cell ahead is held for its vehicle with a full free run, or at the exit edge
        ahead_hold = heard["hold"][rows, dp]
        ahead_ack = heard["ack"][rows, dp]
        go_front = off_array | (trusted[rows, dp] & (ahead_hold == vid) & (ahead_ack >= self.gap))
        # a cell that only sees the parcel's edge may hang over the array's edge or a dead cell: only cells that
        # carry the parcel, or that have a neighbour ahead to ask, can stop it
        own_stop = np.where(front & ~go_front & (core | inputs.connected[rows, dp]), 0, 255)
        nb_stop = np.where(same_nb & (heard["stop"] < self.reach), heard["stop"] + 1, 255)
        stop = np.minimum(own_stop, nb_stop.min(axis=1)) if P else own_stop
        stop = np.where(on, stop, 255)
        moving = on & (direction >= 0) & (stop > self.reach)
        # -- outputs
        wheels = np.zeros((n, 2))
        sign = np.array([1.0, 1.0, -1.0, -1.0])
        axis = np.array([0, 1, 0, 1])
        wheels[rows[moving], axis[dp[moving]]] = sign[dp[moving]] * self.speed
        send = np.ones(n, dtype=bool)
        words = {f"d{e}": np.minimum(dist[:, e], UNREACHABLE) for e in range(MAX_EXITS)}
        out = Mailbox.broadcast(self.schema, send, P, **words, vid=np.where(on, vid, _NONE),
                                goal=np.where(on, goal, _NONE), key=np.minimum(key, 2**31 - 1),
                                stop=np.minimum(stop, 255), req=np.full(n, _NONE), rdep=np.zeros(n),
                                hold=np.where(lit & on, vid, new_hold), ack=np.minimum(ack, 255),
                                ex=np.where(entry, _ENTRY, exit_id),
                                blk=sum(np.minimum(block[:, q], 63) << (6 * q) for q in range(P)))
        # requests: front cells ask the cell ahead (depth 1); held cells pass it on until gap deep
        ask = front & inputs.connected[rows, dp]
        out.values["req"][rows[ask], dp[ask]] = vid[ask]
        out.values["rdep"][rows[ask], dp[ask]] = 1
        pass_on = (new_hold >= 0) & (hdep < L) & inputs.connected[rows, fp]
        out.values["req"][rows[pass_on], fwd[pass_on]] = new_hold[pass_on]
        out.values["rdep"][rows[pass_on], fwd[pass_on]] = hdep[pass_on] + 1
        new_state = {"dist": dist, "heard": heard, "age": age, "vid": vid, "goal": goal,
                     "dir": np.where(moving | (direction >= 0), direction, _NONE), "key": key, "stop": stop,
                     "hold": new_hold, "hdep": hdep, "hport": hport, "ack": ack}
        return new_state, out, wheels


class CentralSorter:
    """The central counterpart of :class:`Sorter`, for side-by-side comparison: one computer that sees every cell's
    sensors at once, with no network delay, applies the same policies globally each tick.

    It finds parcels as connected groups of lit cells, keeps their records (id = arrival tick, goal = the label
    read at an entry), routes each by shortest-path distances to its exit (Dijkstra on the cell graph, edge cells
    costing ``1 + edge_cost`` as in the cells' gradients; a parcel goes the way that brings the cells carrying it
    closest to the exit on average), never moves a parcel over the edge or a dead cell except
    out of its exit lane, moves it sideways into the lane at its exit, and grants cells ahead to the oldest parcel
    first, ``gap + 1`` deep (a parcel moves when ``gap`` are free ahead of every front cell).

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
        :class:`~virtual_vehicle.network.programs.CellProgram`)."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        topo = self.topo
        exit_id = np.asarray(config["exit"])
        conn = topo.connected
        cost = np.where(conn.all(axis=1) | (exit_id >= 0), 1.0, 1.0 + self.edge_cost)
        a, p = np.nonzero(conn)
        b = topo.neighbor[a, p]
        graph = coo_matrix((cost[a], (b, a)), shape=(n, n)).tocsr()  # stepping from b into a costs a's cost
        dist = np.full((MAX_EXITS, n), np.inf)
        for e in range(MAX_EXITS):
            src = np.flatnonzero(exit_id == e)
            if len(src):
                dist[e] = dijkstra(graph, indices=src, min_only=True)
        return {"dist": dist, "vehicles": {}, "owner": np.full(n, _NONE, dtype=np.int64)}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.network.programs.CellProgram`."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        topo, cfg = self.topo, inputs.config
        n, P = inputs.connected.shape
        lit = np.asarray(inputs.sensors, dtype=bool).any(axis=1) & topo.alive
        core = np.asarray(inputs.sensors, dtype=bool)[:, 0] & topo.alive
        exit_id = np.asarray(cfg["exit"])
        exit_port = np.asarray(cfg["exit_port"])
        entry = np.asarray(cfg["entry"], dtype=bool)
        labels = np.full(n, _NONE) if inputs.labels is None else np.asarray(inputs.labels)
        # parcels = connected groups of lit cells
        idx = np.flatnonzero(lit)
        pos = {c: k for k, c in enumerate(idx)}
        a, p = np.nonzero(inputs.connected[idx])
        b = topo.neighbor[idx[a], p]
        keep = lit[b]
        graph = coo_matrix((np.ones(int(keep.sum())), (a[keep], [pos[c] for c in b[keep]])), shape=(len(idx),) * 2)
        count, comp = connected_components(graph, directed=False) if len(idx) else (0, np.zeros(0, int))
        owner_prev = state["owner"]
        vehicles = {}
        owner = np.full(n, _NONE, dtype=np.int64)
        tick = int(round(inputs.t / self.period))
        for k in range(count):
            blob = idx[comp == k]
            prev = owner_prev[blob]
            prev = prev[prev >= 0]
            if len(prev):
                vid = int(np.bincount(prev - prev.min()).argmax() + prev.min())  # the record most of it had
                record = state["vehicles"].get(vid)
            else:
                record = None
            if record is None:
                lab = labels[blob[entry[blob] & (labels[blob] >= 0)]]
                if not len(lab):
                    continue  # an unknown parcel: nobody drives it
                vid = tick * 1024 + int(blob.min()) % 1024
                record = {"goal": int(lab[0]), "dir": _NONE}
            vehicles[vid] = {**record, "cells": blob}
            owner[blob] = vid
        wheels = np.zeros((n, 2))
        held = np.zeros(n, dtype=bool)
        sign = np.array([1.0, 1.0, -1.0, -1.0])
        axis = np.array([0, 1, 0, 1])
        for vid in sorted(vehicles):
            v = vehicles[vid]
            cells, goal = v["cells"], v["goal"]
            body = cells[core[cells]] if core[cells].any() else cells
            direction = self._direction(state["dist"][goal], cells, body, goal, exit_id, exit_port, inputs, v["dir"])
            v["dir"] = direction
            if direction < 0:
                continue
            go, claim = self._ahead(cells, body, direction, vid, owner, held, goal, exit_id, exit_port, inputs)
            if go:
                held[claim] = True
                wheels[cells, axis[direction]] = sign[direction] * self.speed
        return ({"dist": state["dist"], "vehicles": {k: {"goal": v["goal"], "dir": v["dir"]} for k, v in
                                                      vehicles.items()}, "owner": owner},
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
        best, best_score = _NONE, np.inf
        for q in range(4):
            if not inputs.connected[body, q].all():
                continue  # a cell carrying the parcel has no neighbour that way: closed
            score = float(np.mean(dist[topo.neighbor[body, q]]))  # where the carrying cells would be, on average
            if not np.isfinite(score):
                continue
            score = (score, q != current, q)
            if best < 0 or score < best_score:
                best, best_score = q, score
        return best

    def _ahead(self, cells, body, q, vid, owner, held, goal, exit_id, exit_port, inputs):
        """Whether the vehicle may move toward port q, and the cells it then holds."""
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
                    return False, []
                continue  # only its edge hangs over
            run = c
            for depth in range(self.gap + 1):
                nxt = topo.neighbor[run, q] if inputs.connected[run, q] else -1
                if nxt < 0:
                    break
                if (owner[nxt] >= 0 and owner[nxt] != vid) or held[nxt]:
                    if depth < self.gap:
                        return False, []
                    break
                claim.append(nxt)
                run = nxt
        return True, claim
