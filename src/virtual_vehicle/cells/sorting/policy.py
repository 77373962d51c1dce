"""The sorter's cell policy (the rules of :mod:`virtual_vehicle.cells.sorting`), compiled: :func:`step_cells` steps
cells one at a time, each through the policy's phases in order (hear, gradients, track, propose a direction, back
off, agree on the direction, hold cells ahead, stop or go, say). Units: SI (m/s for wheel speeds).

The arrays travel in a few records (named tuples, which numba compiles field by field): :class:`Words` (one array
per sentence word, in the schema's order), :class:`CellState` (the per-cell state words), :class:`Memory` (what a
cell keeps between ticks), :class:`Config`, :class:`Rules` (the sorter's numbers), :class:`Inputs`,
:class:`Outputs`, :class:`Said` (what a cell says) and :class:`Scratch` (working space, one entry per port, allocated
once a call).""" 

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from virtual_vehicle.cells.network.programs import UNREACHABLE
from virtual_vehicle.cells.sorting.rules import (BIG, ENTRY, HUGE, MAX_EXITS, NONE, PARK, direction_key, drive, due,
                                                 hop_cost, split_goal, unpack, vehicle_id)

Words = namedtuple("Words", "d nxt vid goal key stop req rdep hold ack ex blk")
"""The sorter's sentence words, one (n, P) array each, in the schema's order."""
CellState = namedtuple("CellState", "vid goal dir key stop hold hdep hport hage ack nxt park back bdir")
"""The per-cell state words (n,), int64, in the order the sorter's state holds them after ``dist``, ``heard``,
``age``."""
Memory = namedtuple("Memory", "heard age dist cell")
"""What a cell keeps between ticks: words last heard (:class:`Words`, int64), their ages (ticks), the exit
gradients' distances (n, MAX_EXITS) and the :class:`CellState`."""
Config = namedtuple("Config", "exit exit_port entry entry_no park forbid labels")
"""Per-cell configuration (see :class:`~virtual_vehicle.cells.sorting.Sorter`) and the labels read this tick."""
Rules = namedtuple("Rules", "tick max_age edge_cost reach gap back_ticks speed")
"""The tick stepped and the sorter's numbers (hops and ticks; ``speed`` in m/s)."""
Inputs = namedtuple("Inputs", "present arrived sensors connected")
"""Which words arrived (n, P), the words (:class:`Words`), the sensors (n, S) and the live links (n, P)."""
Outputs = namedtuple("Outputs", "present sent wheels unsettled out_changed")
"""Where the sentences go (a presence mask and :class:`Words`), the (n, 2) wheel speeds (m/s), and per row whether
the state and the sentences changed."""
Said = namedtuple("Said", "d nxt vid goal key stop hold ack ex blk")
"""The words a cell says on every port (its requests, per port, are in :class:`Scratch`)."""
Scratch = namedtuple("Scratch", "trusted allowed same_nb open_side score nb_entry cand req block to_req to_rdep")
"""Working space of one cell, one entry per port."""

_INT32_MAX = int(np.iinfo(np.int32).max)


@njit(cache=True)
def _first_min(a):
    """The index of the first smallest of ``a`` (numpy's argmin)."""
    best = 0
    for q in range(1, a.shape[0]):
        if a[q] < a[best]:
            best = q
    return best


@njit(cache=True, inline="always")
def _heard(present, word, heard_in, heard_out, i, q):
    """Port q of cell i hears ``word`` if it arrived, else what it heard last; whether that changed."""
    old = heard_in[i, q]
    heard_out[i, q] = np.int64(word) if present else old
    return heard_out[i, q] != old


@njit(cache=True, inline="always")
def _put(out, i, q, value):
    """Write ``value`` (as ``out``'s type) at (i, q); whether it differs from what was there."""
    old = out[i, q]
    out[i, q] = value
    return out[i, q] != old


@njit(cache=True, inline="always")
def _put1(out, before, i, value):
    """Write ``value`` at ``out[i]``; whether it differs from ``before[i]`` (read first: it may be ``out``)."""
    old = before[i]
    out[i] = value
    return value != old


@njit(cache=True)
def hear(i, inp, old, new, forbid, max_age, s):
    """What the neighbours said: a word that arrived replaces the one last heard, a port's age counts the ticks
    since; a port is trusted while fresh (``max_age``) and linked, allowed unless a one-way arrow forbids it.
    Fills ``s.trusted`` and ``s.allowed``; whether the words heard or their ages changed."""
    P = inp.present.shape[1]
    w, h, hin = inp.arrived, new.heard, old.heard
    changed = False
    for q in range(P):
        p = inp.present[i, q]
        changed |= _heard(p, w.d[i, q], hin.d, h.d, i, q)
        changed |= _heard(p, w.nxt[i, q], hin.nxt, h.nxt, i, q)
        changed |= _heard(p, w.vid[i, q], hin.vid, h.vid, i, q)
        changed |= _heard(p, w.goal[i, q], hin.goal, h.goal, i, q)
        changed |= _heard(p, w.key[i, q], hin.key, h.key, i, q)
        changed |= _heard(p, w.stop[i, q], hin.stop, h.stop, i, q)
        changed |= _heard(p, w.req[i, q], hin.req, h.req, i, q)
        changed |= _heard(p, w.rdep[i, q], hin.rdep, h.rdep, i, q)
        changed |= _heard(p, w.hold[i, q], hin.hold, h.hold, i, q)
        changed |= _heard(p, w.ack[i, q], hin.ack, h.ack, i, q)
        changed |= _heard(p, w.ex[i, q], hin.ex, h.ex, i, q)
        changed |= _heard(p, w.blk[i, q], hin.blk, h.blk, i, q)
        before = old.age[i, q]
        new.age[i, q] = 0 if p else min(before + 1, _INT32_MAX)
        changed |= new.age[i, q] != before
        s.trusted[q] = (new.age[i, q] <= max_age) and inp.connected[i, q]
        s.allowed[q] = q != forbid[i]
    return changed


@njit(cache=True)
def gradients(i, inp, cfg, old, new, edge_cost, park_any, s):
    """Routing: one hop-distance gradient per exit (distance vector over trusted, allowed ports; a hop into this
    cell costs :func:`~virtual_vehicle.cells.sorting.rules.hop_cost`), gradient PARK leading to a parking cell no
    parcel covers when the cells stepped have any. Writes the cell's row of ``new.dist``; whether it changed."""
    P = inp.present.shape[1]
    linked = True
    for q in range(P):
        linked = linked and inp.connected[i, q]
    cost = hop_cost(linked, cfg.exit[i], edge_cost)
    changed = False
    for e in range(MAX_EXITS):
        source = cfg.exit[i] == e
        if e == PARK and park_any:
            source = cfg.park[i] and not inp.sensors[i, 0]
        best = UNREACHABLE
        for q in range(P):
            best = min(best, unpack(new.heard.d[i, q], e, 8) if (s.trusted[q] and s.allowed[q]) else UNREACHABLE)
        before = old.dist[i, e]
        new.dist[i, e] = 0 if source else min(best + cost, UNREACHABLE)
        changed |= new.dist[i, e] != before
    return changed


@njit(cache=True)
def due_next(i, h, nxt, s):
    """Sequencing: the number due next at the exits, the highest this cell or a trusted neighbour knows."""
    most = h.nxt[i, 0] if s.trusted[0] else 0
    for q in range(1, s.trusted.shape[0]):
        most = max(most, h.nxt[i, q] if s.trusted[q] else 0)
    return max(nxt[i], most)


@njit(cache=True)
def track(i, lit, h, cell, cfg, tick, s):
    """Virtual vehicle tracking: the (vehicle id, goal) this cell is under. A cell that starts seeing a parcel takes
    the record of a neighbour whose vehicle is moving into it (else the smallest id around); cells next to entry
    cells settle on the smallest id those hold; an entry cell that sees an unknown labelled parcel makes a vehicle
    (:func:`~virtual_vehicle.cells.sorting.rules.vehicle_id`). Elsewhere a cell never changes vehicle."""
    P = s.trusted.shape[0]
    vid, goal = cell.vid[i], cell.goal[i]
    if not lit:
        vid, goal = NONE, NONE
    for q in range(P):
        toward = (h.key[i, q] < BIG) and ((h.key[i, q] // 64) % 8 == (q + 2) % 4)
        has = s.trusted[q] and h.vid[i, q] >= 0
        s.score[q] = ((0 if toward else HUGE) + h.vid[i, q]) if has else 2 * HUGE
        s.nb_entry[q] = h.vid[i, q] if (has and h.ex[i, q] == ENTRY) else HUGE
    pick = _first_min(s.score)
    found = s.score[pick] < 2 * HUGE
    best_vid = h.vid[i, pick]
    entry_min = s.nb_entry[0]
    for q in range(1, P):
        entry_min = min(entry_min, s.nb_entry[q])
    if lit and vid < 0 and found:
        vid = best_vid
        goal = h.goal[i, pick]
    if lit and vid >= 0 and entry_min < vid:
        k = _first_min(s.nb_entry)
        vid = entry_min
        goal = h.goal[i, k]
    if lit and vid < 0 and cfg.entry[i] and cfg.labels[i] >= 0:
        vid = vehicle_id(tick, cfg.entry_no[i])
        goal = cfg.labels[i]
    return vid, goal


@njit(cache=True)
def propose(i, on, core, target, g, h, inp, cfg, reach, s):
    """This cell's direction proposal (port, distance rank; port -1: none). At its exit a vehicle leaves through
    the edge once it lies within the exit's band (rank 1), and exit cells that see a part of it beside the band move
    it into the band (rank 0); elsewhere the cell proposes its open side toward the neighbour nearest the goal on
    gradient ``g`` (rank: that distance + 3). A side is closed to the whole vehicle when a cell carrying it has no
    neighbour (or an arrow) there, as its cells relay within ``reach`` hops; fills ``s.block`` and
    ``s.open_side``."""
    P = s.trusted.shape[0]
    ep = cfg.exit_port[i]
    mine = on and cfg.exit[i] == target and ep >= 0
    into_band = NONE
    for c in range(2):
        sp = (ep + 1) % 4 if c == 0 else (ep + 3) % 4
        beside = mine and s.same_nb[sp] and h.ex[i, sp] != target
        if beside and into_band < 0:
            into_band = (sp + 2) % 4
    at_exit = mine and into_band < 0
    for q in range(P):
        own_block = core and (not inp.connected[i, q] or not s.allowed[q])
        own_block = own_block and not (at_exit and q == ep)
        relayed = 63
        if on:
            for p in range(P):
                b = unpack(h.blk[i, p], q, 6)
                relayed = min(relayed, b + 1 if (s.same_nb[p] and b < reach) else 63)
        s.block[q] = 0 if own_block else relayed
        if not on:
            s.block[q] = 63
        s.open_side[q] = s.trusted[q] and s.block[q] > reach
        s.cand[q] = unpack(h.d[i, q], g, 8) if s.open_side[q] else BIG
    port = _first_min(s.cand)
    movable = s.cand[port] < UNREACHABLE
    if into_band >= 0:
        return into_band, 0
    if at_exit:
        return ep, 1
    return (port if movable else NONE), s.cand[port] + 3


@njit(cache=True)
def back_off(i, on, vid, h, cell, back_ticks, s):
    """Head on: the cell ahead (in last tick's direction) is held for an older vehicle that asked for it from the
    far side, or carries an older vehicle heading this way. The younger vehicle backs off for ``back_ticks``.
    Returns (ticks left backing off, the port it backs off through, whether it backs off now)."""
    sdir = cell.dir[i]
    pd = max(sdir, 0)
    ahead_vid = h.hold[i, pd] if s.trusted[pd] else NONE
    ahead_from = (h.ack[i, pd] >> 8) - 1
    coming = ((h.key[i, pd] < BIG) and ((h.key[i, pd] // 64) % 8 == (pd + 2) % 4)
              and h.vid[i, pd] == ahead_vid)
    head_on = (on and sdir >= 0 and ahead_vid >= 0 and ahead_vid < vid and not s.same_nb[pd]
               and (ahead_from == pd or coming))
    back = max(cell.back[i] - 1, 0) if on else 0
    bdir = (pd + 2) % 4 if head_on else cell.bdir[i]
    if head_on:
        back = back_ticks
    backing = back > 0 and s.open_side[max(bdir, 0)] and bdir >= 0
    return back, bdir, backing


@njit(cache=True)
def agree(i, on, prop_port, prop_d, h, cell, reach, s):
    """The vehicle's direction key: the smallest of this cell's proposal and those its vehicle's cells relayed (one
    hop more; forgotten beyond ``reach``), the current direction preferred on a tie. Returns (key, port or -1)."""
    own_key = BIG
    if on and prop_port >= 0:
        own_key = direction_key(prop_d, 1 if prop_port == cell.dir[i] else 0, max(prop_port, 0), 0)
    least = 0
    for q in range(s.trusted.shape[0]):  # one more hop; forget beyond reach
        nk = h.key[i, q] if s.same_nb[q] else BIG
        nk = nk + 1 if nk % 64 < reach else BIG
        least = nk if q == 0 else min(least, nk)
    key = min(own_key, least)
    if not on:
        key = BIG
    direction = (key // 64) % 8 if key < BIG else NONE
    if direction >= s.trusted.shape[0]:  # a key word from no sorter
        raise IndexError("a direction key names a port the cell does not have")
    return key, direction


@njit(cache=True)
def _spread(own, stop_word, field, on, reach, s):
    """Hops to the nearest cell of the same vehicle that said 0 (``own`` 0 here) in field ``field`` of the
    neighbours' packed ``stop`` words, forgotten beyond ``reach``."""
    out = own
    for q in range(s.same_nb.shape[0]):
        v = unpack(stop_word[q], field, 8)
        nb = v + 1 if s.same_nb[q] and v < reach else 255
        out = min(out, nb)
    return out if on else 255


@njit(cache=True)
def hold(i, lit, inp, cell, max_age, s):
    """Holding cells ahead for the oldest vehicle that asks (requests are events: only what arrived this tick),
    kept ``max_age`` ticks after the last request unless an older vehicle asks; a cell under a parcel holds for no
    one. Returns (the vehicle held for or -1, the depth of its request, the port asked through, the hold's age,
    the run of held cells ahead: the acknowledgement)."""
    P = s.trusted.shape[0]
    w_req = inp.arrived.req
    for q in range(P):
        s.req[q] = np.int64(w_req[i, q]) if (inp.present[i, q] and s.trusted[q] and w_req[i, q] >= 0) else HUGE
    choice = _first_min(s.req)
    new_hold = s.req[choice] if s.req[choice] < HUGE else NONE
    hport = choice if new_hold >= 0 else NONE
    hdep = np.int64(inp.arrived.rdep[i, max(hport, 0)]) if new_hold >= 0 else 0
    keep = cell.hold[i] >= 0 and cell.hage[i] < max_age and (new_hold < 0 or cell.hold[i] < new_hold)
    if keep:
        new_hold, hport, hdep = cell.hold[i], cell.hport[i], cell.hdep[i]
    hage = cell.hage[i] + 1 if keep else 0
    if lit:
        new_hold = NONE
    if new_hold < 0:
        hport = NONE
    return new_hold, hdep, hport, hage


@njit(cache=True)
def acknowledge(i, new_hold, hport, h, inp, gap, s):
    """How many held cells run ahead from a held cell (the whole chain, ``gap + 1``, when it reaches the edge)."""
    L = gap + 1
    fp = max((hport + 2) % 4, 0)
    succ = new_hold >= 0 and s.trusted[fp] and h.hold[i, fp] == new_hold
    edge = new_hold >= 0 and not inp.connected[i, fp]
    run_ahead = h.ack[i, fp] & 255 if succ else 0
    return (L if edge else min(L, 1 + run_ahead)) if new_hold >= 0 else 0


@njit(cache=True)
def gradient_word(i, on, parked, h, new, reach, s):
    """The gradients this cell says, packed: none through a parked parcel, nor through a gap of one cell beside it
    (too narrow for a parcel)."""
    beside_parked = False
    for q in range(s.trusted.shape[0]):
        beside_parked = beside_parked or (s.trusted[q] and unpack(h.stop[i, q], 1, 8) <= reach)
    beside_parked = beside_parked and not (on and not parked)
    word = 0
    for e in range(MAX_EXITS):
        said = UNREACHABLE if (parked or beside_parked) else min(new.dist[i, e], UNREACHABLE)
        word += said << (8 * e)
    return word - (1 << 32) if word >= 1 << 31 else word


@njit(cache=True)
def closed_word(s):
    """The hops to a closed side, per side (``s.block``), packed six bits a side."""
    blk = 0
    for q in range(s.block.shape[0]):
        blk += min(s.block[q], 63) << (6 * q)
    return blk - (1 << 32) if blk >= 1 << 31 else blk


@njit(cache=True)
def requests(i, front, dp, vid, new_hold, hdep, hport, inp, gap, s):
    """The requests this cell sends, per port (``s.to_req``, ``s.to_rdep``: vehicle id and depth; -1 and 0 for
    none): a front cell asks the cell ahead, a held cell passes the request on until ``gap + 1`` deep."""
    for q in range(s.to_req.shape[0]):
        s.to_req[q], s.to_rdep[q] = NONE, 0
    if front and inp.connected[i, dp]:
        s.to_req[dp], s.to_rdep[dp] = vid, 1
    fwd = (hport + 2) % 4
    if new_hold >= 0 and hdep < gap + 1 and inp.connected[i, max(fwd, 0)]:
        s.to_req[fwd], s.to_rdep[fwd] = new_hold, hdep + 1


@njit(cache=True)
def say(i, said, out, s):
    """Send the sentence (``said``, a :class:`Said`, and the requests in ``s``) on every port; whether it differs
    from what ``out`` held."""
    o = out.sent
    sent_new = False
    for q in range(out.present.shape[1]):
        sent_new |= not out.present[i, q]
        out.present[i, q] = True
        sent_new |= _put(o.d, i, q, said.d)
        sent_new |= _put(o.nxt, i, q, said.nxt)
        sent_new |= _put(o.vid, i, q, said.vid)
        sent_new |= _put(o.goal, i, q, said.goal)
        sent_new |= _put(o.key, i, q, said.key)
        sent_new |= _put(o.stop, i, q, said.stop)
        sent_new |= _put(o.req, i, q, s.to_req[q])
        sent_new |= _put(o.rdep, i, q, s.to_rdep[q])
        sent_new |= _put(o.hold, i, q, said.hold)
        sent_new |= _put(o.ack, i, q, said.ack)
        sent_new |= _put(o.ex, i, q, said.ex)
        sent_new |= _put(o.blk, i, q, said.blk)
    return sent_new


@njit(cache=True)
def remember(i, kept, before, after):
    """Keep the cell's new state words (``kept``, a :class:`CellState` of numbers) in row i of ``after``; whether
    they differ from row i of ``before`` (read first: it may be ``after``)."""
    changed = False
    for k in range(len(kept)):
        changed |= _put1(after[k], before[k], i, kept[k])
    return changed


@njit(cache=True)
def step_cells(rows, inp, cfg, rules, old, new, out):
    """:meth:`~virtual_vehicle.cells.sorting.Sorter.step` for the cells ``rows``, one at a time: the new
    :class:`Memory` of each row stepped goes to ``new``, its sentence and wheel speeds to ``out``, which may hold the
    very arrays read (a row reads and writes only its own row, each value read before it is written): then only those
    rows change. ``out.unsettled[i]`` and ``out.out_changed[i]`` say whether row i's state and sentence differ from
    what they were."""
    P = inp.present.shape[1]
    s = Scratch(np.empty(P, np.bool_), np.empty(P, np.bool_), np.empty(P, np.bool_), np.empty(P, np.bool_),
                np.empty(P, np.int64), np.empty(P, np.int64), np.empty(P, np.int64), np.empty(P, np.int64),
                np.empty(P, np.int64), np.empty(P, np.int64), np.empty(P, np.int64))
    park_any = False  # over the cells stepped
    for i in rows:
        park_any = park_any or cfg.park[i]
    h, cell, reach, gap = new.heard, old.cell, rules.reach, rules.gap
    for i in rows:
        changed = hear(i, inp, old, new, cfg.forbid, rules.max_age, s)
        changed |= gradients(i, inp, cfg, old, new, rules.edge_cost, park_any, s)
        nxt = due_next(i, h, cell.nxt, s)
        lit = False
        for k in range(inp.sensors.shape[1]):
            lit = lit or inp.sensors[i, k]
        vid, goal = track(i, lit, h, cell, cfg, rules.tick, s)
        on = lit and vid >= 0 and goal >= 0
        for q in range(P):
            s.same_nb[q] = s.trusted[q] and h.vid[i, q] == vid and on
        goal_exit, seq = split_goal(max(goal, 0))
        turn = due(seq, nxt)
        target = goal_exit if turn else -99  # the exit it heads for now (none while it must wait)
        core = on and inp.sensors[i, 0]  # the cell carries the parcel (centre sensor lit)
        prop_port, prop_d = propose(i, on, core, target, goal_exit if turn else PARK, h, inp, cfg, reach, s)
        back, bdir, backing = back_off(i, on, vid, h, cell, rules.back_ticks, s)
        if backing:
            prop_port, prop_d = bdir, 0
        key, direction = agree(i, on, prop_port, prop_d, h, cell, reach, s)
        # -- traffic: a parked vehicle asks for nothing; front cells ask the cell ahead and stop the vehicle until
        # it holds a free run of ``gap`` cells (or leaves through its exit)
        dp = max(direction, 0)
        own_park = 0 if (on and not turn and core and cfg.park[i]) else 255
        park = _spread(own_park, h.stop[i], 1, on, reach, s)
        parked = on and park <= reach
        front = on and direction >= 0 and not s.same_nb[dp] and not parked
        off_array = front and not inp.connected[i, dp] and cfg.exit[i] == target and dp == cfg.exit_port[i]
        new_hold, hdep, hport, hage = hold(i, lit, inp, cell, rules.max_age, s)
        ack = acknowledge(i, new_hold, hport, h, inp, gap, s)
        go_front = off_array or (s.trusted[dp] and h.hold[i, dp] == vid and (h.ack[i, dp] & 255) >= gap)
        own_stop = 0 if (front and not go_front and (core or inp.connected[i, dp])) else 255
        stop = _spread(0 if own_park == 0 else own_stop, h.stop[i], 0, on, reach, s)
        moving = on and direction >= 0 and stop > reach
        # -- wheel command, the number due (raised by the exit cell that lets a sequenced parcel out), sentence
        out.wheels[i, 0] = out.wheels[i, 1] = 0.0
        if moving:
            axis, sign = drive(dp)
            out.wheels[i, axis] = sign * rules.speed
        if off_array and go_front and seq >= 0:
            nxt = max(nxt, seq + 1)
        requests(i, front, dp, vid, new_hold, hdep, hport, inp, gap, s)
        said = Said(gradient_word(i, on, parked, h, new, reach, s), nxt, vid if on else NONE, goal if on else NONE,
                    min(key, 2**31 - 1), min(stop, 255) + (min(park, 255) << 8), vid if (lit and on) else new_hold,
                    min(ack, 255) + ((hport + 1) << 8), ENTRY if cfg.entry[i] else cfg.exit[i], closed_word(s))
        out.out_changed[i] = say(i, said, out, s)
        kept = CellState(vid, goal, direction if (moving or direction >= 0) else NONE, key, stop, new_hold, hdep, hport,
                         hage, ack, nxt, park, back, bdir)
        out.unsettled[i] = changed | remember(i, kept, cell, new.cell)
