"""The sorter's cell policy (the rules of :mod:`virtual_vehicle.cells.sorting`), compiled, the only form of it the
package runs: :func:`step_cells` steps cells one at a time, each through the rules' phases in order. Units: SI (m/s
for wheel speeds).

The arrays travel in a few records (named tuples, which numba compiles field by field): :class:`Words` (one array
per sentence word, in the schema's order), :class:`CellState` (the per-cell state words), :class:`Memory` (what a
cell keeps between ticks), :class:`Config`, :class:`Rules` (the sorter's numbers), :class:`Inputs` and
:class:`Outputs`. The step unpacks them once, before its loop over cells: numba counts a reference each time an array
is reached through a record, which inside the loop made the step several times slower.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from virtual_vehicle.cells.network.programs import UNREACHABLE
from virtual_vehicle.cells.sorting.rules import (BIG, ENTRY, HUGE, ID_TICK, MAX_EXITS, NONE, PARK, ack_bits,
                                                 direction_key, due, heading, heartbeat_due, hop_bits,
                                                 hop_cost, into_lane, left_of, opposite, right_of, split_goal, unpack,
                                                 vehicle_id)

Words = namedtuple("Words", "d nxt vid goal key stop req rdep hold ack ex blk")
"""The sorter's sentence words, one (n, P) array each, in the schema's order."""
CellState = namedtuple("CellState", "vid goal dir key stop hold hdep hport hage ack nxt park back bdir lane")
"""The per-cell state words (n,), int64, in the order the sorter's state holds them after ``dist``, ``heard``,
``age``."""
Memory = namedtuple("Memory", "heard heard_at dist cell said again")
"""What a cell keeps between ticks: words last heard (:class:`Words`, int64), the tick each port last heard one (a
tick, not an age, so that a silent neighbour leaves the state as it is), the exit
gradients' distances (n, MAX_EXITS), the :class:`CellState`, the words it last sent on each port (:class:`Words`,
int64; it sends again only what changed, and everything at its heartbeat) and how many ticks more it repeats a
port's new sentence (n, P), so that one lost sentence does not leave a neighbour a heartbeat behind (with the
:data:`LOSSY` mark of a link that lost one, :data:`AGAIN_BITS`)."""
Config = namedtuple("Config", "exit exit_port entry entry_no park forbid labels inner sides")
"""Per-cell configuration (see :class:`~virtual_vehicle.cells.sorting.Sorter`), the labels read this tick, the
(n, P) ports with a neighbour installed and another cell beyond it (such a port not connected leads to a dead cell
or link inside the array, not off it) and, (n, P), the cell's sensor at the point it shares with the neighbour on
each port (the midpoint of their centres; -1 none): lit, the body over it covers that neighbour too."""
Rules = namedtuple("Rules", "tick max_age edge_cost reach gap back_ticks speed heartbeat trust repeats partial lead "
                   "lane_hold")
"""The tick stepped and the sorter's numbers (hops and ticks; ``speed`` in m/s; ``heartbeat`` the ticks between two
sentences of a cell with nothing new to say, ``trust`` the ticks a neighbour's last sentence is trusted, ``repeats``
the ticks a new sentence is sent again after it changed; ``partial``: a sentence carries only the words that changed,
and those that changed in the last ``repeats`` ticks, all of them at the heartbeat; ``lead``: the cells a vehicle asks
beyond ``gap + 1``, where its run of held cells is told back slower than it drives; ``lane_hold``: the ticks a vehicle
moved sideways into its exit lane stands at the lane's far side, 0 none: see :func:`lane_stop`)."""
Inputs = namedtuple("Inputs", "present arrived sensors connected words")
"""Which sentences arrived (n, P), their words (:class:`Words`), the sensors (n, S), the live links (n, P) and the
bit mask of the words each sentence carries (n, P; bit k: the schema's k-th word)."""
Outputs = namedtuple("Outputs", "present sent wheels unsettled out_changed words ticking")
"""Where the sentences go (a presence mask and :class:`Words`), the (n, 2) wheel speeds (m/s), per row whether
the state and the sentences changed, the bit mask of the words each sentence carries (n, P), and per row whether
its state changed, but in none of the words the rules read back from the cell's own state (``vid``, ``goal``,
``dir``, ``nxt``, ``hold``, ``hdep``, ``hport``, ``hage``, ``back``, ``bdir``, ``stop``, ``park``): only in its
clocks (the tick each port last heard, the repeats left), the words it heard (heard again, a sentence leaves them as
they are), the words it last said (said again, they equal them) or the words every step computes afresh from those
(the gradients, ``key``, ``ack``). Such a row, stepped again on the same inputs, reads what it read and changes
nothing but its clocks (see :func:`tick_cells`). A rule that comes to read one of the latter back from the state moves it
to the former in :func:`step_cells`."""
ALL_WORDS = (1 << len(Words._fields)) - 1
"""The bit mask of every sentence word."""
REST = (-1, 0, NONE, NONE, BIG, 255 + (255 << 8), NONE, 0, NONE, 0, 0, 63 * (1 + 64 + 4096 + 262144))
"""Each word's value on a cell with nothing to say (no vehicle, no hold, no way anywhere: ``d`` all unreachable,
``stop`` and ``park`` none, every side closed; ``ex`` has none): a full sentence leaves the words at rest out.
Square cells; :data:`REST_HEX` on hexagonal ones."""
REST_HEX = REST[:11] + ((1 << 30) - 1,)
""":data:`REST` on hexagonal cells: every side closed is six 5-bit fields at 31 (:func:`~.rules.hop_bits`)."""


@njit(cache=True, inline="always")
def asking(tick, heard_at, heartbeat, max_age, trust, partial):
    """Whether a cell asks a connected neighbour it last heard at tick ``heard_at`` to say everything again: it
    missed a heartbeat (a neighbour is heard at least every ``heartbeat`` ticks, plus ``max_age``), and still trusts
    the neighbour's words. With lossless delivery it never asks; with loss ``p`` a lapse of trust then needs a round
    trip lost on every tick of a whole heartbeat instead of two heartbeats lost (``p**2``). Whole sentences only
    (``partial`` sentences are the wire's, whose handshake retries a lost one)."""
    return not partial and heartbeat + max_age < tick - heard_at <= trust


def rest_words(P: int) -> tuple:
    """:data:`REST` for cells with ``P`` ports."""
    return REST if P == 4 else REST_HEX


WEAK = 8
"""Added to ``bdir`` (a port) when the vehicle gives way to a younger asker (it is not due): such a back-off
proposes distance 1, one to an older asker 0, so that where cells of one vehicle are asked by both, it gives way to
the older."""
YIELD = 128
"""The mark on a request (``rdep``'s high bit, above any depth) of a vehicle giving way: a cell is held for such a
vehicle before any other, so that the cells it gives way into are not held for the older one it makes room for."""
LATE = 64
"""The mark on a request (``rdep``'s bit below :data:`YIELD`, above any depth) of a vehicle that is late (its sequence
number not yet due): a cell is held for such a vehicle after every vehicle that is due or carries no number, so that
the cells on the due one's way are its before any late one's, whose number waits on it."""
CORE_BIT = 30
"""The bit of the ``blk`` word (above the side fields: bits 0-23 on a square cell, 0-29 on a hexagonal one) in which
a cell next to a dead cell (its own or a neighbour's) says that the body it carries covers its centre; never set on
a sound array, whose words stay as they were."""
FULL = 1 << Words._fields.index("ex")
"""A partial sentence that carries ``ex`` (which never changes: said in the first sentence, then only at the
heartbeat) says every word: those it leaves out are at rest (:data:`REST`)."""
ASK = 1 << 14
"""Added to the ``ex`` word of a sentence that asks the neighbour to say everything again (whole sentences only):
the cell missed that neighbour's heartbeat. ``ex`` itself is small (an exit id or ENTRY), so a word of at least
``ASK // 2`` asks; what a cell keeps of ``ex`` is the word without it. The asker sends it every tick until it hears
the neighbour (or stops trusting it); the neighbour answers each ask that arrives with its whole sentence."""
AGAIN_BITS = 16
"""A port's ``again`` memory: the ticks it repeats its sentence (low bits, below :data:`LOSSY`) and, when sentences
are partial, the bit mask of the words to repeat (above these bits)."""
LOSSY = 1 << (AGAIN_BITS - 1)
"""The mark in a port's ``again`` memory (the top bit of its count, above any ``2 * repeats``) of a link that lost a
sentence: the cell asked that neighbour to say everything again, or was asked (:data:`ASK`; whole sentences only, so
never on loss-free rounds). Kept for good; a change on a marked port is repeated for twice ``repeats`` ticks, so that
it is lost only when all of those are, as rarely as on a link that loses half as much."""

@njit(cache=True)
def _first_min(a):
    """The index of the first smallest of ``a`` (numpy's argmin)."""
    best = 0
    for q in range(1, a.shape[0]):
        if a[q] < a[best]:
            best = q
    return best


@njit(cache=True)
def _spread(own, stop_word, field, same, on, reach):
    """Hops to the nearest cell of the same vehicle that said 0 (``own`` 0 here), forgotten beyond ``reach``:
    ``stop_word`` its neighbours' packed ``stop`` words (field ``field``), ``same`` which of them carry its
    vehicle."""
    out = own
    for q in range(same.shape[0]):
        v = unpack(stop_word[q], field, 8)
        nb = v + 1 if same[q] and v < reach else 255
        out = min(out, nb)
    return out if on else 255


@njit(cache=True, inline="always")
def lane_stop(at_end, count, hold):
    """A vehicle's front cell at its exit lane's far side (``at_end``; the vehicle moved sideways into the lane)
    stops it for ``hold`` ticks, lets it go for ``hold // 2`` (at least one), and so on while it is there: the new
    tick count (0 away from the lane's end; ``count`` the last) and whether it stops the vehicle now. The stop keeps a
    body that the cells have not yet agreed to turn out of the lane from running on past its far side (on a slow
    link a withdrawn proposal to move in takes ``reach`` exchanges to be forgotten: ``hold``); the pauses move in a
    body that still reaches out of the lane's near side (a body wider than three pitches covers the far cell's
    sensor before it has left the cell outside the near side: a stop that never let go held it there for good)."""
    if not at_end:
        return 0, False
    count = count % (hold + max(hold // 2, 1)) + 1
    return count, count <= hold


@njit(cache=True)
def _spread_stop(own, stop_word, same, on, reach, direction):
    """The stop byte of a vehicle's cell: hops to the nearest of its cells that said stop (``own`` 0 here; low six
    bits, 63 none) and the port it was heard through (high two bits; on a hexagonal cell five and three bits,
    :func:`~.rules.hop_bits`); 255 when no stop is within ``reach``. A cell
    takes a stop from the cell ahead (port ``direction``) or beside it, not from behind, and not from a neighbour
    that took it from this cell: a stop then runs only backward and sideways through the vehicle, along no loop. A
    cleared stop is not gone at once for all that: the last stop its cell said still arrives along every longer way
    through the vehicle's cells (back a column, sideways, back, sideways the other way: simple paths, no loop), a hop
    later for each hop longer, and a cell whose shorter way has said go takes it from the next longer one, until the
    ways are longer than ``reach`` (traced at the junction's entry: counts up to ``reach``, ~0.08 s on ideal rounds
    and ~0.6 s at 9600 baud; docs/distributed-control.md)."""
    if not on:
        return 255
    if own == 0:
        return 0
    P = same.shape[0]
    H = hop_bits(P)  # the hops' bits; the port above them
    none = (1 << H) - 1
    best = none
    came = P - 1
    for q in range(P):
        v = unpack(stop_word[q], 0, 8)
        hops = v & none
        mine = hops > 0 and (v >> H) == opposite(q, P)  # the neighbour heard it from this cell
        behind = direction >= 0 and q == opposite(direction, P)
        if same[q] and hops < reach and not mine and not behind and hops + 1 < best:
            best = hops + 1
            came = q
    return 255 if best == none else best + (came << H)


@njit(cache=True, inline="always")
def _heard(present, full, rest, word, heard_in, heard_out, i, q):
    """Port q of cell i hears ``word`` if it arrived (in a sentence that carried it), ``rest`` if a full sentence
    left it out, else what it heard last; whether that changed."""
    old = heard_in[i, q]
    heard_out[i, q] = np.int64(word) if present else (np.int64(rest) if full else old)
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


@njit(cache=True, inline="always")
def _say(told, now, beat, i, q):
    """Whether cell i sends the words ``now`` on port q: at its heartbeat (``beat``) or when any differs from what it
    last sent there (``told``: the (last sent, new) :class:`Words` records), which then becomes what it sent; and
    whether it differed, and the bit mask of the words that differed."""
    said_in, said_out = told
    differs = False
    mask = 0
    for w in range(len(now)):
        if said_in[w][i, q] != now[w]:
            differs = True
            mask |= 1 << w
    for w in range(len(now)):
        said_out[w][i, q] = now[w] if differs else said_in[w][i, q]
    return beat or differs, differs, mask


@njit(cache=True, inline="always")
def _rank(vid, dep):
    """The order in which a cell is held for the vehicles asking: those giving way (``dep`` marked
    :data:`YIELD`) first, then those due or carrying no sequence number, then the late ones (``dep`` marked
    :data:`LATE`), the oldest (the smallest ``vid``) first within each."""
    return vid + (0 if dep & YIELD else (2 * HUGE if dep & LATE else HUGE))


@njit(cache=True)
def _away(open_side, q, P):
    """The port a vehicle gives way through from a vehicle on port ``q``: straight away from it (across from q)
    if that side is open (``open_side``), else the first open one beside, nearest straight away first (one-way
    aisles, the edge and parked parcels close the way back: a side step then clears the way); straight away
    when none is open (the vehicle then cannot give way, and stands)."""
    back = opposite(q, P)
    for k in range(P // 2):
        for port in ((back + k) % P, (back + P - k) % P):
            if port != q and open_side[port]:
                return port
    return back


@njit(cache=True)
def step_cells(rows, inp, cfg, rules, old, new, out):
    """:meth:`~virtual_vehicle.cells.sorting.Sorter.step` for the cells ``rows``, one at a time, in the order of the
    rules (see :mod:`virtual_vehicle.cells.sorting`): hear, route (gradients), sequence, track, propose a direction
    (exit band, closed sides, gradient), back off head on, agree on the direction, park, hold cells ahead and
    acknowledge, stop or go, command the wheels, say. The new :class:`Memory` of each row stepped goes to ``new``,
    its sentence and wheel speeds to ``out``, which may hold the very arrays read (a row reads and writes only its
    own row, each value read before it is written): then only those rows change. ``out.unsettled[i]`` and
    ``out.out_changed[i]`` say whether row i's state and sentence differ from what they were, ``out.ticking[i]``
    whether its state changed, but in none of the words the rules read back (:data:`Outputs`)."""
    P = inp.present.shape[1]
    H = hop_bits(P)  # a side's closing hops in the block word, and the hops in the stop byte
    none = (1 << H) - 1
    rest = REST if P == 4 else REST_HEX
    RB, PB = ack_bits(P)  # the ack word: the run of held cells, the port asked through, the ports to a dead cell
    run_max = (1 << RB) - 1  # (a cell's dead ports tell a cell beside it whether the vehicle has a live cell on
    dead_shift = RB + PB  # that side; none on a sound array, where the word is what it always was)
    present, words, sensors, connected, carried = inp  # the records unpacked once, outside the loop over cells: an array
    heard_in, at_in, dist_in, state_in, said_in, again_in = old  # reached through a record inside it costs a reference
    heard_out, at_out, dist_out, state_out, said_out, again_out = new  # count a use
    exit_id, exit_port, entry, entry_no, park_cell, forbid, labels, inner, sides = cfg
    tick, max_age, edge_cost, reach, gap, back_ticks, speed, heartbeat, trust, repeats, partial, lead, lane_hold = rules
    sent_present, sent, wheels, unsettled, out_changed, sent_words, ticking = out
    n_vid, n_goal, n_dir, n_key, n_stop, n_hold, n_hdep, n_hport, n_hage, n_ack, n_nxt, n_park, n_back, n_bdir, \
        n_lane = state_out
    w_d, w_nxt, w_vid, w_goal, w_key, w_stop, w_req, w_rdep, w_hold, w_ack, w_ex, w_blk = words
    i_d, i_nxt, i_vid, i_goal, i_key, i_stop, i_req, i_rdep, i_hold, i_ack, i_ex, i_blk = heard_in
    hd, hnxt, hvid, hgoal, hkey, hstop, hreq, hrdep, hhold, hack, hex_, hblk = heard_out
    s_vid, s_goal, s_dir, s_key, s_stop, s_hold, s_hdep, s_hport, s_hage, s_ack, s_nxt, s_park, s_back, s_bdir, \
        s_lane = state_in
    told = (said_in, said_out)  # what each port last sent, and where the step writes it
    o_d, o_nxt, o_vid, o_goal, o_key, o_stop, o_req, o_rdep, o_hold, o_ack, o_ex, o_blk = sent
    park_any = False  # over the cells stepped, as stepping those rows gathered sees them
    for i in rows:
        park_any = park_any or park_cell[i]
    trusted = np.empty(P, np.bool_)
    asked = np.empty(P, np.bool_)  # the neighbour asked this cell to say everything again (see ASK)
    allowed = np.empty(P, np.bool_)
    same_nb = np.empty(P, np.bool_)
    open_side = np.empty(P, np.bool_)
    score = np.empty(P, np.int64)
    nb_entry = np.empty(P, np.int64)
    cand = np.empty(P, np.int64)
    req = np.empty(P, np.int64)
    block = np.empty(P, np.int64)
    to_req = np.empty(P, np.int64)
    to_rdep = np.empty(P, np.int64)
    passable = np.empty(P, np.bool_)
    for i in rows:
        # -- hear: what the neighbours said (last heard, trusted while fresh)
        changed = False
        clocks = False  # the tick a port last heard and the repeats left changed (see tick_cells)
        for q in range(P):
            p = present[i, q]
            c = carried[i, q] if p else 0  # the words this port's sentence carried (a partial sentence: some)
            full = c & FULL != 0
            changed |= _heard(c & 1 != 0, full, rest[0], w_d[i, q], i_d, hd, i, q)
            changed |= _heard(c >> 1 & 1 != 0, full, rest[1], w_nxt[i, q], i_nxt, hnxt, i, q)
            changed |= _heard(c >> 2 & 1 != 0, full, rest[2], w_vid[i, q], i_vid, hvid, i, q)
            changed |= _heard(c >> 3 & 1 != 0, full, rest[3], w_goal[i, q], i_goal, hgoal, i, q)
            changed |= _heard(c >> 4 & 1 != 0, full, rest[4], w_key[i, q], i_key, hkey, i, q)
            changed |= _heard(c >> 5 & 1 != 0, full, rest[5], w_stop[i, q], i_stop, hstop, i, q)
            changed |= _heard(c >> 6 & 1 != 0, full, rest[6], w_req[i, q], i_req, hreq, i, q)
            changed |= _heard(c >> 7 & 1 != 0, full, rest[7], w_rdep[i, q], i_rdep, hrdep, i, q)
            changed |= _heard(c >> 8 & 1 != 0, full, rest[8], w_hold[i, q], i_hold, hhold, i, q)
            changed |= _heard(c >> 9 & 1 != 0, full, rest[9], w_ack[i, q], i_ack, hack, i, q)
            asked[q] = c >> 10 & 1 != 0 and w_ex[i, q] >= ASK // 2
            changed |= _heard(c >> 10 & 1 != 0, full, rest[10], w_ex[i, q] - ASK if asked[q] else w_ex[i, q], i_ex,
                              hex_, i, q)
            changed |= _heard(c >> 11 & 1 != 0, full, rest[11], w_blk[i, q], i_blk, hblk, i, q)
            old = at_in[i, q]
            at_out[i, q] = tick if p else old
            clocks |= at_out[i, q] != old
            trusted[q] = (tick - at_out[i, q] <= trust) and connected[i, q]
            allowed[q] = q != forbid[i]
        # -- routing: one gradient per exit
        lit = False
        for s in range(sensors.shape[1]):
            lit = lit or sensors[i, s]
        linked = True
        for q in range(P):
            linked = linked and connected[i, q]
        cost = hop_cost(linked, exit_id[i], edge_cost)
        for e in range(MAX_EXITS):
            source = exit_id[i] == e
            if e == PARK and park_any:
                source = park_cell[i] and not sensors[i, 0]
            best = UNREACHABLE
            for q in range(P):
                best = min(best, unpack(hd[i, q], e, 8) if (trusted[q] and allowed[q]) else UNREACHABLE)
            old = dist_in[i, e]
            dist_out[i, e] = 0 if source else min(best + cost, UNREACHABLE)
            changed |= dist_out[i, e] != old
        # -- sequencing
        most = hnxt[i, 0] if trusted[0] else 0
        for q in range(1, P):
            most = max(most, hnxt[i, q] if trusted[q] else 0)
        nxt = max(s_nxt[i], most)
        # -- tracking
        vid, goal = s_vid[i], s_goal[i]
        if not lit:
            vid, goal = NONE, NONE
        for q in range(P):
            toward = (hkey[i, q] < BIG) and ((hkey[i, q] // 64) % 8 == opposite(q, P))
            has = trusted[q] and hvid[i, q] >= 0
            score[q] = ((0 if toward else HUGE) + hvid[i, q]) if has else 2 * HUGE
            nb_entry[q] = hvid[i, q] if (has and hex_[i, q] == ENTRY) else HUGE
        pick = _first_min(score)
        found = score[pick] < 2 * HUGE
        best_vid = hvid[i, pick]
        entry_min = nb_entry[0]
        for q in range(1, P):
            entry_min = min(entry_min, nb_entry[q])
        # a cell that sees only an edge of a vehicle (its centre uncovered) keeps it while a neighbour on a side it sees
        # covered (``sides``: the point the two share lies under the body, so that neighbour sees the same body)
        # carries it; where such neighbours carry only other vehicles it takes the first one's. Two such cells that
        # kept a gone vehicle's id said it to each other, which the rule below never clears (stress floor 140: under
        # the due parcel's edge, the parcel waiting on them and the gone one, late, waiting on the due number)
        if lit and vid >= 0 and not sensors[i, 0]:
            kept = False
            other = NONE
            for q in range(P):
                sn = sides[i, q]
                if 0 <= sn < sensors.shape[1] and sensors[i, sn] and trusted[q] and hvid[i, q] >= 0:
                    kept = kept or hvid[i, q] == vid
                    if hvid[i, q] != vid and other < 0:
                        other = q
            if not kept and other >= 0:
                vid, goal = hvid[i, other], hgoal[i, other]
        # a cell that sees only an edge (its centre uncovered) of a vehicle no neighbour carries holds a parcel that
        # has gone (seen under sentence loss at the entry, where the next parcel arrives at once), and the edge is
        # another's, which a neighbour carries; keeping the gone one's older id stood the new parcel behind it for
        # ever, since it waits on older vehicles. It takes its neighbours' vehicle as a cell that starts seeing one
        alone = lit and vid >= 0 and not sensors[i, 0] and found
        for q in range(P):
            alone = alone and not (trusted[q] and hvid[i, q] == vid)
        if alone:
            vid, goal = NONE, NONE
        if lit and vid < 0 and found:
            vid = best_vid
            goal = hgoal[i, pick]
        if lit and vid >= 0 and entry_min < vid:
            k = _first_min(nb_entry)
            vid = entry_min
            goal = hgoal[i, k]
        # where a dead cell cut a parcel's cells apart (at the entry, where they settle on one id, or under it) the
        # parcel can carry two ids, whose cells then pull it two ways: next to a dead cell (this one's or the
        # neighbour's), a cell takes the smaller id of a neighbour that says the same goal. So does any cell whose
        # neighbour's id was made in the same tick (the tick is the id's high part): a parcel put on at once over
        # more cells than its entry's (a longer parcel) got an id from each entry cell, and the cells beyond the
        # entry's neighbours kept the one they took first, so that it stood for good under two or three ids; the
        # loader's clearance keeps two parcels put on in one tick apart
        dead_mask = 0
        for q in range(P):
            dead_mask |= (1 << q) if (inner[i, q] and not connected[i, q]) else 0
        born = vid // ID_TICK
        for q in range(P):
            near_dead = dead_mask != 0 or (hack[i, q] >> dead_shift) != 0
            twin = hvid[i, q] // ID_TICK == born
            if lit and vid >= 0 and (near_dead or twin) and trusted[q] and 0 <= hvid[i, q] < vid and \
                    hgoal[i, q] == goal:
                vid = hvid[i, q]
        if lit and vid < 0 and entry[i] and labels[i] >= 0:
            vid = vehicle_id(tick, entry_no[i])
            goal = labels[i]
        # a cell that took the id before it heard the goal (a partial sentence carries a word only when it
        # changed) takes the goal from a neighbour of the same vehicle that says one
        if lit and vid >= 0 and goal < 0:
            for q in range(P):
                if trusted[q] and hvid[i, q] == vid and hgoal[i, q] >= 0:
                    goal = hgoal[i, q]
                    break
        on = lit and vid >= 0 and goal >= 0
        for q in range(P):
            same_nb[q] = trusted[q] and hvid[i, q] == vid and on
        g0 = max(goal, 0)
        goal_exit, seq = split_goal(g0)
        turn = due(seq, nxt)
        target = goal_exit if turn else -99
        # -- direction
        g = goal_exit if turn else PARK
        ep = exit_port[i]
        mine = on and exit_id[i] == target and ep >= 0
        into_band = NONE
        for c in range(2):
            sp = left_of(ep, P) if c == 0 else right_of(ep, P)
            beside = mine and same_nb[sp] and hex_[i, sp] != target
            if beside and into_band < 0:
                into_band = into_lane(sp, ep, P)
        at_exit = mine and into_band < 0
        core = on and sensors[i, 0]
        for q in range(P):
            # a dead neighbour (inner, silent) does not close a side when a cell of the vehicle beside this one has
            # a live cell on that side: the live cells under the vehicle carry it over the dead one, whose held
            # wheels only brake it, where closing the side makes a parcel wider than the gaps between dead cells
            # shuffle in front of them for ever
            dead_q = inner[i, q] and not connected[i, q]
            live_beside = False
            for b in (left_of(q, P), right_of(q, P)):
                live_beside = live_beside or (same_nb[b] and (hack[i, b] >> (dead_shift + q)) & 1 == 0)
            passable[q] = dead_q and live_beside
        for q in range(P):
            # nor a step through q that brings a second dead cell under the body in line with one it covers: the
            # cell ahead on q, live, says a dead neighbour on a side b beside q where this cell's own dead neighbour
            # lies under the body (its sensor toward it lit). A dead cell's held wheels brake with up to mu_static N
            # at rest and mu N sliding while the live ones drive with mu N or hold with up to mu_static N, so a
            # parcel on four cells two of which are dead stands for good. Never on a sound array (no dead cell)
            # The sensor toward the dead cell is lit once the body passes the point midway to it, short of its
            # centre; the body surely covers that centre when the neighbour across from it carries no part of the
            # body at its own centre (it says so, next to a dead cell, in ``blk``'s bit CORE_BIT): a parcel is at
            # least two pitches wide, and it does not reach past this cell's far side by half a pitch
            in_line = False
            if core and connected[i, q] and trusted[q]:
                for b in (left_of(q, P), right_of(q, P)):
                    sn = sides[i, b]
                    under = 0 <= sn < sensors.shape[1] and sensors[i, sn]
                    far = opposite(b, P)
                    under = under and not (same_nb[far] and (hblk[i, far] >> CORE_BIT) & 1 != 0)
                    in_line = in_line or (under and (dead_mask >> b) & 1 != 0
                                          and (hack[i, q] >> (dead_shift + b)) & 1 != 0)
            own_block = core and ((not connected[i, q] and not passable[q]) or not allowed[q] or in_line)
            own_block = own_block and not (at_exit and q == ep)
            relayed = none
            if on:
                for p in range(P):
                    b = unpack(hblk[i, p], q, H)
                    relayed = min(relayed, b + 1 if (same_nb[p] and b < reach) else none)
            block[q] = 0 if own_block else relayed
            if not on:
                block[q] = none
            open_side[q] = trusted[q] and block[q] > reach
            cand[q] = unpack(hd[i, q], g, 8) if open_side[q] else BIG
        port = _first_min(cand)
        movable = cand[port] < UNREACHABLE
        # next to a dead cell (its own or a neighbour's), a cell at the lane's side pulls the vehicle into the lane
        # only while that side is open to the whole vehicle: where dead cells close it (a cell of the body faces
        # one with no live cell beside), the pull and that cell's stop held the vehicle still for ever; the
        # gradient then moves it along first, until the side opens. Only there, so that a sound array runs as
        # it always did
        near_dead = dead_mask != 0
        for q in range(P):
            near_dead = near_dead or (trusted[q] and (hack[i, q] >> dead_shift) != 0)
        if into_band >= 0 and near_dead and not open_side[into_band]:
            into_band = NONE
        if into_band >= 0:  # distances 2, 3 and up: 0 and 1 are a vehicle giving way's (see ``yielding``)
            prop_port, prop_d = into_band, 2
        elif at_exit:
            prop_port, prop_d = ep, 3
        else:
            prop_port, prop_d = (port if movable else NONE), cand[port] + 4
        # head on: back off
        sdir = s_dir[i]
        pd = max(sdir, 0)
        ahead_vid = hhold[i, pd] if trusted[pd] else NONE
        ahead_from = ((hack[i, pd] >> RB) & ((1 << PB) - 1)) - 1
        coming = ((hkey[i, pd] < BIG) and ((hkey[i, pd] // 64) % 8 == opposite(pd, P))
                  and hvid[i, pd] == ahead_vid)
        head_on = (on and sdir >= 0 and ahead_vid >= 0 and ahead_vid < vid and not same_nb[pd]
                   and (ahead_from == pd or coming))
        back = max(s_back[i] - 1, 0) if on else 0
        bdir = _away(open_side, pd, P) if head_on else s_bdir[i]
        if head_on:
            back = back_ticks
        # yield: a standing vehicle that carries a cell an older vehicle asks for (or any vehicle, while its own
        # number is not due, or a vehicle giving way: its request marked YIELD) gives way, away from the asker or
        # aside (the package notes: every cycle of holds has a member waiting on a cell a younger one carries, and
        # that one gives way). One that cannot (every side but the asker's closed) asks back, marked: the asker
        # then gives way to it
        # the asker it gives way to is the first in the order holds go by (one giving way, then the oldest): a
        # late vehicle asked by the due one and by a younger late one gave way to whichever its cells' proposals
        # put first, and went into the due one's holds. Giving way to a younger one (while not due) proposes
        # distance 1 (``bdir`` marked WEAK), so that the vehicle gives way to an older asker first
        asker = NONE
        first = 4 * HUGE
        # a parked vehicle gives way too, as the late one it is (floors 59 and 96: parked in a bay on the due one's
        # only way, it and the due one waited on each other for ever). A vehicle due (or carrying no number) gives
        # way to an asker that comes before it in the order holds go by (see _rank), so not to a late one
        standing = on and (s_stop[i] & none) <= reach
        for q in range(P):
            r = hreq[i, q] if (trusted[q] and not same_nb[q]) else NONE
            if standing and r >= 0 and r != vid and (not turn or _rank(r, hrdep[i, q]) < vid + HUGE) \
                    and _rank(r, hrdep[i, q]) < first:
                asker, first = q, _rank(r, hrdep[i, q])
        boxed = False
        if asker >= 0:
            bdir = _away(open_side, asker, P)
            back = back_ticks
            boxed = not open_side[bdir]
            if first >= HUGE and hreq[i, asker] > vid:
                bdir += WEAK
        backing = back > 0 and bdir >= 0 and open_side[bdir % WEAK]
        if backing:
            prop_port, prop_d = bdir % WEAK, (1 if bdir >= WEAK else 0)
        least = 0
        for q in range(P):  # one more hop; forget beyond reach
            nk = hkey[i, q] if same_nb[q] else BIG
            nk = nk + 1 if nk % 64 < reach else BIG
            least = nk if q == 0 else min(least, nk)
        # the direction a proposal keeps: the cell's own, or, for a cell that has just come under the vehicle and has
        # none yet, the vehicle's (its neighbours' least key): else each step of a vehicle onto a new front cell went
        # through all its cells twice, as a change of direction and a tick later as keeping it
        current = sdir if sdir >= 0 else ((least // 64) % 8 if least < BIG else NONE)
        own_key = BIG
        if on and prop_port >= 0:
            own_key = direction_key(prop_d, 1 if prop_port == current else 0, max(prop_port, 0), 0)
        key = min(own_key, least)
        if not on:
            key = BIG
        direction = (key // 64) % 8 if key < BIG else NONE
        # the vehicle gives way (a cell of it within reach backs off: its proposal, distance 0, is the least)
        yielding = on and key < direction_key(2, 1, 0, 0)
        if direction >= P:  # a key word from no sorter (the oracle fails here too)
            raise IndexError("a direction key names a port the cell does not have")
        # -- traffic
        ahead_ok_port = direction >= 0
        dp = max(direction, 0)
        ahead_is_mine = same_nb[dp] and ahead_ok_port
        # a vehicle giving way is not parked (it leaves the bay for the back-off, and comes back to a free one)
        own_park = 0 if (on and not turn and core and park_cell[i] and not yielding) else 255
        park = 255 if yielding else _spread(own_park, hstop[i], 1, same_nb, on, reach)
        parked = on and park <= reach
        front = on and ahead_ok_port and not ahead_is_mine and not parked
        off_array = front and not connected[i, dp] and exit_id[i] == target and dp == ep
        # a request stands until its sender says otherwise (it sends only what changed); a vehicle giving way
        # (its request marked YIELD) gets the cell before any other, then the due and unsequenced, then the late
        # (marked LATE), the oldest asking first within each (see _rank)
        for q in range(P):
            req[q] = _rank(hreq[i, q], hrdep[i, q]) if (trusted[q] and hreq[i, q] >= 0) else 4 * HUGE
        choice = _first_min(req)
        new_hold = req[choice] % HUGE if req[choice] < 4 * HUGE else NONE
        hport = choice if new_hold >= 0 else NONE
        hdep = hrdep[i, max(hport, 0)] if new_hold >= 0 else 0
        keep = s_hold[i] >= 0 and s_hage[i] < max_age and (
            new_hold < 0 or _rank(s_hold[i], s_hdep[i]) < _rank(new_hold, hdep))
        if keep:
            new_hold, hport, hdep = s_hold[i], s_hport[i], s_hdep[i]
        hage = s_hage[i] + 1 if keep else 0
        if lit:
            new_hold = NONE
        if new_hold < 0:
            hport = NONE
        L = gap + 1 + lead  # the cells asked (it moves on a run of gap: the rest is slack for a slow link)
        fwd = opposite(hport, P)
        fp = max(fwd, 0)
        succ = new_hold >= 0 and trusted[fp] and hhold[i, fp] == new_hold
        edge = new_hold >= 0 and not connected[i, fp]
        run_ahead = hack[i, fp] & run_max if succ else 0
        ack = (L if edge else min(L, 1 + run_ahead)) if new_hold >= 0 else 0
        # a held cell beside a parked vehicle (a side neighbour carries it) gives no free run: a body reaches past
        # the cell centres it covers, so a parcel passing there could brush it (a cell row is no gap). Only a parked
        # one: a vehicle that may still go holds the cells ahead of it (its gap), and a held cell beside an older
        # vehicle that is merely on its way or waiting cost deliveries and prevented no collision in the bundled
        # scenarios or on the stress floor where the rule came from (seed 132). The sides: every port but the
        # hold's and the one across it (two on a square cell, four on a hexagonal one)
        for k in range(1, P):
            sq = (hport + k) % P
            other = hvid[i, sq]
            if k != P // 2 and new_hold >= 0 and trusted[sq] and other >= 0 and other != new_hold and unpack(
                    hstop[i, sq], 1, 8) <= reach:
                ack = 0
        ahead_hold = hhold[i, dp]
        ahead_ack = hack[i, dp] & run_max
        # on a slow link (lane_hold) a vehicle moved sideways into its exit lane stops at the lane's far side: its
        # front cell there stops it, where the cells agree on the turn out only after the body ran on (on ideal
        # rounds the turn reaches them within a tick, and the stop would only cost time); for lane_hold ticks at a
        # time, so that a body still reaching out of the lane's near side is moved in (see lane_stop)
        at_lane_end = lane_hold > 0 and mine and front and not yielding and (dp == left_of(ep, P) or dp == right_of(
            ep, P)) and not (trusted[dp] and hex_[i, dp] == target)
        lane, lane_end = lane_stop(at_lane_end, s_lane[i], lane_hold)
        go_front = (off_array or (trusted[dp] and ahead_hold == vid and ahead_ack >= gap)) and not lane_end
        own_stop = 0 if (front and not go_front and (core or connected[i, dp]) and not passable[dp]) else 255
        stop = _spread_stop(0 if (own_park == 0 or parked) else own_stop, hstop[i], same_nb, on, reach, direction)
        moving = on and direction >= 0 and (stop & none) > reach
        # -- outputs
        wheels[i, 0] = wheels[i, 1] = 0.0
        if moving:
            vx, vy = heading(dp, P)
            wheels[i, 0], wheels[i, 1] = vx * speed, vy * speed
        if off_array and go_front and seq >= 0:
            nxt = max(nxt, seq + 1)
        beside_parked = False
        for q in range(P):
            beside_parked = beside_parked or (trusted[q] and unpack(hstop[i, q], 1, 8) <= reach)
        beside_parked = beside_parked and not (on and not parked)
        word = 0
        for e in range(MAX_EXITS):
            said = UNREACHABLE if (parked or beside_parked) else min(dist_out[i, e], UNREACHABLE)
            word += said << (8 * e)
        if word >= 1 << 31:
            word -= 1 << 32
        blk = 0
        for q in range(P):
            blk += min(block[q], none) << (H * q)
        near_any = dead_mask != 0  # next to a dead cell (its own or a neighbour's): say whether the body is over
        for q in range(P):  # this cell's centre (above the side fields; never on a sound array)
            near_any = near_any or (trusted[q] and (hack[i, q] >> dead_shift) != 0)
        if core and near_any:
            blk += 1 << CORE_BIT
        if blk >= 1 << 31:
            blk -= 1 << 32
        for q in range(P):  # requests: front cells ask the cell ahead, held cells pass it on until gap deep
            to_req[q], to_rdep[q] = NONE, 0
        late = 0 if turn else LATE  # a late vehicle's requests go after the due ones' (see _rank)
        if front and connected[i, dp]:
            to_req[dp], to_rdep[dp] = vid, 1 + (YIELD if yielding else 0) + late
        if new_hold >= 0 and (hdep & (LATE - 1)) < L and connected[i, fp]:
            to_req[fwd], to_rdep[fwd] = new_hold, hdep + 1  # (the marks passed on with it)
        if boxed and connected[i, asker]:
            to_req[asker], to_rdep[asker] = vid, 1 + YIELD + late
        # say: on a port only what changed since it last sent there (and again for ``repeats`` ticks), and
        # everything at its heartbeat, which repairs a lost sentence; the words are written whether sent or not
        beat = heartbeat_due(tick, entry_no[i], heartbeat)
        sent_new = False
        for q in range(P):
            now = (np.int64(word), np.int64(nxt), np.int64(vid if on else NONE), np.int64(goal if on else NONE),
                   np.int64(min(key, 2**31 - 1)), np.int64(min(stop, 255) + (min(park, 255) << 8)),
                   np.int64(to_req[q]), np.int64(to_rdep[q]), np.int64(vid if (lit and on) else new_hold),
                   np.int64(min(ack, run_max) + ((hport + 1) << RB) + (dead_mask << dead_shift)),
                   np.int64(ENTRY if entry[i] else exit_id[i]), np.int64(blk))
            send, differs, diff = _say(told, now, beat, i, q)
            # a missed heartbeat: ask again rather than wait for the next one; an ask heard: answer in whole
            ask = connected[i, q] and asking(tick, at_out[i, q], heartbeat, max_age, trust, partial)
            send = send or ask or asked[q]
            old_again = again_in[i, q]
            left = old_again & (LOSSY - 1)  # ticks still to repeat, and (partial) which words
            window = old_again >> AGAIN_BITS if left > 0 else 0
            # a link that lost a sentence (an ask sent or heard on it): its changes repeated twice as long
            lossy = (old_again & LOSSY) != 0 or ask or asked[q]
            count = (2 * repeats if lossy else repeats) if differs else max(left - 1, 0)
            again_out[i, q] = count + (((window | diff) << AGAIN_BITS) if (partial and count > 0) else 0) + (
                LOSSY if lossy else 0)
            send = send or left > 0
            carry = ALL_WORDS if not partial else (diff | window)
            if partial and beat:  # everything, but the words at rest go without saying
                carry = FULL
                for w in range(len(now)):
                    carry |= (1 << w) if now[w] != rest[w] else 0
            changed |= differs
            clocks |= again_out[i, q] != old_again
            sent_new |= sent_present[i, q] != send
            sent_present[i, q] = send
            sent_new |= _put(sent_words, i, q, carry) and partial  # (a scratch array when not partial)
            sent_new |= _put(o_d, i, q, now[0])
            sent_new |= _put(o_nxt, i, q, now[1])
            sent_new |= _put(o_vid, i, q, now[2])
            sent_new |= _put(o_goal, i, q, now[3])
            sent_new |= _put(o_key, i, q, now[4])
            sent_new |= _put(o_stop, i, q, now[5])
            sent_new |= _put(o_req, i, q, now[6])
            sent_new |= _put(o_rdep, i, q, now[7])
            sent_new |= _put(o_hold, i, q, now[8])
            sent_new |= _put(o_ack, i, q, now[9])
            sent_new |= _put(o_ex, i, q, now[10] + ASK if ask else now[10])
            sent_new |= _put(o_blk, i, q, now[11])
        out_changed[i] = sent_new
        # the state words the rules read back (held; stop and park too: giving way reads whether the vehicle stands);
        # the others (key, ack, the gradients) and what the cell heard and said, a step on the same inputs computes
        # again as this one did (see Outputs.ticking)
        held = _put1(n_vid, s_vid, i, vid)
        held |= _put1(n_goal, s_goal, i, goal)
        held |= _put1(n_dir, s_dir, i, direction if (moving or direction >= 0) else NONE)
        changed |= _put1(n_key, s_key, i, key)
        held |= _put1(n_stop, s_stop, i, stop)
        held |= _put1(n_hold, s_hold, i, new_hold)
        held |= _put1(n_hdep, s_hdep, i, hdep)
        held |= _put1(n_hport, s_hport, i, hport)
        held |= _put1(n_hage, s_hage, i, hage)
        changed |= _put1(n_ack, s_ack, i, ack)
        held |= _put1(n_nxt, s_nxt, i, nxt)
        held |= _put1(n_park, s_park, i, park)
        held |= _put1(n_back, s_back, i, back)
        held |= _put1(n_bdir, s_bdir, i, bdir)
        held |= _put1(n_lane, s_lane, i, lane)
        unsettled[i] = changed or held or clocks
        ticking[i] = (changed or clocks) and not held


@njit(cache=True)
def tick_cells(rows, inp, entry_no, tick, heartbeat, trust, partial, old, sent_present, sent_words, unsettled,
               out_changed, ticking, done):
    """What :func:`step_cells` does to the rows ``rows`` whose last step changed none of the state words the rules
    read back (``ticking``, or nothing at all) and whose sensors, links and labels are those of that step, at a tick
    at which no neighbour they trust turns stale (and, with partial sentences, not their heartbeat), when every port
    that hears now hears what the cell already holds from a neighbour it trusted last tick (a port that falls
    silent keeps what it heard): their clocks only, in place, and ``done[i]`` set; a row that hears something new
    is left as it is (``done[i]`` False) to be stepped whole. A heartbeat (of whole sentences) only makes the cell
    send, as computed here.

    Why nothing else changes: every rule reads the neighbours' words (the same: a port that hears, hears what it
    held; a silent one keeps it), whether each is trusted (the same: a port that hears was trusted and stays so; a
    silent one turns stale only at a due tick) and the state words it reads back, which its last step left as it
    found them (``ticking``), so each rule gives what it gave in that step, which is what the state holds; the
    sentence equals what was said, so it does not differ, and the repeats only count down. The tick itself enters only a
    new vehicle's id, made in a step that changes the vehicle word (then the row is not ``ticking``), and the
    heartbeat, computed here as there. ``inp``: the :class:`Inputs` (its sensors and links unused); ``old``: the
    :class:`Memory` (its ``heard_at`` and ``again`` written in place); ``sent_present`` (n, P) bool and
    ``sent_words`` (n, P) int64 (when ``partial``) written in place; ``unsettled``, ``out_changed`` and
    ``ticking`` as :func:`step_cells` writes them."""
    present, words, sensors, connected, carried = inp  # unpacked once, outside the loop (see step_cells)
    heard, heard_at, dist, state, said, again = old
    w_d, w_nxt, w_vid, w_goal, w_key, w_stop, w_req, w_rdep, w_hold, w_ack, w_ex, w_blk = words
    i_d, i_nxt, i_vid, i_goal, i_key, i_stop, i_req, i_rdep, i_hold, i_ack, i_ex, i_blk = heard
    P = present.shape[1]
    rest = REST if P == 4 else REST_HEX
    low = LOSSY - 1
    for i in rows:
        same = True  # what each port that hears now leaves heard as it is, from a neighbour trusted last tick
        for q in range(P):
            if present[i, q]:
                c = carried[i, q]
                full = c & FULL != 0
                same = same and tick - 1 - heard_at[i, q] <= trust
                same = same and _kept(c & 1 != 0, full, rest[0], w_d[i, q], i_d[i, q])
                same = same and _kept(c >> 1 & 1 != 0, full, rest[1], w_nxt[i, q], i_nxt[i, q])
                same = same and _kept(c >> 2 & 1 != 0, full, rest[2], w_vid[i, q], i_vid[i, q])
                same = same and _kept(c >> 3 & 1 != 0, full, rest[3], w_goal[i, q], i_goal[i, q])
                same = same and _kept(c >> 4 & 1 != 0, full, rest[4], w_key[i, q], i_key[i, q])
                same = same and _kept(c >> 5 & 1 != 0, full, rest[5], w_stop[i, q], i_stop[i, q])
                same = same and _kept(c >> 6 & 1 != 0, full, rest[6], w_req[i, q], i_req[i, q])
                same = same and _kept(c >> 7 & 1 != 0, full, rest[7], w_rdep[i, q], i_rdep[i, q])
                same = same and _kept(c >> 8 & 1 != 0, full, rest[8], w_hold[i, q], i_hold[i, q])
                same = same and _kept(c >> 9 & 1 != 0, full, rest[9], w_ack[i, q], i_ack[i, q])
                same = same and _kept(c >> 10 & 1 != 0, full, rest[10], w_ex[i, q], i_ex[i, q])
                same = same and _kept(c >> 11 & 1 != 0, full, rest[11], w_blk[i, q], i_blk[i, q])
        done[i] = same
        if not same:
            continue
        beat = heartbeat_due(tick, entry_no[i], heartbeat)
        clocks = False
        sent_new = False
        for q in range(P):
            if present[i, q]:  # as step_cells' hear phase
                clocks |= heard_at[i, q] != tick
                heard_at[i, q] = tick
            old_again = again[i, q]  # as step_cells' say phase, with a sentence that does not differ
            left = old_again & low
            window = old_again >> AGAIN_BITS if left > 0 else 0
            count = max(left - 1, 0)
            again[i, q] = count + ((window << AGAIN_BITS) if (partial and count > 0) else 0) + (old_again & LOSSY)
            clocks |= again[i, q] != old_again
            send = beat or left > 0
            sent_new |= sent_present[i, q] != send
            sent_present[i, q] = send
            if partial:
                sent_new |= sent_words[i, q] != window
                sent_words[i, q] = window
        unsettled[i] = clocks
        ticking[i] = clocks
        out_changed[i] = sent_new


@njit(cache=True, inline="always")
def _kept(arrived, full, rest, word, held):
    """Whether a port hearing ``word`` (if it ``arrived``; ``rest`` if a full sentence left it out) leaves what it
    ``held`` as it is (:func:`_heard`, compared without writing)."""
    return (np.int64(word) if arrived else (np.int64(rest) if full else held)) == held
