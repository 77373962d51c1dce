"""The distributed sorter (:class:`Sorter`): the cell program that runs the compiled policy
(:mod:`virtual_vehicle.cells.sorting.policy`; the rules in :mod:`virtual_vehicle.cells.sorting`). Units: SI."""

from __future__ import annotations

import numpy as np

from virtual_vehicle.cells.network.messages import DTYPE, Mailbox, Schema, rows_any
from virtual_vehicle.cells.network.programs import UNREACHABLE, CellInputs
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.cells.sorting import policy
from virtual_vehicle.cells.sorting.calendar import DueCalendar
from virtual_vehicle.cells.sorting.rules import BIG, MAX_EXITS, NONE, back_off_ticks, heartbeat_due, tick_of


class Sorter:
    """Distributed sorting program (the rules: :mod:`virtual_vehicle.cells.sorting`).

    Args:
        speed: wheel surface speed of a moving vehicle, m/s.
        gap: free cells a vehicle keeps ahead of it.
        reach: hops over which a vehicle's cells share direction and stop/go (at least its size in cells; 1..62,
            at most 30 on a hexagonal lattice).
        max_age: ticks a neighbour's words are trusted after it was last heard (0 on ideal rounds).
        edge_cost: extra hops a cell on the edge of the array (not an exit) counts in the gradients.
        period: the control period (s): a vehicle's id is the tick it was made (times 1024, plus its entry cell's
            installation number modulo 1024), so smaller ids are older vehicles.
        pitch: the cell pitch (m), known to every cell: a vehicle that meets an older one head on backs off for the
            time it takes to travel ``gap + 1`` pitches.
        heartbeat: the longest a cell stays silent (s): it sends on a port only when its sentence there changed, and
            every sentence at least this often, which repairs a lost one (0: every tick). A neighbour's last
            sentence is trusted for ``max_age`` ticks plus two heartbeats, so one lost heartbeat does not drop it;
            with whole sentences a cell that missed a neighbour's heartbeat asks it to say everything again, every
            tick until it hears it (:data:`~virtual_vehicle.cells.sorting.policy.ASK`), so that lost sentences do not
            make a connected neighbour untrusted.
        repeats: ticks a cell sends a port's sentence again after it changed (with a heartbeat): a change is lost
            only when all of them are. Twice as many on a port whose link lost a sentence (the cell asked that
            neighbour to say everything again, or was asked: :data:`~virtual_vehicle.cells.sorting.policy.LOSSY`,
            kept for good; never on loss-free rounds).
        partial: a sentence carries only the words that changed on its port (and those that changed in the last
            ``repeats`` ticks; every word at the heartbeat), and a cell keeps what it last heard of the words a
            sentence leaves out: on a slow wire a sentence of two changed words takes a fifth of the time of all
            twelve, so what changes reaches the neighbours sooner. Needs a heartbeat (it repairs a lost word).
        lead: cells a vehicle asks (and holds) beyond the ``gap + 1`` ahead of its front cells, while it still moves
            on a run of ``gap``: the slack that lets it ride on while each step's run of held cells is told back, where
            that takes longer than the step (a slow link: :func:`~virtual_vehicle.cells.sorting.rules.lead_cells`).
        lane_hold: ticks a vehicle moved sideways into its exit lane stands at the lane's far side before it is let go
            for half as long, again and again while it is there (0: it is not stopped there): on a slow link the
            cells agree on the turn out of the lane only after the body ran on
            (:func:`~virtual_vehicle.cells.sorting.rules.lane_hold_ticks`; the rule:
            :func:`~virtual_vehicle.cells.sorting.policy.lane_stop`).

    Cells have four ports (square lattices) or six (hexagonal ones: see :mod:`virtual_vehicle.cells.sorting` for
    what ahead, beside and behind mean there), all cells alike. Sensor 0 of every cell must be its centre (the
    default layout): a cell whose centre is covered carries the parcel; the others only see its edge.

    Config (per cell): ``exit`` exit id or -1; ``exit_port`` the way out of the array for an exit cell (the
    side through which its exit lane leaves);
    ``entry`` bool; ``entry_no`` an entry cell's installation number; ``park`` bool, a parking cell (optional);
    ``forbid`` the port a parcel on a one-way cell may not move toward, -1 for none (optional); ``inner`` (n, P) the
    ports with a neighbour installed and another cell beyond it (optional; default: those connected, so a dead
    neighbour looks like the edge); ``sides`` (n, P) the cell's sensor at the point it shares with the neighbour on
    each port (the midpoint of their centres), -1 none (optional; default none: a cell that sees only an edge then
    keeps its vehicle as before).
    Inputs: ``labels``
    (the label read at entry cells, :func:`~virtual_vehicle.cells.sorting.rules.encode_goal`; -1 for none).

    Stationary (see :mod:`virtual_vehicle.cells.network.programs`): the tick's time enters only a new vehicle's id,
    given by a cell whose own id word then changes, and the heartbeat, at the ticks :meth:`due` names; so a cell whose
    state a step left unchanged repeats its outputs when its inputs do, but at those ticks.
    """

    stationary = True
    clocks = True
    """:meth:`step_rows` takes the rows whose last step changed none of the state words the rules read back and
    whose sensors and labels did not change (``quiet``) and ticks the clocks alone of those that hear nothing new
    (see :class:`~virtual_vehicle.cells.network.programs.ChangedCells`)."""

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
                 period: float = 0.01, pitch: float = 0.1, heartbeat: float = 0.0,
                 repeats: int = 2, partial: bool = False, lead: int = 0, lane_hold: int = 0):
        if not speed > 0:
            raise ValueError("speed must be positive (m/s)")
        if not 1 <= reach <= 62:
            raise ValueError("reach must be 1..62 hops")
        if not 1 <= gap <= 62:  # a request's depth (up to gap + 1) lies below its LATE and YIELD marks
            raise ValueError("gap must be 1..62 cells")
        self.speed = float(speed)
        self.gap = int(gap)
        self.reach = int(reach)
        self.max_age = int(max_age)
        self.edge_cost = int(edge_cost)
        self.period = float(period)
        if not heartbeat >= 0:
            raise ValueError("heartbeat must be non-negative (s)")
        self.heartbeat_ticks = max(1, tick_of(heartbeat, self.period))
        """Ticks between two sentences of a cell with nothing new to say (1: it sends every tick)."""
        if not 0 <= repeats <= 1000:
            raise ValueError("repeats must be 0..1000 ticks")
        self.repeats = int(repeats) if self.heartbeat_ticks > 1 else 0
        """Ticks a new sentence is sent again (none when every tick sends everything anyway)."""
        if partial and self.heartbeat_ticks <= 1:
            raise ValueError("partial sentences need a heartbeat (it sends every word, repairing a lost one)")
        self.partial = bool(partial)
        """Whether sentences carry only the words that changed (see the class notes)."""
        if not (0 <= lead and self.gap + 1 + lead < 64):  # a request's depth lies below its LATE and YIELD marks
            raise ValueError(f"lead must be 0..{62 - self.gap} cells (gap + 1 + lead below 64)")
        self.lead = int(lead)
        """Cells a vehicle asks beyond ``gap + 1`` (see the class notes)."""
        if not 0 <= lane_hold <= 1_000_000:
            raise ValueError("lane_hold must be 0..1000000 ticks")
        self.lane_hold = int(lane_hold)
        """Ticks a vehicle stands at its exit lane's far side at a time (see the class notes)."""
        self.trust = self.max_age + 2 * (self.heartbeat_ticks - 1)
        """Ticks a neighbour's last sentence is trusted after it arrived."""
        self.back_ticks = back_off_ticks((self.gap + 1) * pitch, self.speed, self.period)
        """Ticks a vehicle backs off for when it meets an older one head on: the gap and one more cell."""

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        _check_ports(ports, self.reach)
        P = ports
        return {"dist": np.full((n, MAX_EXITS), UNREACHABLE, dtype=np.int64),
                # nothing heard yet: a neighbour with nothing to say, so that a partial sentence that comes first
                # (the one before it lost) leaves no zero distance to an exit, which would take a count to forget
                "heard": {f.name: np.full((n, P), rest, dtype=np.int64)
                          for f, rest in zip(self.schema.fields, policy.rest_words(P))},
                "heard_at": np.full((n, P), _NEVER, dtype=np.int64),
                "vid": np.full(n, NONE, dtype=np.int64), "goal": np.full(n, NONE, dtype=np.int64),
                "dir": np.full(n, NONE, dtype=np.int64), "key": np.full(n, BIG, dtype=np.int64),
                "stop": np.full(n, 255, dtype=np.int64), "hold": np.full(n, NONE, dtype=np.int64),
                "hdep": np.zeros(n, dtype=np.int64), "hport": np.full(n, NONE, dtype=np.int64),
                "hage": np.zeros(n, dtype=np.int64), "back": np.zeros(n, dtype=np.int64),
                "bdir": np.full(n, NONE, dtype=np.int64), "lane": np.zeros(n, dtype=np.int64),
                "ack": np.zeros(n, dtype=np.int64), "nxt": np.zeros(n, dtype=np.int64),
                "park": np.full(n, 255, dtype=np.int64),
                # nothing said yet: the first tick says everything
                "said": {f.name: np.full((n, P), _NEVER, dtype=np.int64) for f in self.schema.fields},
                "again": np.zeros((n, P), dtype=np.int64)}

    def due(self, t: float, state, config: dict) -> np.ndarray:
        """The (n,) cells that must be stepped at time ``t`` (s) whatever changed: those that stop trusting a
        silent neighbour now, those whose heartbeat is now, and those whose heartbeat was last tick (to fall silent
        again)."""
        tick = tick_of(t, self.period)
        woken = np.any(tick - state["heard_at"] == self.trust + 1, axis=1) | self._asking(tick, state)
        if self.heartbeat_ticks > 1:
            n = len(woken)
            number = np.broadcast_to(np.asarray(config.get("entry_no", 0), dtype=np.int64), (n,))
            woken |= heartbeat_due(tick, number, self.heartbeat_ticks)
            woken |= heartbeat_due(tick - 1, number, self.heartbeat_ticks)
        return woken

    def calendar(self, n: int, config: dict) -> DueCalendar:
        """A calendar of the cells :meth:`due` names, kept as the cells are stepped (what
        :class:`~virtual_vehicle.cells.network.programs.ChangedCells` asks instead of :meth:`due` over every cell
        every tick; :class:`~virtual_vehicle.cells.sorting.calendar.DueCalendar`), for ``n`` cells configured by
        ``config``."""
        return DueCalendar(n, self.period, self.trust, self.heartbeat_ticks, config.get("entry_no", 0),
                           None if self.partial else self.heartbeat_ticks + self.max_age)

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`. Compiled
        (:func:`~virtual_vehicle.cells.sorting.policy.step_cells`)."""
        n, P = inputs.inbox.present.shape
        heard = state["heard"]
        new = {"dist": np.empty((n, MAX_EXITS), np.int64),
               "heard": {w: np.empty((n, P), np.int64) for w in self._words},
               "heard_at": np.empty((n, P), np.int64), **{k: np.empty(n, np.int64) for k in _STATE},
               "said": {w: np.empty((n, P), np.int64) for w in self._words}, "again": np.empty((n, P), np.int64)}
        out = Mailbox(self.schema, np.empty((n, P), bool),
                      {w: np.empty((n, P), t) for w, t in zip(self._words, self._types)},
                      np.empty((n, P), np.int64) if self.partial else None)
        wheels = np.zeros((n, 2))
        self._run(state, inputs, np.arange(n), new, out, wheels)
        return {"dist": new["dist"], "heard": {k: new["heard"][k] for k in heard}, "heard_at": new["heard_at"],
                **{k: new[k] for k in _STATE}, "said": new["said"], "again": new["again"]}, out, wheels

    def step_rows(self, state, inputs: CellInputs, rows: np.ndarray, outbox: Mailbox, wheels: np.ndarray,
                  quiet: np.ndarray | None = None):
        """Step only the cells ``rows`` (indices into the full inputs), writing their new state, sentences and wheel
        speeds into ``state``, ``outbox`` and ``wheels`` in place (as :class:`~virtual_vehicle.cells.network.programs.
        ChangedCells` keeps them): what :meth:`step` gives those rows when given their rows of everything, with
        no rows gathered nor written back. Returns two (n,) masks, the rows whose state and whose sentences changed
        (False for the others), or None when the arrays are not the sorter's own kinds (int64 state, the schema's
        word types, C-contiguous, writeable), to step the rows the general way.

        ``quiet`` ((n,) bool): rows among ``rows`` whose last step changed none of the state words the rules read
        back (the third mask this returns then, or nothing at all; :data:`~virtual_vehicle.cells.sorting.policy.
        Outputs`) and whose sensors, links and labels are those of that step: those
        that hear nothing new, at a tick at which no neighbour they trust turns stale (and, with partial sentences,
        not their heartbeat), tick only their clocks
        (:func:`~virtual_vehicle.cells.sorting.policy.tick_cells`, which says why that is their step), the others
        are stepped whole. With it, four masks are returned: the two above, the rows whose state changed but in
        none of the words read back, and the rows that ticked their clocks alone."""
        kept = [state["dist"], *state["heard"].values(), state["heard_at"], *(state[k] for k in _STATE),
                *state["said"].values(), state["again"]]
        if (tuple(state["heard"]) != self._words or tuple(state["said"]) != self._words
                or any(a.dtype != np.int64 for a in kept)
                or any(outbox.values[w].dtype != t for w, t in zip(self._words, self._types))
                or outbox.present.dtype != bool or wheels.dtype != np.float64
                or (outbox.words is None) == self.partial
                or (self.partial and outbox.words.dtype != np.int64)
                or not all(a.flags.c_contiguous and a.flags.writeable for a in (*kept, wheels, *outbox.arrays))):
            return None
        rows = np.asarray(rows, dtype=np.int64)
        if quiet is None:
            return self._run(state, inputs, rows, state, outbox, wheels)[:2]
        n = len(quiet)
        light = quiet[rows]
        park = inputs.config.get("park")  # step_cells looks for parking cells among the rows it steps whole
        if park is not None and np.broadcast_to(np.asarray(park, dtype=bool), (n,))[rows].any():
            light[:] = False
        tick = tick_of(inputs.t, self.period)
        number = _arg(inputs.config.get("entry_no", _filled((n,), 0, np.int64)), np.int64)
        if self.partial:  # a heartbeat then says every word: a whole step
            light &= ~heartbeat_due(tick, number[rows], self.heartbeat_ticks)
        # a neighbour's last sentence that stops being trusted now changes what the rules read: a whole step (the
        # rest of what due() wakes a cell for, a heartbeat that only sends and the tick after it, tick_cells does)
        light[light] = ~rows_any(state["heard_at"][rows[light]] == tick - self.trust - 1)  # (numpy's any is slow)
        light[light] = ~self._asking(tick, state, rows[light])  # asking a neighbour again sends: a whole step
        unsettled, out_changed, ticking = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
        if light.any():  # first the clocks of the rows that hear nothing new, then the others whole
            done = np.zeros(n, bool)
            inbox = inputs.inbox
            carried = (_filled(inbox.present.shape, policy.ALL_WORDS, np.int64) if inbox.words is None
                       else _arg(inbox.words, np.int64))
            words = policy.Words(*(_arg(inbox.values[w], t) for w, t in zip(self._words, self._types)))
            policy.tick_cells(rows[light], policy.Inputs(_arg(inbox.present, bool), words,
                                                         _arg(inputs.sensors, bool), _arg(inputs.connected, bool),
                                                         carried),
                              number, tick, self.heartbeat_ticks, self.trust, self.partial, self._memory(state),
                              outbox.present,
                              np.empty(outbox.present.shape, np.int64) if outbox.words is None else outbox.words,
                              unsettled, out_changed, ticking, done)
            rows = rows[~done[rows]]
        else:
            done = np.zeros(n, bool)
        if len(rows):
            masks = self._run(state, inputs, rows, state, outbox, wheels)
            for mask, part in zip((unsettled, out_changed, ticking), masks):
                mask |= part
        return unsettled, out_changed, ticking, done

    def _asking(self, tick: int, state, rows=slice(None)) -> np.ndarray:
        """Per row of ``rows``, whether the cell may ask a neighbour to say everything again at ``tick``: it missed
        that neighbour's heartbeat (:func:`~virtual_vehicle.cells.sorting.policy.asking`; whether the link is up the
        step decides)."""
        if self.partial:
            return np.zeros(len(state["heard_at"][rows]), bool)
        ago = tick - state["heard_at"][rows]
        return np.any((ago > self.heartbeat_ticks + self.max_age) & (ago <= self.trust), axis=1)

    def _memory(self, st, arg=lambda a, dtype: a):
        """The state dict ``st`` as the compiled step's :class:`~virtual_vehicle.cells.sorting.policy.Memory`, each
        array through ``arg`` (default: as it is, for a state written in place)."""
        return policy.Memory(policy.Words(*(arg(st["heard"][w], np.int64) for w in self._words)),
                             arg(st["heard_at"], np.int64), arg(st["dist"], np.int64),
                             policy.CellState(*(arg(st[k], np.int64) for k in _STATE)),
                             policy.Words(*(arg(st["said"][w], np.int64) for w in self._words)),
                             arg(st["again"], np.int64))

    def _run(self, state, inputs, rows, new, out, wheels):
        """Step ``rows`` (:func:`~virtual_vehicle.cells.sorting.policy.step_cells`), the new state into ``new`` (a
        state dict), the sentences into ``out`` and the wheel speeds into ``wheels``; returns the (unsettled,
        out_changed, ticking) masks."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        _check_ports(P, self.reach)
        cfg = inputs.config

        def cells(name, default, dtype):
            return _arg(cfg[name] if name in cfg else _filled((n,), default, dtype), dtype)

        labels = _filled((n,), NONE, np.int64) if getattr(inputs, "labels", None) is None else inputs.labels
        carried = _filled((n, P), policy.ALL_WORDS, np.int64) if inbox.words is None else _arg(inbox.words, np.int64)
        words_out = np.empty((n, P), np.int64) if out.words is None else out.words  # scratch when not partial
        unsettled, out_changed, ticking = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
        policy.step_cells(
            rows,
            policy.Inputs(_arg(inbox.present, bool),
                          policy.Words(*(_arg(inbox.values[w], t) for w, t in zip(self._words, self._types))),
                          _arg(inputs.sensors, bool), _arg(inputs.connected, bool), carried),
            policy.Config(cells("exit", NONE, np.int64), cells("exit_port", NONE, np.int64),
                          cells("entry", False, bool), cells("entry_no", 0, np.int64),
                          cells("park", False, bool), cells("forbid", NONE, np.int64),
                          _arg(labels, np.int64),
                          _arg(cfg["inner"] if "inner" in cfg else inputs.connected, bool),
                          _arg(cfg["sides"] if "sides" in cfg else _filled((n, P), NONE, np.int64), np.int64)),
            policy.Rules(tick_of(inputs.t, self.period), self.max_age, self.edge_cost, self.reach, self.gap,
                         self.back_ticks, self.speed, self.heartbeat_ticks, self.trust,
                         self.repeats, self.partial, self.lead, self.lane_hold),
            self._memory(state, _arg), self._memory(new),
            policy.Outputs(out.present, policy.Words(*(out.values[w] for w in self._words)), wheels, unsettled,
                           out_changed, words_out, ticking))
        return unsettled, out_changed, ticking


def _check_ports(P: int, reach: int) -> None:
    """Raise ValueError unless the sorter runs on cells with ``P`` ports: four (square lattices) or six (hexagonal
    ones, where a hop count packs into five bits, so ``reach`` is at most 30 hops)."""
    if P not in (4, 6):
        raise ValueError(f"the sorter runs on square (four ports a cell) or hexagonal (six ports) lattices, not on "
                         f"cells with {P} ports")
    if P == 6 and reach > 30:
        raise ValueError(f"on a hexagonal lattice the sorter's reach is at most 30 hops (got {reach}): a hop count "
                         "packs into five bits beside the six ports")


def _filled(shape: tuple, value, dtype) -> np.ndarray:
    """An array of ``shape`` filled with ``value`` of ``dtype``, made once and kept (the step only reads these: the
    words a full sentence carries, a configuration's defaults), instead of anew every tick."""
    key = (shape, value, np.dtype(dtype))
    a = _FILLED.get(key)
    if a is None:
        if len(_FILLED) > 64:  # (arrays of other sizes: a few runs' worth)
            _FILLED.clear()
        a = _FILLED[key] = np.full(shape, value, dtype)
    return a


_FILLED: dict = {}


def _arg(a, dtype) -> np.ndarray:
    """``a`` as :func:`~virtual_vehicle.cells.sorting.policy.step_cells` takes it: C-contiguous, writeable (a
    read-only array is another compiled signature), of ``dtype``; copied only when it is not so already."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


_NEVER = -(1 << 40)
"""What a cell has said on a port before it first sends there (no word, 32 bits at most, equals it), and the tick
it heard a port that never spoke."""

_STATE = policy.CellState._fields
"""The sorter's per-cell state words after ``dist``, ``heard`` and ``age``, in the order the compiled step takes
them."""
