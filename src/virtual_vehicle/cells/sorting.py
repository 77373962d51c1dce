"""The Virtual Vehicle as a distributed cell program: parcels sorted to exits by local decisions only (paper
Section 1 and Figure 2: each parcel moves as if it rode its own vehicle, made of whichever cells are under it).

Units: SI (m/s for wheel speeds). Every rule below reads only the cell's own sensors, state and configuration and
what its neighbours said last tick (:mod:`virtual_vehicle.cells.network.programs` contract, checked by
:func:`~virtual_vehicle.cells.network.programs.check_program`).

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
  vehicle like its direction. Parcels therefore keep ``gap`` free cells between them and do not collide. Two
  vehicles that meet head on would each hold what the other needs; a front cell that sees the cell ahead held for
  an older vehicle that asked from the far side (the held cell tells through which port it was asked), or carrying
  an older vehicle coming this way, makes its vehicle back off for as long as ``gap + 1`` cells take. A hold
  lasts ``max_age`` ticks after the last request that renewed it (one tick on ideal rounds), so on a network that
  delivers a sentence only every few ticks the chain of holds ahead of a vehicle does not fall apart between them.
- *Exits*: a cell of the goal's exit lane drives the vehicle out through the lane's open side once the vehicle lies
  within the lane (no cell beside it, across the way out, is under the vehicle without belonging to the lane);
  until then such cells move the vehicle sideways into the lane. Nowhere else may a vehicle move over the edge: a
  front cell with no neighbour ahead stops it.
- *One-way cells* (config ``forbid``: the port a parcel on the cell may not move toward): gradients are not
  followed against the arrow, and a side against an arrow under any carrying cell is closed to the whole vehicle.
  Aisles drawn one-way cannot have two parcels meet head on (nor can a parcel back off against an arrow).
- *Sequencing* (parcels whose label carries a sequence number, :func:`encode_goal`): the number due next spreads
  through the array as the highest heard (word ``nxt``); the exit cell that lets a sequenced parcel out raises it
  to that parcel's number plus one. A parcel whose number is not yet due follows gradient :data:`PARK` to a parking
  cell (config ``park``) whose centre no parcel covers, and parks once a cell carrying it is one: it stops, asks
  for no cells, and it and the cells beside it tell their neighbours there is no way through (so others route
  around it). When its number is due it heads for its exit. Parcels therefore leave in sequence, as long as there
  are enough parking cells for those that arrive early.
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

from virtual_vehicle.cells.network.messages import DTYPE, Mailbox, Schema
from virtual_vehicle.cells.network.programs import UNREACHABLE, CellInputs
from virtual_vehicle.cells.network.sentence import WordType

MAX_EXITS = 4
PARK = MAX_EXITS - 1
"""In a sequenced run (parcels with sequence numbers), gradient PARK leads to a free parking cell, not to exit 3."""
_NONE = -1
_BIG = 1 << 20  # above any direction key
_HUGE = 1 << 40  # above any vehicle id
_ENTRY = -2  # the "ex" word of an entry cell


def _across(ufunc, a: np.ndarray) -> np.ndarray:
    """``ufunc`` reduced over axis 1 (a cell's ports or sensors), column by column: numpy's reductions along a short
    axis cost about ten times as much. Axis 1 must not be empty."""
    return functools.reduce(ufunc, [a[:, q] for q in range(a.shape[1])])


def _weighted_gradient(dist_in, present, is_source, cost, cap: int = UNREACHABLE):
    """Distance-vector step with a per-cell cost (hops): a source is at 0, any other cell at its cost plus the
    smallest distance it trusts from a neighbour, capped (unreachable)."""
    heard = np.where(present, dist_in.astype(np.int64), cap)
    best = _across(np.minimum, heard) if heard.shape[1] else np.full(len(is_source), cap)
    return np.where(is_source, 0, np.minimum(best + cost, cap)).astype(np.int64)


def decode_goal(goal):
    """(exit, sequence number) of goal words: ``exit + 4 (sequence + 1)``; sequence -1 for an unsequenced parcel."""
    goal = np.asarray(goal, dtype=np.int64)
    return goal % 4, goal // 4 - 1


def encode_goal(exit: int, sequence: int | None) -> int:
    """The label a reader at the entry sees: the exit, and the sequence number when the parcel has one."""
    return int(exit) + (0 if sequence is None else 4 * (int(sequence) + 1))


def _pack(values, bits: int = 8) -> np.ndarray:
    """Small non-negative integers (n, k), each below 2**bits, packed into one signed 32-bit word per row."""
    v = np.asarray(values, dtype=np.int64)
    word = sum(v[:, q] << (bits * q) for q in range(v.shape[1]))
    return np.where(word >= 1 << 31, word - (1 << 32), word)


def _unpack(words, q: int, bits: int = 8) -> np.ndarray:
    """Field q of words packed by :func:`_pack`."""
    return ((np.asarray(words, dtype=np.int64) & 0xFFFFFFFF) >> (bits * q)) & ((1 << bits) - 1)


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
        pitch: the cell pitch (m), known to every cell: a vehicle that meets an older one head on backs off for the
            time it takes to travel ``gap + 1`` pitches.
        compiled: step in compiled code (the default), or in array operations (the same numbers, slower; the
            readable statement of the rules).

    Sensor 0 of every cell must be its centre (the default layout): a cell whose centre is covered carries the
    parcel; the others only see its edge.

    Config (per cell): ``exit`` exit id or -1; ``exit_port`` the way out of the array for an exit cell (the
    side through which its exit lane leaves);
    ``entry`` bool; ``entry_no`` an entry cell's installation number; ``park`` bool, a parking cell (optional);
    ``forbid`` the port a parcel on a one-way cell may not move toward, -1 for none (optional). Inputs: ``labels``
    (the label read at entry cells, :func:`encode_goal`; -1 for none).

    Stationary (see :mod:`virtual_vehicle.cells.network.programs`): the tick's time enters only a new vehicle's id,
    given by a cell whose own id word then changes, so a cell whose state a step left unchanged repeats its outputs when
    its inputs do.
    """

    stationary = True

    schema = Schema.of(d=(1, WordType.I32), nxt=(4, WordType.I16),
                       vid=(5, WordType.I32), goal=(6, WordType.I16), key=(7, WordType.I32),
                       stop=(8, WordType.U16), req=(9, WordType.I32), rdep=(10, WordType.U8),
                       hold=(11, WordType.I32), ack=(12, WordType.U16), ex=(13, WordType.I16),
                       blk=(14, WordType.I32))
    """Words: ``d`` the four gradients' hop distances (one byte each), ``nxt`` the sequence number due next at the
    exits, ``stop`` the hops to the nearest stopping cell of the vehicle (low byte) and to its parking cell (high
    byte), ``ack`` the run of held cells ahead (low byte) and the port the hold was asked through plus one (high
    byte), the rest as their names say (see the module notes)."""
    _words = tuple(f.name for f in schema.fields)
    _types = tuple(DTYPE[f.type] for f in schema.fields)
    """The words' names and numpy types, in the schema's order (as the compiled step takes them)."""

    def __init__(self, speed: float, gap: int = 2, reach: int = 8, max_age: int = 0, edge_cost: int = 3,
                 period: float = 0.01, pitch: float = 0.1, compiled: bool = True):
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
        self.back_ticks = int(np.ceil((self.gap + 1) * pitch / (self.speed * self.period)))
        """Ticks a vehicle backs off for when it meets an older one head on: the gap and one more cell."""
        self.compiled = bool(compiled)
        """Step in compiled code (:func:`_step_cells`); False: in array operations (:meth:`_step_arrays`)."""

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
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
                "hage": np.zeros(n, dtype=np.int64), "back": np.zeros(n, dtype=np.int64),
                "bdir": np.full(n, _NONE, dtype=np.int64),
                "ack": np.zeros(n, dtype=np.int64), "nxt": np.zeros(n, dtype=np.int64),
                "park": np.full(n, 255, dtype=np.int64)}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`. Compiled
        (:func:`_step_cells`), or in array operations (:meth:`_step_arrays`, the same numbers) with
        ``compiled=False``."""
        if not self.compiled:
            return self._step_arrays(state, inputs)
        n, P = inputs.inbox.present.shape
        heard = state["heard"]
        new = {"dist": np.empty((n, MAX_EXITS), np.int64),
               "heard": {w: np.empty((n, P), np.int64) for w in self._words},
               "age": np.empty((n, P), np.int64), **{k: np.empty(n, np.int64) for k in _STATE}}
        out = Mailbox(self.schema, np.empty((n, P), bool),
                      {w: np.empty((n, P), t) for w, t in zip(self._words, self._types)})
        wheels = np.zeros((n, 2))
        self._run(state, inputs, np.arange(n), new, out, wheels)
        return {"dist": new["dist"], "heard": {k: new["heard"][k] for k in heard}, "age": new["age"],
                **{k: new[k] for k in _STATE}}, out, wheels

    def step_rows(self, state, inputs: CellInputs, rows: np.ndarray, outbox: Mailbox, wheels: np.ndarray):
        """Step only the cells ``rows`` (indices into the full inputs), writing their new state, sentences and wheel
        speeds into ``state``, ``outbox`` and ``wheels`` in place (as :class:`~virtual_vehicle.cells.network.programs.
        ChangedCells` keeps them): what :meth:`step` gives those rows when given their rows of everything, with
        no rows gathered nor written back. Returns two (n,) masks, the rows whose state and whose sentences changed
        (False for the others), or None when the arrays are not the sorter's own kinds (int64 state, the schema's
        word types, C-contiguous, writeable), to step the rows the general way."""
        if not self.compiled:
            return None
        n, P = inputs.inbox.present.shape
        kept = [state["dist"], *state["heard"].values(), state["age"], *(state[k] for k in _STATE)]
        if (tuple(state["heard"]) != self._words or any(a.dtype != np.int64 for a in kept)
                or any(outbox.values[w].dtype != t for w, t in zip(self._words, self._types))
                or outbox.present.dtype != bool or wheels.dtype != np.float64
                or not all(a.flags.c_contiguous and a.flags.writeable for a in (*kept, wheels, *outbox.arrays))):
            return None
        return self._run(state, inputs, np.asarray(rows, dtype=np.int64), state, outbox, wheels)

    def _run(self, state, inputs, rows, new, out, wheels):
        """Call :func:`_step_cells` for ``rows``, the new state into ``new`` (a state dict), the sentences into
        ``out`` and the wheel speeds into ``wheels``; returns its (unsettled, out_changed) masks."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        if P != 4:
            raise ValueError("the sorter runs on square lattices (four ports a cell)")
        cfg = inputs.config

        def cells(name, default, dtype):
            return _arg(cfg[name] if name in cfg else default, dtype)

        words = self._words
        labels = np.full(n, _NONE) if getattr(inputs, "labels", None) is None else inputs.labels
        tick = int(round(inputs.t / self.period)) if self.period else 0
        unsettled, out_changed = np.zeros(n, bool), np.zeros(n, bool)
        _step_cells(rows, _arg(inbox.present, bool),
                    tuple(_arg(inbox.values[w], t) for w, t in zip(words, self._types)),
                    tuple(_arg(state["heard"][w], np.int64) for w in words), _arg(state["age"], np.int64),
                    _arg(state["dist"], np.int64), tuple(_arg(state[k], np.int64) for k in _STATE),
                    _arg(inputs.sensors, bool), _arg(inputs.connected, bool),
                    cells("exit", np.full(n, _NONE), np.int64), cells("exit_port", np.full(n, _NONE), np.int64),
                    cells("entry", np.zeros(n, bool), bool), cells("entry_no", np.zeros(n), np.int64),
                    cells("park", np.zeros(n, bool), bool), cells("forbid", np.full(n, _NONE), np.int64),
                    _arg(labels, np.int64), tuple(new["heard"][w] for w in words), new["age"], new["dist"],
                    tuple(new[k] for k in _STATE), out.present, tuple(out.values[w] for w in words), wheels,
                    unsettled, out_changed, tick, self.max_age, self.edge_cost, self.reach, self.gap,
                    self.back_ticks, self.speed)
        return unsettled, out_changed

    def _step_arrays(self, state, inputs: CellInputs):
        """:meth:`step` in array operations: the readable statement of the rules (see the module notes), which the
        compiled step mirrors line by line and is tested against."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        cfg = inputs.config
        exit_id = np.asarray(cfg.get("exit", np.full(n, _NONE)), dtype=np.int64)
        exit_port = np.asarray(cfg.get("exit_port", np.full(n, _NONE)), dtype=np.int64)
        entry = np.asarray(cfg.get("entry", np.zeros(n, bool)), dtype=bool)
        entry_no = np.asarray(cfg.get("entry_no", np.zeros(n)), dtype=np.int64)
        park_cell = np.asarray(cfg.get("park", np.zeros(n, bool)), dtype=bool)
        forbid = np.asarray(cfg.get("forbid", np.full(n, _NONE)), dtype=np.int64)
        allowed = np.arange(P)[None, :] != forbid[:, None]  # one-way cells: not against the arrow
        labels = np.full(n, _NONE) if getattr(inputs, "labels", None) is None else np.asarray(inputs.labels)
        rows = np.arange(n)
        # -- what the neighbours said (last heard, trusted while fresh)
        heard = {k: np.where(inbox.present, inbox.values[k].astype(np.int64), v) for k, v in state["heard"].items()}
        age = np.where(inbox.present, 0, np.minimum(state["age"] + 1, np.iinfo(np.int32).max))
        trusted = (age <= self.max_age) & inputs.connected
        # -- routing: one gradient per exit
        # A cell at the edge of the array (a side with no neighbour) costs more, so parcels travel inside it and
        # meet the edge only at their exit.
        # In a sequenced run gradient PARK leads to a parking cell that no parcel covers.
        lit = _across(np.logical_or, np.asarray(inputs.sensors, dtype=bool))
        cost = np.where(_across(np.logical_and, inputs.connected) | (exit_id >= 0), 1, 1 + self.edge_cost)
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
        toward = (heard["key"] < _BIG) & ((heard["key"] // 64) % 8 == (np.arange(P)[None, :] + 2) % 4)
        has = trusted & (heard["vid"] >= 0)
        score = np.where(has, np.where(toward, 0, _HUGE) + heard["vid"], 2 * _HUGE)
        pick = np.argmin(score, axis=1)
        found = score[rows, pick] < 2 * _HUGE
        best_vid = heard["vid"][rows, pick]
        nb_entry = np.where(has & (heard["ex"] == _ENTRY), heard["vid"], _HUGE)
        entry_min = _across(np.minimum, nb_entry) if P else np.full(n, _HUGE)
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
        side = np.stack([(exit_port + 1) % 4, (exit_port + 3) % 4], axis=1)
        mine = on & (exit_id == target) & (exit_port >= 0)
        into_band = np.full(n, _NONE)
        for c in range(2):
            sp = side[:, c]
            beside = mine & same_nb[rows, sp] & (heard["ex"][rows, sp] != target)
            into_band = np.where(beside & (into_band < 0), (sp + 2) % 4, into_band)
        at_exit = mine & (into_band < 0)
        # The vehicle is a body, not a point: a side on which any cell carrying it (centre sensor lit) has no
        # neighbour (the array's edge, a dead cell, a cut link) is closed to the whole vehicle (spread hop-limited,
        # like stopping), except the way out at its exit. Each cell proposes its open side toward the neighbour
        # nearest the goal, ranked by that neighbour's distance: the front's proposals win, and a vehicle that
        # cannot go on sidesteps.
        core = on & np.asarray(inputs.sensors, dtype=bool)[:, 0]  # the cell carries the parcel (centre sensor lit)
        own_block = core[:, None] & (~inputs.connected | ~allowed)
        own_block &= ~(at_exit[:, None] & (np.arange(P)[None, :] == exit_port[:, None]))
        # only cells under a vehicle relay closed sides (the others say 63): computed on those rows alone
        under = np.flatnonzero(on)
        nb_block = np.stack([_unpack(heard["blk"][under], q, 6) for q in range(P)], axis=-1)  # (from port, side)
        relayed = np.full((n, P), 63, dtype=np.int64)
        relayed[under] = _across(np.minimum, np.where(same_nb[under, :, None] & (nb_block < self.reach),
                                                      nb_block + 1, 63))
        block = np.where(own_block, 0, relayed)
        block = np.where(on[:, None], block, 63)
        open_side = trusted & (block > self.reach)
        cand = np.where(open_side, nb_d, _BIG)
        port = np.argmin(cand, axis=1)
        movable = cand[rows, port] < UNREACHABLE
        prop_port = np.where(into_band >= 0, into_band, np.where(at_exit, exit_port, np.where(movable, port, _NONE)))
        prop_d = np.where(into_band >= 0, 0, np.where(at_exit, 1, cand[rows, port] + 3))
        # Head on: the cell ahead (in last tick's direction) is held for an older vehicle that asked for it from the
        # far side, or carries an older vehicle heading this way. Hold-based traffic alone would wait forever: the
        # younger vehicle backs off, for long enough to clear the other's gap and one more cell.
        pd = np.maximum(state["dir"], 0)
        ahead_vid = np.where(trusted[rows, pd], heard["hold"][rows, pd], _NONE)
        ahead_from = (heard["ack"][rows, pd] >> 8) - 1
        coming = ((heard["key"][rows, pd] < _BIG) & ((heard["key"][rows, pd] // 64) % 8 == (pd + 2) % 4)
                  & (heard["vid"][rows, pd] == ahead_vid))
        head_on = (on & (state["dir"] >= 0) & (ahead_vid >= 0) & (ahead_vid < vid) & ~same_nb[rows, pd]
                   & ((ahead_from == pd) | coming))
        back = np.where(on, np.maximum(state["back"] - 1, 0), 0)
        bdir = np.where(head_on, (pd + 2) % 4, state["bdir"])
        back = np.where(head_on, self.back_ticks, back)
        backing = (back > 0) & open_side[rows, np.maximum(bdir, 0)] & (bdir >= 0)
        prop_port = np.where(backing, bdir, prop_port)
        prop_d = np.where(backing, 0, prop_d)
        own_key = np.where(on & (prop_port >= 0), _key(prop_d, prop_port == state["dir"], np.maximum(prop_port, 0), 0),
                           _BIG)
        nb_key = np.where(same_nb, heard["key"], _BIG)
        nb_key = np.where(nb_key % 64 < self.reach, nb_key + 1, _BIG)  # one more hop; forget beyond reach
        key = np.minimum(own_key, _across(np.minimum, nb_key)) if P else own_key
        key = np.where(on, key, _BIG)
        direction = np.where(key < _BIG, (key // 64) % 8, _NONE)
        # -- traffic: requests ahead, holds, acknowledgements
        ahead_ok_port = (direction >= 0)
        dp = np.maximum(direction, 0)
        ahead_is_mine = same_nb[rows, dp] & ahead_ok_port
        # a waiting parcel parks where a cell that carries it is a parking cell; parked, it asks for nothing and is
        # an obstacle to the others
        own_park = np.where(on & ~turn & core & park_cell, 0, 255)
        park = self._spread(own_park, _unpack(heard["stop"], 1), same_nb, on)
        parked = on & (park <= self.reach)
        front = on & ahead_ok_port & ~ahead_is_mine & ~parked
        # leaving the array: only out of an exit cell of the goal (anywhere else the edge stops the vehicle)
        off_array = front & ~inputs.connected[rows, dp] & (exit_id == target) & (dp == exit_port)
        # requests that arrived: from a neighbour's front cell or a held cell passing it on
        req = np.where(inbox.present & trusted & (inbox.values["req"] >= 0), inbox.values["req"].astype(np.int64),
                       _HUGE)  # requests are events: only what arrived this tick
        choice = np.argmin(req, axis=1)  # the oldest vehicle asking (smallest id) gets the cell, always
        new_hold = np.where(req[rows, choice] < _HUGE, req[rows, choice], _NONE)
        hport = np.where(new_hold >= 0, choice, _NONE)
        hdep = np.where(new_hold >= 0, inbox.values["rdep"].astype(np.int64)[rows, np.maximum(hport, 0)], 0)
        # On a slow network a request does not arrive every tick: a hold lasts max_age ticks after it was last asked
        # for (on ideal rounds, one tick), unless an older vehicle asks meanwhile.
        keep = (state["hold"] >= 0) & (state["hage"] < self.max_age) & ((new_hold < 0) | (state["hold"] < new_hold))
        new_hold = np.where(keep, state["hold"], new_hold)
        hport = np.where(keep, state["hport"], hport)
        hdep = np.where(keep, state["hdep"], hdep)
        hage = np.where(keep, state["hage"] + 1, 0)
        new_hold = np.where(lit, _NONE, new_hold)  # a cell under a parcel is that parcel's, not anyone's to hold
        hport = np.where(new_hold >= 0, hport, _NONE)
        # acknowledgement: how many held cells run ahead from here (the whole chain when it reaches the edge)
        L = self.gap + 1  # one cell of look-ahead beyond the gap keeps a moving vehicle's chain ahead of it
        fwd = (hport + 2) % 4
        fp = np.maximum(fwd, 0)
        succ = (new_hold >= 0) & trusted[rows, fp] & (heard["hold"][rows, fp] == new_hold)
        edge = (new_hold >= 0) & ~inputs.connected[rows, fp]
        run_ahead = np.where(succ, heard["ack"][rows, fp] & 255, 0)
        ack = np.where(new_hold >= 0, np.where(edge, L, np.minimum(L, 1 + run_ahead)), 0)
        # a front cell may go when the cell ahead is held for its vehicle with a full free run, or at the exit edge
        ahead_hold = heard["hold"][rows, dp]
        ahead_ack = heard["ack"][rows, dp] & 255
        go_front = off_array | (trusted[rows, dp] & (ahead_hold == vid) & (ahead_ack >= self.gap))
        # a cell that only sees the parcel's edge may hang over the array's edge or a dead cell: only cells that
        # carry the parcel, or that have a neighbour ahead to ask, can stop it
        own_stop = np.where(front & ~go_front & (core | inputs.connected[rows, dp]), 0, 255)
        stop = self._spread(np.where(own_park == 0, 0, own_stop), _unpack(heard["stop"], 0), same_nb, on)
        moving = on & (direction >= 0) & (stop > self.reach)
        # -- outputs
        wheels = np.zeros((n, 2))
        sign = np.array([1.0, 1.0, -1.0, -1.0])
        axis = np.array([0, 1, 0, 1])
        wheels[rows[moving], axis[dp[moving]]] = sign[dp[moving]] * self.speed
        # the exit cell that lets a sequenced parcel out makes the next number due
        leaving = off_array & go_front & (seq >= 0)
        nxt = np.where(leaving, np.maximum(nxt, seq + 1), nxt)
        send = np.ones(n, dtype=bool)
        # no way through a parked parcel, nor through a gap of one cell beside it (too narrow for a parcel)
        beside_parked = _across(np.logical_or, trusted & (_unpack(heard["stop"], 1) <= self.reach)) & ~(on & ~parked)
        said = np.where((parked | beside_parked)[:, None], UNREACHABLE, np.minimum(dist, UNREACHABLE))
        out = Mailbox.broadcast(self.schema, send, P, d=_pack(said), nxt=nxt, vid=np.where(on, vid, _NONE),
                                goal=np.where(on, goal, _NONE), key=np.minimum(key, 2**31 - 1),
                                stop=np.minimum(stop, 255) + (np.minimum(park, 255) << 8), req=np.full(n, _NONE),
                                rdep=np.zeros(n),
                                hold=np.where(lit & on, vid, new_hold),
                                ack=np.minimum(ack, 255) + ((hport + 1) << 8),
                                ex=np.where(entry, _ENTRY, exit_id),
                                blk=_pack(np.minimum(block, 63), 6))
        # requests: front cells ask the cell ahead (depth 1); held cells pass it on until gap deep
        ask = front & inputs.connected[rows, dp]
        out.values["req"][rows[ask], dp[ask]] = vid[ask]
        out.values["rdep"][rows[ask], dp[ask]] = 1
        pass_on = (new_hold >= 0) & (hdep < L) & inputs.connected[rows, fp]
        out.values["req"][rows[pass_on], fwd[pass_on]] = new_hold[pass_on]
        out.values["rdep"][rows[pass_on], fwd[pass_on]] = hdep[pass_on] + 1
        new_state = {"dist": dist, "heard": heard, "age": age, "vid": vid, "goal": goal,
                     "dir": np.where(moving | (direction >= 0), direction, _NONE), "key": key, "stop": stop,
                     "hold": new_hold, "hdep": hdep, "hport": hport, "hage": hage, "ack": ack, "nxt": nxt,
                     "park": park, "back": back, "bdir": bdir}
        return new_state, out, wheels

    def _spread(self, own, heard, same_nb, on):
        """Hops to the nearest cell of the same vehicle that said 0 (``own`` 0 here), forgotten beyond ``reach``."""
        nb = np.where(same_nb & (heard < self.reach), heard + 1, 255)
        out = np.minimum(own, _across(np.minimum, nb)) if nb.shape[1] else own
        return np.where(on, out, 255)


# --------------------------------------------------------------------------- the step, compiled

def _arg(a, dtype) -> np.ndarray:
    """``a`` as :func:`_step_cells` takes it: C-contiguous, writeable (a read-only array is another compiled
    signature), of ``dtype``; copied only when it is not so already."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


_INT32_MAX = int(np.iinfo(np.int32).max)


@njit(cache=True)
def _unpacked(word, q, bits):
    """Field q of a word packed by :func:`_pack` (one value)."""
    return ((word & 0xFFFFFFFF) >> (bits * q)) & ((1 << bits) - 1)


@njit(cache=True)
def _first_min(a):
    """The index of the first smallest of ``a`` (numpy's argmin)."""
    best = 0
    for q in range(1, a.shape[0]):
        if a[q] < a[best]:
            best = q
    return best


@njit(cache=True)
def _spread_one(own, stop_word, field, same, on, reach):
    """:meth:`Sorter._spread` of one cell: ``stop_word`` its neighbours' packed ``stop`` words, ``same`` which of
    them carry its vehicle."""
    out = own
    for q in range(same.shape[0]):
        v = _unpacked(stop_word[q], field, 8)
        nb = v + 1 if same[q] and v < reach else 255
        out = min(out, nb)
    return out if on else 255


@njit(cache=True)
def _step_cells(rows, present, words, heard_in, age_in, dist_in, state_in, sensors, connected, exit_id, exit_port,
                entry, entry_no, park_cell, forbid, labels, heard_out, age_out, dist_out, state_out, sent_present,
                sent, wheels, unsettled, out_changed, tick, max_age, edge_cost, reach, gap, back_ticks, speed):
    """:meth:`Sorter.step` for the cells ``rows``, one at a time, compiled: the same integers, sentences and wheel
    speeds as the array version (:meth:`Sorter._step_arrays`, which the tests hold it to), each line of which is
    mirrored here in order. ``words`` are the words that arrived (``present``), ``heard_in`` those last heard,
    ``age_in``, ``dist_in`` and ``state_in`` (:data:`_STATE`'s order) the rest of the state; the new state, the
    sentences and the wheel speeds of each row stepped go to the ``*_out`` arrays, ``sent_present``, ``sent`` (the
    schema's order) and ``wheels``, which may be the very arrays read (a row reads and writes only its own row,
    each value read before it is written): then only those rows change. ``unsettled[i]`` and ``out_changed[i]``
    say whether row i's state and sentences differ from what the outputs held before."""
    n, P = present.shape
    w_d, w_nxt, w_vid, w_goal, w_key, w_stop, w_req, w_rdep, w_hold, w_ack, w_ex, w_blk = words
    hd, hnxt, hvid, hgoal, hkey, hstop, hreq, hrdep, hhold, hack, hex_, hblk = heard_out
    s_vid, s_goal, s_dir, s_key, s_stop, s_hold, s_hdep, s_hport, s_hage, s_ack, s_nxt, s_park, s_back, s_bdir = \
        state_in
    o_d, o_nxt, o_vid, o_goal, o_key, o_stop, o_req, o_rdep, o_hold, o_ack, o_ex, o_blk = sent
    park_any = False  # over the cells stepped, as the array version sees them
    for i in rows:
        park_any = park_any or park_cell[i]
    trusted = np.empty(P, np.bool_)
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
    for i in rows:
        # -- what the neighbours said (last heard, trusted while fresh)
        changed = False
        for q in range(P):
            p = present[i, q]
            changed |= _heard(p, w_d[i, q], heard_in[0], hd, i, q)
            changed |= _heard(p, w_nxt[i, q], heard_in[1], hnxt, i, q)
            changed |= _heard(p, w_vid[i, q], heard_in[2], hvid, i, q)
            changed |= _heard(p, w_goal[i, q], heard_in[3], hgoal, i, q)
            changed |= _heard(p, w_key[i, q], heard_in[4], hkey, i, q)
            changed |= _heard(p, w_stop[i, q], heard_in[5], hstop, i, q)
            changed |= _heard(p, w_req[i, q], heard_in[6], hreq, i, q)
            changed |= _heard(p, w_rdep[i, q], heard_in[7], hrdep, i, q)
            changed |= _heard(p, w_hold[i, q], heard_in[8], hhold, i, q)
            changed |= _heard(p, w_ack[i, q], heard_in[9], hack, i, q)
            changed |= _heard(p, w_ex[i, q], heard_in[10], hex_, i, q)
            changed |= _heard(p, w_blk[i, q], heard_in[11], hblk, i, q)
            old = age_in[i, q]
            age_out[i, q] = 0 if p else min(old + 1, _INT32_MAX)
            changed |= age_out[i, q] != old
            trusted[q] = (age_out[i, q] <= max_age) and connected[i, q]
            allowed[q] = q != forbid[i]
        # -- routing: one gradient per exit
        lit = False
        for s in range(sensors.shape[1]):
            lit = lit or sensors[i, s]
        linked = True
        for q in range(P):
            linked = linked and connected[i, q]
        cost = 1 if (linked or exit_id[i] >= 0) else 1 + edge_cost
        for e in range(MAX_EXITS):
            source = exit_id[i] == e
            if e == PARK and park_any:
                source = park_cell[i] and not sensors[i, 0]
            best = UNREACHABLE
            for q in range(P):
                best = min(best, _unpacked(hd[i, q], e, 8) if (trusted[q] and allowed[q]) else UNREACHABLE)
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
            vid, goal = _NONE, _NONE
        for q in range(P):
            toward = (hkey[i, q] < _BIG) and ((hkey[i, q] // 64) % 8 == (q + 2) % 4)
            has = trusted[q] and hvid[i, q] >= 0
            score[q] = ((0 if toward else _HUGE) + hvid[i, q]) if has else 2 * _HUGE
            nb_entry[q] = hvid[i, q] if (has and hex_[i, q] == _ENTRY) else _HUGE
        pick = _first_min(score)
        found = score[pick] < 2 * _HUGE
        best_vid = hvid[i, pick]
        entry_min = nb_entry[0]
        for q in range(1, P):
            entry_min = min(entry_min, nb_entry[q])
        if lit and vid < 0 and found:
            vid = best_vid
            goal = hgoal[i, pick]
        if lit and vid >= 0 and entry_min < vid:
            k = _first_min(nb_entry)
            vid = entry_min
            goal = hgoal[i, k]
        if lit and vid < 0 and entry[i] and labels[i] >= 0:
            vid = tick * 1024 + entry_no[i] % 1024
            goal = labels[i]
        on = lit and vid >= 0 and goal >= 0
        for q in range(P):
            same_nb[q] = trusted[q] and hvid[i, q] == vid and on
        g0 = max(goal, 0)
        goal_exit, seq = g0 % 4, g0 // 4 - 1
        turn = seq < 0 or seq <= nxt
        target = goal_exit if turn else -99
        # -- direction
        g = goal_exit if turn else PARK
        ep = exit_port[i]
        mine = on and exit_id[i] == target and ep >= 0
        into_band = _NONE
        for c in range(2):
            sp = (ep + 1) % 4 if c == 0 else (ep + 3) % 4
            beside = mine and same_nb[sp] and hex_[i, sp] != target
            if beside and into_band < 0:
                into_band = (sp + 2) % 4
        at_exit = mine and into_band < 0
        core = on and sensors[i, 0]
        for q in range(P):
            own_block = core and (not connected[i, q] or not allowed[q])
            own_block = own_block and not (at_exit and q == ep)
            relayed = 63
            if on:
                for p in range(P):
                    b = _unpacked(hblk[i, p], q, 6)
                    relayed = min(relayed, b + 1 if (same_nb[p] and b < reach) else 63)
            block[q] = 0 if own_block else relayed
            if not on:
                block[q] = 63
            open_side[q] = trusted[q] and block[q] > reach
            cand[q] = _unpacked(hd[i, q], g, 8) if open_side[q] else _BIG
        port = _first_min(cand)
        movable = cand[port] < UNREACHABLE
        if into_band >= 0:
            prop_port, prop_d = into_band, 0
        elif at_exit:
            prop_port, prop_d = ep, 1
        else:
            prop_port, prop_d = (port if movable else _NONE), cand[port] + 3
        # head on: back off
        sdir = s_dir[i]
        pd = max(sdir, 0)
        ahead_vid = hhold[i, pd] if trusted[pd] else _NONE
        ahead_from = (hack[i, pd] >> 8) - 1
        coming = ((hkey[i, pd] < _BIG) and ((hkey[i, pd] // 64) % 8 == (pd + 2) % 4)
                  and hvid[i, pd] == ahead_vid)
        head_on = (on and sdir >= 0 and ahead_vid >= 0 and ahead_vid < vid and not same_nb[pd]
                   and (ahead_from == pd or coming))
        back = max(s_back[i] - 1, 0) if on else 0
        bdir = (pd + 2) % 4 if head_on else s_bdir[i]
        if head_on:
            back = back_ticks
        backing = back > 0 and open_side[max(bdir, 0)] and bdir >= 0
        if backing:
            prop_port, prop_d = bdir, 0
        own_key = _BIG
        if on and prop_port >= 0:
            own_key = ((prop_d * 2 + (1 - (1 if prop_port == sdir else 0))) * 8 + max(prop_port, 0)) * 64 + 0
        least = 0
        for q in range(P):  # one more hop; forget beyond reach
            nk = hkey[i, q] if same_nb[q] else _BIG
            nk = nk + 1 if nk % 64 < reach else _BIG
            least = nk if q == 0 else min(least, nk)
        key = min(own_key, least)
        if not on:
            key = _BIG
        direction = (key // 64) % 8 if key < _BIG else _NONE
        if direction >= P:  # (the array version fails here too: a key word from no sorter)
            raise IndexError("a direction key names a port the cell does not have")
        # -- traffic
        ahead_ok_port = direction >= 0
        dp = max(direction, 0)
        ahead_is_mine = same_nb[dp] and ahead_ok_port
        own_park = 0 if (on and not turn and core and park_cell[i]) else 255
        park = _spread_one(own_park, hstop[i], 1, same_nb, on, reach)
        parked = on and park <= reach
        front = on and ahead_ok_port and not ahead_is_mine and not parked
        off_array = front and not connected[i, dp] and exit_id[i] == target and dp == ep
        for q in range(P):
            req[q] = np.int64(w_req[i, q]) if (present[i, q] and trusted[q] and w_req[i, q] >= 0) else _HUGE
        choice = _first_min(req)
        new_hold = req[choice] if req[choice] < _HUGE else _NONE
        hport = choice if new_hold >= 0 else _NONE
        hdep = np.int64(w_rdep[i, max(hport, 0)]) if new_hold >= 0 else 0
        keep = s_hold[i] >= 0 and s_hage[i] < max_age and (new_hold < 0 or s_hold[i] < new_hold)
        if keep:
            new_hold, hport, hdep = s_hold[i], s_hport[i], s_hdep[i]
        hage = s_hage[i] + 1 if keep else 0
        if lit:
            new_hold = _NONE
        if new_hold < 0:
            hport = _NONE
        L = gap + 1
        fwd = (hport + 2) % 4
        fp = max(fwd, 0)
        succ = new_hold >= 0 and trusted[fp] and hhold[i, fp] == new_hold
        edge = new_hold >= 0 and not connected[i, fp]
        run_ahead = hack[i, fp] & 255 if succ else 0
        ack = (L if edge else min(L, 1 + run_ahead)) if new_hold >= 0 else 0
        ahead_hold = hhold[i, dp]
        ahead_ack = hack[i, dp] & 255
        go_front = off_array or (trusted[dp] and ahead_hold == vid and ahead_ack >= gap)
        own_stop = 0 if (front and not go_front and (core or connected[i, dp])) else 255
        stop = _spread_one(0 if own_park == 0 else own_stop, hstop[i], 0, same_nb, on, reach)
        moving = on and direction >= 0 and stop > reach
        # -- outputs
        wheels[i, 0] = wheels[i, 1] = 0.0
        if moving:
            wheels[i, dp % 2] = (1.0 if dp < 2 else -1.0) * speed
        if off_array and go_front and seq >= 0:
            nxt = max(nxt, seq + 1)
        beside_parked = False
        for q in range(P):
            beside_parked = beside_parked or (trusted[q] and _unpacked(hstop[i, q], 1, 8) <= reach)
        beside_parked = beside_parked and not (on and not parked)
        word = 0
        for e in range(MAX_EXITS):
            said = UNREACHABLE if (parked or beside_parked) else min(dist_out[i, e], UNREACHABLE)
            word += said << (8 * e)
        if word >= 1 << 31:
            word -= 1 << 32
        blk = 0
        for q in range(P):
            blk += min(block[q], 63) << (6 * q)
        if blk >= 1 << 31:
            blk -= 1 << 32
        for q in range(P):  # requests: front cells ask the cell ahead, held cells pass it on until gap deep
            to_req[q], to_rdep[q] = _NONE, 0
        if front and connected[i, dp]:
            to_req[dp], to_rdep[dp] = vid, 1
        if new_hold >= 0 and hdep < L and connected[i, fp]:
            to_req[fwd], to_rdep[fwd] = new_hold, hdep + 1
        sent_new = False
        for q in range(P):
            sent_new |= not sent_present[i, q]
            sent_present[i, q] = True
            sent_new |= _put(o_d, i, q, word)
            sent_new |= _put(o_nxt, i, q, nxt)
            sent_new |= _put(o_vid, i, q, vid if on else _NONE)
            sent_new |= _put(o_goal, i, q, goal if on else _NONE)
            sent_new |= _put(o_key, i, q, min(key, 2**31 - 1))
            sent_new |= _put(o_stop, i, q, min(stop, 255) + (min(park, 255) << 8))
            sent_new |= _put(o_req, i, q, to_req[q])
            sent_new |= _put(o_rdep, i, q, to_rdep[q])
            sent_new |= _put(o_hold, i, q, vid if (lit and on) else new_hold)
            sent_new |= _put(o_ack, i, q, min(ack, 255) + ((hport + 1) << 8))
            sent_new |= _put(o_ex, i, q, _ENTRY if entry[i] else exit_id[i])
            sent_new |= _put(o_blk, i, q, blk)
        out_changed[i] = sent_new
        changed |= _put1(state_out[0], s_vid, i, vid)  # in _STATE's order
        changed |= _put1(state_out[1], s_goal, i, goal)
        changed |= _put1(state_out[2], s_dir, i, direction if (moving or direction >= 0) else _NONE)
        changed |= _put1(state_out[3], s_key, i, key)
        changed |= _put1(state_out[4], s_stop, i, stop)
        changed |= _put1(state_out[5], s_hold, i, new_hold)
        changed |= _put1(state_out[6], s_hdep, i, hdep)
        changed |= _put1(state_out[7], s_hport, i, hport)
        changed |= _put1(state_out[8], s_hage, i, hage)
        changed |= _put1(state_out[9], s_ack, i, ack)
        changed |= _put1(state_out[10], s_nxt, i, nxt)
        changed |= _put1(state_out[11], s_park, i, park)
        changed |= _put1(state_out[12], s_back, i, back)
        changed |= _put1(state_out[13], s_bdir, i, bdir)
        unsettled[i] = changed


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


_STATE = ("vid", "goal", "dir", "key", "stop", "hold", "hdep", "hport", "hage", "ack", "nxt", "park", "back", "bdir")
"""The sorter's per-cell state words that :func:`_step_cells` takes and makes as one tuple, in the order the state
holds them after ``dist``, ``heard`` and ``age``."""


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
        exit_id = np.asarray(config["exit"])
        self.forbid = np.asarray(config.get("forbid", np.full(n, _NONE)), dtype=np.int64)
        dist = self._distances([exit_id == e for e in range(MAX_EXITS)], exit_id, np.zeros(n, bool))
        return {"dist": dist, "vehicles": {}, "owner": np.full(n, _NONE, dtype=np.int64), "next": 0}

    def _distances(self, sources, exit_id, blocked) -> np.ndarray:
        """(len(sources), n) weighted hop distances to each mask of source cells (edge cells cost ``1 +
        edge_cost``, as in the cells' gradients), never through a ``blocked`` cell (a parked parcel's) nor against
        a one-way cell's arrow."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        topo = self.topo
        n = len(exit_id)
        conn = topo.connected
        cost = np.where(conn.all(axis=1) | (exit_id >= 0), 1.0, 1.0 + self.edge_cost)
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
        held = np.full(n, _NONE, dtype=np.int64)  # the vehicle each cell is held for this tick
        sign = np.array([1.0, 1.0, -1.0, -1.0])
        axis = np.array([0, 1, 0, 1])
        # sequencing, as the cells do: a parcel whose number is not yet due heads for a free parking cell and parks
        # where a cell carrying it is one; other parcels route around parked ones
        park_cell = np.asarray(cfg.get("park", np.zeros(n, bool)), dtype=bool)
        nxt = state.get("next", 0)
        blocked = np.zeros(n, dtype=bool)
        moving = np.zeros(n, dtype=bool)
        for vid, v in vehicles.items():
            goal_exit, seq = (int(x) for x in decode_goal(v["goal"]))
            v["turn"] = seq < 0 or seq <= nxt
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
                v["dir"] = _NONE
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
                wheels[cells, axis[direction]] = sign[direction] * self.speed
                out = (exit_id[cells] == target) & (exit_port[cells] == direction) & ~inputs.connected[cells, direction]
                if seq >= 0 and out.any():  # it leaves through its exit: the next number is due
                    nxt = max(nxt, seq + 1)
        return ({"dist": state["dist"], "vehicles": {k: {"goal": v["goal"], "dir": v["dir"], "back": v.get("back", 0),
                                                          "back_dir": v.get("back_dir", _NONE)}
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
        best, best_score = _NONE, np.inf
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
        return int(np.ceil(float(cfg.get("clearance", 0.3)) / (self.speed * self.period)))

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
