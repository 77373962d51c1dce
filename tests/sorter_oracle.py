"""The sorter's rules in array operations: an oracle for the compiled policy
(:mod:`virtual_vehicle.cells.sorting.policy`), which the tests step side by side with it on random states and in
whole runs. Written independently of the compiled phases, for every cell at once; only the packed word format
(:func:`~virtual_vehicle.cells.sorting.rules.pack`), the goal encoding and the constants are shared."""

from __future__ import annotations

import functools

import numpy as np

from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import UNREACHABLE, CellInputs
from virtual_vehicle.cells.sorting import Sorter, decode_goal
from virtual_vehicle.cells.sorting.policy import ASK, LOSSY
from virtual_vehicle.cells.sorting.rules import BIG as _BIG
from virtual_vehicle.cells.sorting.rules import ENTRY as _ENTRY
from virtual_vehicle.cells.sorting.policy import LATE as _LATE
from virtual_vehicle.cells.sorting.policy import WEAK as _WEAK
from virtual_vehicle.cells.sorting.policy import YIELD as _YIELD
from virtual_vehicle.cells.sorting.rules import HUGE as _HUGE
from virtual_vehicle.cells.sorting.rules import ID_TICK as _ID_TICK
from virtual_vehicle.cells.sorting.rules import MAX_EXITS, PARK, pack
from virtual_vehicle.cells.sorting.rules import NONE as _NONE


def _across(ufunc, a: np.ndarray) -> np.ndarray:
    """``ufunc`` reduced over axis 1 (a cell's ports or sensors), column by column. Axis 1 must not be empty."""
    return functools.reduce(ufunc, [a[:, q] for q in range(a.shape[1])])


def _weighted_gradient(dist_in, present, is_source, cost, cap: int = UNREACHABLE):
    """Distance-vector step with a per-cell cost (hops): a source is at 0, any other cell at its cost plus the
    smallest distance it trusts from a neighbour, capped (unreachable)."""
    heard = np.where(present, dist_in.astype(np.int64), cap)
    best = _across(np.minimum, heard) if heard.shape[1] else np.full(len(is_source), cap)
    return np.where(is_source, 0, np.minimum(best + cost, cap)).astype(np.int64)


def _unpack(words, q: int, bits: int = 8) -> np.ndarray:
    """Field q of words packed by :func:`~virtual_vehicle.cells.sorting.rules.pack`."""
    return ((np.asarray(words, dtype=np.int64) & 0xFFFFFFFF) >> (bits * q)) & ((1 << bits) - 1)


def _key(dist, same, port, hops):
    """Direction proposals ordered by distance to the goal, then keeping the current direction, then port."""
    return ((dist * 2 + (1 - same)) * 8 + port) * 64 + hops


def stepped_by_arrays(program: Sorter) -> Sorter:
    """``program`` made to step by :func:`step_arrays` (and never in place), for whole runs side by side."""
    program.step = functools.partial(step_arrays, program)
    program.step_rows = lambda *args: None
    return program


def step_arrays(sorter: Sorter, state, inputs: CellInputs):
    """:meth:`Sorter.step` in array operations (the numbers those of ``sorter``): the rules of
    :mod:`virtual_vehicle.cells.sorting` stated for every cell at once, which the compiled step is tested against."""
    inbox = inputs.inbox
    n, P = inbox.present.shape
    cfg = inputs.config
    exit_id = np.asarray(cfg.get("exit", np.full(n, _NONE)), dtype=np.int64)
    exit_port = np.asarray(cfg.get("exit_port", np.full(n, _NONE)), dtype=np.int64)
    entry = np.asarray(cfg.get("entry", np.zeros(n, bool)), dtype=bool)
    entry_no = np.asarray(cfg.get("entry_no", np.zeros(n)), dtype=np.int64)
    park_cell = np.asarray(cfg.get("park", np.zeros(n, bool)), dtype=bool)
    forbid = np.asarray(cfg.get("forbid", np.full(n, _NONE)), dtype=np.int64)
    inner = np.asarray(cfg.get("inner", inputs.connected), dtype=bool)
    allowed = np.arange(P)[None, :] != forbid[:, None]  # one-way cells: not against the arrow
    labels = np.full(n, _NONE) if getattr(inputs, "labels", None) is None else np.asarray(inputs.labels)
    rows = np.arange(n)
    ports = np.arange(P)[None, :]
    across = P // 2  # the port straight across is this many ports on
    H = 6 if P == 4 else 5  # bits of a hop count beside a port (square: 6 + 2, hexagonal: 5 + 3)
    none = (1 << H) - 1
    RB, PB = (8, 4) if P == 4 else (7, 3)  # ack: bits of the held run, of the port asked through + 1; dead ports above
    dead_shift = RB + PB
    # -- what the neighbours said (last heard, trusted while fresh)
    # a partial sentence (``inbox.words``) carries some words only: the others stay as last heard
    carried = np.full((n, P), (1 << len(sorter.schema.fields)) - 1) if inbox.words is None else inbox.words
    # and one that carries ``ex`` says every word: those it leaves out are at rest
    full = inbox.present & ((carried >> 10) & 1 == 1)
    rest = {"d": -1, "nxt": 0, "vid": _NONE, "goal": _NONE, "key": _BIG, "stop": 65535, "req": _NONE, "rdep": 0,
            "hold": _NONE, "ack": 0, "ex": 0, "blk": (1 << (H * P)) - 1}
    heard = {k: np.where(inbox.present & ((carried >> w) & 1 == 1), inbox.values[k].astype(np.int64),
                         np.where(full, rest[k], v)) for w, (k, v) in enumerate(state["heard"].items())}
    # an ``ex`` word of at least ASK // 2 asks this cell to say everything again: kept without the ask
    asked_again = inbox.present & ((carried >> 10) & 1 == 1) & (inbox.values["ex"].astype(np.int64) >= ASK // 2)
    heard["ex"] = np.where(asked_again, heard["ex"] - ASK, heard["ex"])
    tick = int(round(inputs.t / sorter.period)) if sorter.period else 0
    heard_at = np.where(inbox.present, tick, state["heard_at"])  # the tick each port last heard a sentence
    trusted = (tick - heard_at <= sorter.trust) & inputs.connected
    # -- routing: one gradient per exit
    # A cell at the edge of the array (a side with no neighbour) costs more, so parcels travel inside it and
    # meet the edge only at their exit.
    # In a sequenced run gradient PARK leads to a parking cell that no parcel covers.
    lit = _across(np.logical_or, np.asarray(inputs.sensors, dtype=bool))
    cost = np.where(_across(np.logical_and, inputs.connected) | (exit_id >= 0), 1, 1 + sorter.edge_cost)
    source = [exit_id == e for e in range(MAX_EXITS)]
    if park_cell.any():  # free while no parcel covers its centre (a parcel parks once it does)
        source[PARK] = park_cell & ~np.asarray(inputs.sensors, dtype=bool)[:, 0]
    heard_d = [_unpack(heard["d"], e) for e in range(MAX_EXITS)]  # (n, P) each: the neighbours' gradients
    dist = np.stack([_weighted_gradient(heard_d[e], trusted & allowed, source[e], cost)
                     for e in range(MAX_EXITS)], axis=1)
    # -- sequencing: the number due next at the exits, the highest any neighbour knows
    nxt = np.maximum(state["nxt"], _across(np.maximum, np.where(trusted, heard["nxt"], 0)) if P else 0)
    # -- tracking
    vid, goal = state["vid"].copy(), state["goal"].copy()
    vid[~lit] = _NONE
    goal[~lit] = _NONE
    # A cell that starts seeing a parcel takes the record of a neighbour whose vehicle is moving into it (else
    # the smallest id around). At the entry one new parcel may get several ids in its first tick: cells next to
    # entry cells settle on the smallest id those hold. Elsewhere a cell never changes vehicle while it sees one.
    toward = (heard["key"] < _BIG) & ((heard["key"] // 64) % 8 == (ports + across) % P)
    has = trusted & (heard["vid"] >= 0)
    score = np.where(has, np.where(toward, 0, _HUGE) + heard["vid"], 2 * _HUGE)
    pick = np.argmin(score, axis=1)
    found = score[rows, pick] < 2 * _HUGE
    best_vid = heard["vid"][rows, pick]
    nb_entry = np.where(has & (heard["ex"] == _ENTRY), heard["vid"], _HUGE)
    entry_min = _across(np.minimum, nb_entry) if P else np.full(n, _HUGE)
    # A cell seeing only an edge of a vehicle keeps it while a neighbour across a lit shared point (config
    # ``sides``: that neighbour sees the same body) carries it; if such neighbours carry only others, it takes the
    # first one's (in port order).
    sensed = np.asarray(inputs.sensors, dtype=bool)
    sides = np.asarray(cfg.get("sides", np.full((n, P), _NONE)), dtype=np.int64)
    on_side = (sides >= 0) & (sides < sensed.shape[1]) \
        & sensed[rows[:, None], np.clip(sides, 0, sensed.shape[1] - 1)] & trusted & (heard["vid"] >= 0)
    others = on_side & (heard["vid"] != vid[:, None])
    switch = lit & (vid >= 0) & ~sensed[:, 0] & ~(on_side & (heard["vid"] == vid[:, None])).any(axis=1) \
        & others.any(axis=1)
    if switch.any():
        first_other = np.argmax(others, axis=1)
        vid = np.where(switch, heard["vid"][rows, first_other], vid)
        goal = np.where(switch, heard["goal"][rows, first_other], goal)
    # A cell seeing only an edge of a vehicle no neighbour carries (a stale word gave it) takes its neighbours' one.
    alone = lit & (vid >= 0) & ~sensed[:, 0] & found \
        & ~(trusted & (heard["vid"] == vid[:, None])).any(axis=1)
    vid[alone] = _NONE
    goal[alone] = _NONE
    adopt = lit & (vid < 0) & found
    vid[adopt] = best_vid[adopt]
    goal[adopt] = heard["goal"][rows, pick][adopt]
    merge = lit & (vid >= 0) & (entry_min < vid)
    if merge.any():
        k = np.argmin(nb_entry, axis=1)
        vid[merge] = entry_min[merge]
        goal[merge] = heard["goal"][rows, k][merge]
    # Next to a dead cell (its own or the neighbour's, the ack word's top bits) a cell takes the smallest id of
    # the neighbours that say its goal: a dead cell can cut one parcel's cells apart into two ids.
    dead = inner & ~inputs.connected
    near_dead = dead.any(axis=1)[:, None] | ((heard["ack"] >> dead_shift) != 0)
    # So does any cell whose neighbour's id was made in the same tick (a parcel put on at once over more cells than
    # its entry's got several ids, and the cells beyond the entry's neighbours kept the one they took first).
    twin = heard["vid"] // _ID_TICK == vid[:, None] // _ID_TICK
    joins = lit[:, None] & (vid[:, None] >= 0) & (near_dead | twin) & trusted & (heard["vid"] >= 0) \
        & (heard["goal"] == goal[:, None])
    vid = np.minimum(vid, _across(np.minimum, np.where(joins, heard["vid"], _HUGE)) if P else vid)
    fresh = lit & (vid < 0) & entry & (labels >= 0)
    # ids order vehicles by age (the tick they were made), which is the priority at a merge
    vid[fresh] = tick * _ID_TICK + entry_no[fresh] % _ID_TICK
    goal[fresh] = labels[fresh]
    # a cell that took the id before it heard the goal (a partial sentence carries a word only when it changed)
    # takes the goal from a neighbour of the same vehicle that says one
    told = trusted & (heard["vid"] == vid[:, None]) & (heard["goal"] >= 0)
    ask = lit & (vid >= 0) & (goal < 0) & told.any(axis=1)
    goal[ask] = heard["goal"][rows, np.argmax(told, axis=1)][ask]
    on = lit & (vid >= 0) & (goal >= 0)
    same_nb = trusted & (heard["vid"] == vid[:, None]) & on[:, None]
    # A sequenced parcel whose number is not yet due heads for a free parking cell instead of its exit.
    goal_exit, seq = decode_goal(np.maximum(goal, 0))
    turn = (seq < 0) | (seq <= nxt)
    target = np.where(turn, goal_exit, -99)  # the exit it heads for now (none while it must wait)
    # -- direction: own proposal, then the smallest heard from the same vehicle (hop-limited)
    g = np.where(turn, goal_exit, PARK)
    nb_d = np.stack(heard_d)[g, rows]  # (n, P): each cell's neighbours on the gradient it follows
    # At its exit a vehicle leaves through the edge once it lies within the exit's band: no cell beside an exit
    # cell (across the way out) is under the same vehicle without being part of that exit. Until then the exit
    # cells that see such a neighbour move the vehicle away from it, into the band. These proposals come first
    # (distance 0: into the band; 1: out), then the gradient's (the chosen neighbour's distance + 3).
    # (on a hexagonal cell the sides 60 degrees off the way out; the vehicle moves away from one across the way out,
    # sideways and on toward the edge)
    side = np.stack([(exit_port + 1) % P, (exit_port - 1) % P], axis=1)
    mine = on & (exit_id == target) & (exit_port >= 0)
    into_band = np.full(n, _NONE)
    for c in range(2):
        sp = side[:, c]
        beside = mine & same_nb[rows, sp] & (heard["ex"][rows, sp] != target)
        into_band = np.where(beside & (into_band < 0), (2 * exit_port - sp) % P, into_band)
    at_exit = mine & (into_band < 0)
    # The vehicle is a body, not a point: a side on which any cell carrying it (centre sensor lit) has no
    # neighbour (the array's edge, a dead cell, a cut link) is closed to the whole vehicle (spread hop-limited,
    # like stopping), except the way out at its exit. Each cell proposes its open side toward the neighbour
    # nearest the goal, ranked by that neighbour's distance: the front's proposals win, and a vehicle that
    # cannot go on sidesteps.
    core = on & np.asarray(inputs.sensors, dtype=bool)[:, 0]  # the cell carries the parcel (centre sensor lit)
    # A dead neighbour (an inner port, silent) closes nothing where a cell of the same vehicle beside this one
    # (across that side) has a live cell on the side: the vehicle's live cells carry it over the dead one. Each
    # cell says its dead ports in the ack word's top bits.
    live_beside = np.zeros((n, P), dtype=bool)
    for q in range(P):
        for b in ((q + 1) % P, (q + P - 1) % P):
            live_beside[:, q] |= same_nb[:, b] & ((heard["ack"][:, b] >> (dead_shift + q)) & 1 == 0)
    passable = dead & live_beside
    # Nor a step that brings a second dead cell under the body in line with one it covers: a carrying cell's side
    # q closes where the live cell ahead on q says a dead neighbour on a side b beside q on which this cell's own
    # dead neighbour lies under the body (its sensor toward it lit).
    side_lit = (sides >= 0) & (sides < sensed.shape[1]) & sensed[rows[:, None], np.clip(sides, 0, sensed.shape[1] - 1)]
    # The dead cell counts as under the body unless the neighbour across from it says (blk's bit 30, sent next to
    # a dead cell) that the body covers its centre.
    core_says = same_nb & ((heard["blk"] >> 30) & 1 != 0)
    in_line = np.zeros((n, P), dtype=bool)
    for q in range(P):
        for b in ((q + 1) % P, (q + P - 1) % P):
            in_line[:, q] |= (inputs.connected[:, q] & trusted[:, q] & side_lit[:, b] & dead[:, b]
                              & ~core_says[:, (b + across) % P]
                              & ((heard["ack"][:, q] >> (dead_shift + b)) & 1 != 0))
    own_block = core[:, None] & ((~inputs.connected & ~passable) | ~allowed | in_line)
    near_blk = dead.any(axis=1) | (trusted & ((heard["ack"] >> dead_shift) != 0)).any(axis=1)
    own_block &= ~(at_exit[:, None] & (np.arange(P)[None, :] == exit_port[:, None]))
    # only cells under a vehicle relay closed sides (the others say 63): computed on those rows alone
    under = np.flatnonzero(on)
    nb_block = np.stack([_unpack(heard["blk"][under], q, H) for q in range(P)], axis=-1)  # (from port, side)
    relayed = np.full((n, P), none, dtype=np.int64)
    relayed[under] = _across(np.minimum, np.where(same_nb[under, :, None] & (nb_block < sorter.reach),
                                                  nb_block + 1, none))
    block = np.where(own_block, 0, relayed)
    block = np.where(on[:, None], block, none)
    open_side = trusted & (block > sorter.reach)
    cand = np.where(open_side, nb_d, _BIG)
    port = np.argmin(cand, axis=1)
    movable = cand[rows, port] < UNREACHABLE
    # ... and, next to a dead cell (its own or a trusted neighbour's), into the band only while that side is open
    # to the whole vehicle (dead cells can close it)
    near = dead.any(axis=1) | (trusted & ((heard["ack"] >> dead_shift) != 0)).any(axis=1)
    into_band = np.where((into_band >= 0) & near & ~open_side[rows, np.maximum(into_band, 0)], _NONE, into_band)
    prop_port = np.where(into_band >= 0, into_band, np.where(at_exit, exit_port, np.where(movable, port, _NONE)))
    prop_d = np.where(into_band >= 0, 2, np.where(at_exit, 3, cand[rows, port] + 4))  # 0, 1: giving way
    # Head on: the cell ahead (in last tick's direction) is held for an older vehicle that asked for it from the
    # far side, or carries an older vehicle heading this way. Hold-based traffic alone would wait forever: the
    # younger vehicle backs off, for long enough to clear the other's gap and one more cell.
    pd = np.maximum(state["dir"], 0)
    ahead_vid = np.where(trusted[rows, pd], heard["hold"][rows, pd], _NONE)
    ahead_from = ((heard["ack"][rows, pd] >> RB) & ((1 << PB) - 1)) - 1
    coming = ((heard["key"][rows, pd] < _BIG) & ((heard["key"][rows, pd] // 64) % 8 == (pd + across) % P)
              & (heard["vid"][rows, pd] == ahead_vid))
    head_on = (on & (state["dir"] >= 0) & (ahead_vid >= 0) & (ahead_vid < vid) & ~same_nb[rows, pd]
               & ((ahead_from == pd) | coming))
    back = np.where(on, np.maximum(state["back"] - 1, 0), 0)
    bdir = np.where(head_on, _away(open_side, pd, P), state["bdir"])
    back = np.where(head_on, sorter.back_ticks, back)
    # Yield: a standing vehicle (not parked) that carries a cell an older vehicle asks for, or any vehicle while
    # its own number is not due, gives way through the first port (lowest) such an asker is on: away from it, or
    # aside when that side is closed.
    # A parked vehicle is late: it gives way too. One due (or carrying no number) gives way only to an asker
    # before it in the order holds go by (below): marked, or not late and older.
    standing = on & ((state["stop"] & none) <= sorter.reach)
    # A vehicle giving way asks marked; one asked that cannot give way (every side but the asker's closed) asks
    # the asker back, marked, and the asker gives way to it.
    marked_req = (heard["rdep"].astype(np.int64) & _YIELD) != 0
    late_req = (heard["rdep"].astype(np.int64) & _LATE) != 0
    req_rank = heard["req"] + np.where(marked_req, 0, np.where(late_req, 2 * _HUGE, _HUGE))
    asking = (trusted & ~same_nb & (heard["req"] >= 0) & (heard["req"] != vid[:, None])
              & ((req_rank < vid[:, None] + _HUGE) | ~turn[:, None]) & standing[:, None])
    # the asker is the first in the order holds go by (marked, then due, then late, oldest first in each);
    # giving way to a younger one (while not due) is marked WEAK in bdir and proposes distance 1, so that an
    # older asker goes first
    order = np.where(asking, req_rank, 4 * _HUGE)
    asked = asking.any(axis=1)
    asker = np.argmin(order, axis=1)
    first = order[rows, asker]
    bdir = np.where(asked, _away(open_side, asker, P), bdir)
    boxed = asked & ~open_side[rows, np.maximum(bdir, 0) % _WEAK]  # (bdir of rows not asked may be WEAK)
    bdir = np.where(asked & (first >= _HUGE) & (heard["req"][rows, asker] > vid), bdir + _WEAK, bdir)
    back = np.where(asked, sorter.back_ticks, back)
    backing = (back > 0) & open_side[rows, np.maximum(bdir, 0) % _WEAK] & (bdir >= 0)
    prop_port = np.where(backing, bdir % _WEAK, prop_port)
    prop_d = np.where(backing, np.where(bdir >= _WEAK, 1, 0), prop_d)
    nb_key = np.where(same_nb, heard["key"], _BIG)
    nb_key = np.where(nb_key % 64 < sorter.reach, nb_key + 1, _BIG)  # one more hop; forget beyond reach
    least = _across(np.minimum, nb_key) if P else np.full(len(rows), _BIG)
    # the direction kept: the cell's own, or for a cell new under the vehicle the one its neighbours' least key says
    current = np.where(state["dir"] >= 0, state["dir"], np.where(least < _BIG, (least // 64) % 8, _NONE))
    own_key = np.where(on & (prop_port >= 0), _key(prop_d, prop_port == current, np.maximum(prop_port, 0), 0), _BIG)
    key = np.minimum(own_key, least) if P else own_key
    key = np.where(on, key, _BIG)
    direction = np.where(key < _BIG, (key // 64) % 8, _NONE)
    yielding = on & (key < _key(2, 1, 0, 0))  # a cell within reach gives way (distance 0, the least proposal)
    # -- traffic: requests ahead, holds, acknowledgements
    ahead_ok_port = (direction >= 0)
    dp = np.maximum(direction, 0)
    ahead_is_mine = same_nb[rows, dp] & ahead_ok_port
    # a waiting parcel parks where a cell that carries it is a parking cell; parked, it asks for nothing and is
    # an obstacle to the others
    # (a vehicle giving way is not parked: it leaves the bay for its back-off)
    own_park = np.where(on & ~turn & core & park_cell & ~yielding, 0, 255)
    park = np.where(yielding, 255, _spread(sorter, own_park, _unpack(heard["stop"], 1), same_nb, on))
    parked = on & (park <= sorter.reach)
    front = on & ahead_ok_port & ~ahead_is_mine & ~parked
    # leaving the array: only out of an exit cell of the goal (anywhere else the edge stops the vehicle)
    off_array = front & ~inputs.connected[rows, dp] & (exit_id == target) & (dp == exit_port)
    # requests that arrived: from a neighbour's front cell or a held cell passing it on
    # a request stands until its sender says otherwise: it sends only what changed. A vehicle giving way (its
    # request marked) gets the cell first, then one due or carrying no number, then a late one (marked LATE), the
    # oldest vehicle asking (smallest id) first within each, always
    req = np.where(trusted & (heard["req"] >= 0), req_rank, 4 * _HUGE)
    choice = np.argmin(req, axis=1)
    new_hold = np.where(req[rows, choice] < 4 * _HUGE, req[rows, choice] % _HUGE, _NONE)
    hport = np.where(new_hold >= 0, choice, _NONE)
    hdep = np.where(new_hold >= 0, heard["rdep"][rows, np.maximum(hport, 0)], 0)
    # On a slow network a request does not arrive every tick: a hold lasts max_age ticks after it was last asked
    # for (on ideal rounds, one tick), unless an older vehicle asks meanwhile.
    def rank(v, dep):
        dep = np.asarray(dep).astype(np.int64)
        return v + np.where(dep & _YIELD, 0, np.where(dep & _LATE, 2 * _HUGE, _HUGE))

    keep = (state["hold"] >= 0) & (state["hage"] < sorter.max_age) & (
        (new_hold < 0) | (rank(state["hold"], state["hdep"]) < rank(new_hold, hdep)))
    new_hold = np.where(keep, state["hold"], new_hold)
    hport = np.where(keep, state["hport"], hport)
    hdep = np.where(keep, state["hdep"], hdep)
    hage = np.where(keep, state["hage"] + 1, 0)
    new_hold = np.where(lit, _NONE, new_hold)  # a cell under a parcel is that parcel's, not anyone's to hold
    hport = np.where(new_hold >= 0, hport, _NONE)
    # acknowledgement: how many held cells run ahead from here (the whole chain when it reaches the edge)
    L = sorter.gap + 1 + sorter.lead  # look-ahead beyond the gap keeps a moving vehicle's chain ahead of it
    fwd = (hport + across) % P
    fp = np.maximum(fwd, 0)
    succ = (new_hold >= 0) & trusted[rows, fp] & (heard["hold"][rows, fp] == new_hold)
    edge = (new_hold >= 0) & ~inputs.connected[rows, fp]
    run_ahead = np.where(succ, heard["ack"][rows, fp] & ((1 << RB) - 1), 0)
    ack = np.where(new_hold >= 0, np.where(edge, L, np.minimum(L, 1 + run_ahead)), 0)
    for k in range(1, P):  # a held cell beside a parked vehicle gives no free run (a cell row is no gap)
        if k == across:
            continue
        sq = (hport + k) % P
        other = heard["vid"][rows, sq]
        parked_there = ((heard["stop"][rows, sq] & 0xFFFFFFFF) >> 8 & 255) <= sorter.reach
        beside = trusted[rows, sq] & (other >= 0) & (other != new_hold) & parked_there
        ack = np.where((new_hold >= 0) & beside, 0, ack)
    # a front cell may go when the cell ahead is held for its vehicle with a full free run, or at the exit edge
    ahead_hold = heard["hold"][rows, dp]
    ahead_ack = heard["ack"][rows, dp] & ((1 << RB) - 1)
    # ... but on a slow link not out of its exit lane's far side, where its front cell stops a vehicle moved
    # sideways into it: for lane_hold ticks, then lets it go for half as long, and again while it is there
    at_end = (sorter.lane_hold > 0) & mine & front & ~yielding & ((dp == side[:, 0]) | (dp == side[:, 1])) & ~(
        trusted[rows, dp] & (heard["ex"][rows, dp] == target))
    lane = np.where(at_end, state["lane"] % (sorter.lane_hold + max(sorter.lane_hold // 2, 1)) + 1, 0)
    lane_end = at_end & (lane <= sorter.lane_hold)
    go_front = (off_array | (trusted[rows, dp] & (ahead_hold == vid) & (ahead_ack >= sorter.gap))) & ~lane_end
    # a cell that only sees the parcel's edge may hang over the array's edge or a dead cell: only cells that
    # carry the parcel, or that have a neighbour ahead to ask, can stop it
    own_stop = np.where(front & ~go_front & (core | inputs.connected[rows, dp]) & ~passable[rows, dp], 0, 255)
    # a stop runs only backward and sideways through the vehicle (from the cell ahead or beside, not from one that
    # heard it from this cell: the stop byte's high two bits name the port it came through), along no loop, so it
    # is gone as soon as its cells say go; a parked vehicle's every cell says stop
    src = np.where((own_park == 0) | parked, 0, own_stop)
    nb_stop = _unpack(heard["stop"], 0)
    hops, came = nb_stop & none, nb_stop >> H
    mine = (hops > 0) & (came == (ports + across) % P)
    behind = (direction[:, None] >= 0) & (ports == (direction[:, None] + across) % P)
    nb = np.where(same_nb & (hops < sorter.reach) & ~mine & ~behind, hops + 1, none)
    via = np.argmin(nb, axis=1)
    best = nb[rows, via]
    stop = np.where(src == 0, 0, np.where(best < none, best + (via << H), 255))
    stop = np.where(on, stop, 255)
    moving = on & (direction >= 0) & ((stop & none) > sorter.reach)
    # -- outputs
    wheels = np.zeros((n, 2))
    # the surface velocity out through each port, in the cell frame: square cells drive one wheel; hexagonal ones
    # any planar velocity, port q at 60 q degrees (cos 60 = 0.5 exactly, sin 60 = sqrt(3) / 2)
    s = np.sqrt(3.0) / 2
    unit = (np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]) if P == 4 else
            np.array([[1.0, 0.0], [0.5, s], [-0.5, s], [-1.0, 0.0], [-0.5, -s], [0.5, -s]]))
    wheels[rows[moving]] = unit[dp[moving]] * sorter.speed
    # the exit cell that lets a sequenced parcel out makes the next number due
    leaving = off_array & go_front & (seq >= 0)
    nxt = np.where(leaving, np.maximum(nxt, seq + 1), nxt)
    send = np.ones(n, dtype=bool)
    # no way through a parked parcel, nor through a gap of one cell beside it (too narrow for a parcel)
    beside_parked = _across(np.logical_or, trusted & (_unpack(heard["stop"], 1) <= sorter.reach)) & ~(on & ~parked)
    said = np.where((parked | beside_parked)[:, None], UNREACHABLE, np.minimum(dist, UNREACHABLE))
    out = Mailbox.broadcast(sorter.schema, send, P, d=pack(said), nxt=nxt, vid=np.where(on, vid, _NONE),
                            goal=np.where(on, goal, _NONE), key=np.minimum(key, 2**31 - 1),
                            stop=np.minimum(stop, 255) + (np.minimum(park, 255) << 8), req=np.full(n, _NONE),
                            rdep=np.zeros(n),
                            hold=np.where(lit & on, vid, new_hold),
                            ack=np.minimum(ack, (1 << RB) - 1) + ((hport + 1) << RB) + (pack(dead, 1) << dead_shift),
                            ex=np.where(entry, _ENTRY, exit_id),
                            blk=pack(np.minimum(block, none), H) + np.where(core & near_blk, 1 << 30, 0))
    # requests: front cells ask the cell ahead (depth 1); held cells pass it on until gap deep
    ask = front & inputs.connected[rows, dp]
    out.values["req"][rows[ask], dp[ask]] = vid[ask]
    # marked YIELD while giving way, LATE while its number is not due
    late = np.where(turn, 0, _LATE)
    out.values["rdep"][rows[ask], dp[ask]] = np.where(yielding[ask], 1 + _YIELD, 1) + late[ask]
    pass_on = (new_hold >= 0) & ((hdep.astype(np.int64) & (_LATE - 1)) < L) & inputs.connected[rows, fp]
    out.values["req"][rows[pass_on], fwd[pass_on]] = new_hold[pass_on]
    out.values["rdep"][rows[pass_on], fwd[pass_on]] = hdep[pass_on] + 1
    back_ask = boxed & inputs.connected[rows, asker]
    out.values["req"][rows[back_ask], asker[back_ask]] = vid[back_ask]
    out.values["rdep"][rows[back_ask], asker[back_ask]] = 1 + _YIELD + late[back_ask]
    # say only what changed on a port since it was last sent there, and everything at the heartbeat
    beat = (tick + entry_no) % sorter.heartbeat_ticks == 0  # staggered by installation number
    each = np.stack([out.values[k].astype(np.int64) != v for k, v in state["said"].items()])  # (words, n, P)
    differs = each.any(axis=0)
    # a new sentence goes out again for ``repeats`` ticks, so that one loss does not cost a heartbeat; partial
    # sentences carry the words that changed in those ticks (the mask kept above the count in ``again``)
    left, window = state["again"] & (LOSSY - 1), state["again"] >> 16
    window = np.where(left > 0, window, 0)
    diff = sum(each[w].astype(np.int64) << w for w in range(len(each)))
    out.present[:] = beat[:, None] | differs | (left > 0)
    # a missed heartbeat of a neighbour still trusted: ask it again (whole sentences only); an ask heard: answer
    ago = tick - heard_at
    asks = inputs.connected & (ago > sorter.heartbeat_ticks + sorter.max_age) & (ago <= sorter.trust) \
        & (not sorter.partial)
    # a port that asked or was asked lost a sentence: marked LOSSY for good, its changes repeated twice as long
    lossy = ((state["again"] & LOSSY) != 0) | asks | asked_again
    count = np.where(differs, np.where(lossy, 2 * sorter.repeats, sorter.repeats), np.maximum(left - 1, 0))
    again = count + (np.where(count > 0, (window | diff) << 16, 0) if sorter.partial else 0) + np.where(lossy, LOSSY, 0)
    if sorter.partial:  # at the heartbeat all words but those at rest, and ``ex``, which says so
        busy = sum((out.values[k].astype(np.int64) != rest[k]).astype(np.int64) << w
                   for w, k in enumerate(state["said"]))
        out.words = np.where(beat[:, None], busy | (1 << 10), diff | window)
    said = {k: np.where(differs, out.values[k].astype(np.int64), v) for k, v in state["said"].items()}
    out.present |= asks | asked_again
    out.values["ex"][asks] += ASK
    new_state = {"dist": dist, "heard": heard, "heard_at": heard_at, "vid": vid, "goal": goal,
                 "dir": np.where(moving | (direction >= 0), direction, _NONE), "key": key, "stop": stop,
                 "hold": new_hold, "hdep": hdep, "hport": hport, "hage": hage, "ack": ack, "nxt": nxt,
                 "park": park, "back": back, "bdir": bdir, "lane": lane, "said": said, "again": again}
    return new_state, out, wheels

def _away(open_side, q, P):
    """Per row, the port a vehicle gives way through from one on port ``q``: across from it if open, else the first
    open one beside, nearest across first; across when none is open."""
    rows = np.arange(len(q))
    back = (q + P // 2) % P
    out, found = back.copy(), np.zeros(len(q), dtype=bool)
    for k in range(P // 2):
        for port in ((back + k) % P, (back + P - k) % P):
            ok = ~found & (port != q) & open_side[rows, port]
            out, found = np.where(ok, port, out), found | ok
    return out


def _spread(sorter: Sorter, own, heard, same_nb, on):
    """Hops to the nearest cell of the same vehicle that said 0 (``own`` 0 here), forgotten beyond ``reach``."""
    nb = np.where(same_nb & (heard < sorter.reach), heard + 1, 255)
    out = np.minimum(own, _across(np.minimum, nb)) if nb.shape[1] else own
    return np.where(on, out, 255)
