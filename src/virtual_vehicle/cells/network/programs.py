"""Cell programs and the multi-hop primitives they are built from.

The contract (one program runs on every cell; written once, vectorised over cells):

- ``schema``: the words of the sentences the program sends (:class:`~virtual_vehicle.cells.network.messages.Schema`).
- ``init(n, ports, config) -> state``: per-cell state, a dict of arrays whose first axis is the cell.
- ``step(state, inputs) -> (state, outbox, wheel_speeds)``: one control tick. ``inputs`` is a :class:`CellInputs`;
  ``outbox`` a Mailbox (what each cell sends on each port); ``wheel_speeds`` (n, 2) the surface speed of each cell's
  two wheels along their own drive directions, m/s.

Row i of every input is cell i's own: its sensors, its state, the sentences that arrived on its ports, which of its
ports lead to a neighbour, and its local configuration (set when it was installed, e.g. "I am an exit"). A program
must compute row i of its outputs from row i of its inputs only: no cell has an address, knows its position, or sees
another cell's state except through sentences. :func:`check_program` tests a program against this contract.

A program may also declare ``stationary = True``: a cell whose step left its state unchanged, given the same sensors,
inbox, links, configuration and label again, returns the same outputs whatever the tick's time, and its state holds
only per-cell arrays. A program whose cells act on a clock as well (a heartbeat) names the cells the time wakes with
``due(t, state, config)`` ((n,) bool, or None for none). :class:`ChangedCells` then steps only the cells whose inputs
or state changed (on a sorting floor, those near parcels and where routing is still settling), which gives the same
run to the last bit.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from virtual_vehicle.cells.network.messages import Mailbox, Schema, rows_differ
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.model import state_data

UNREACHABLE = 255
"""Hop distance meaning "no path known" (the largest U8)."""


@dataclass
class CellInputs:
    """What every cell sees at a tick. Arrays have one row per cell.

    Attributes:
        t: time of the tick, s: the instant on the run's time line at which these cells tick (one shared clock, or
            each cell's own, :mod:`~virtual_vehicle.cells.network.clocks`).
        sensors: (n, S) presence readings, 1 where a parcel covers the sensor.
        inbox: sentences that arrived since the last tick, per port.
        connected: (n, P) ports that lead to a neighbour (a cell can tell whether a neighbour is plugged in).
        config: per-cell local configuration, arrays by name.
        labels: (n,) the label (e.g. destination) a reader in the cell sees on the parcel above it, -1 for none;
            None when the run has no labelled parcels. Programs read it only where a reader is installed.
    """

    t: float
    sensors: np.ndarray
    inbox: Mailbox
    connected: np.ndarray
    config: dict = field(default_factory=dict)
    labels: np.ndarray | None = None


class CellProgram(Protocol):
    schema: Schema

    def init(self, n: int, ports: int, config: dict) -> dict:
        """Per-cell state for ``n`` cells with ``ports`` links each, as a dict of arrays with first axis n (``config``
        is the scenario's [control.config] table)."""

    def step(self, state: dict, inputs: CellInputs) -> tuple[dict, Mailbox, np.ndarray]:
        """One control tick for all cells at once, each using only its own row of ``state`` and ``inputs`` (its sensors,
        its inbox from its neighbours, its links): returns the new state, the outbox (a sentence per port) and the (n,
        2) wheel speeds, m/s along each cell's drive directions."""


# --------------------------------------------------------------------------- primitives (pure, vectorised)

def gradient_update(dist_in: np.ndarray, present: np.ndarray, is_source: np.ndarray, cap: int = UNREACHABLE) -> np.ndarray:
    """Distance-vector step: a source is at 0; any other cell is one more than the smallest distance it currently
    trusts from a neighbour (``present``), or ``cap`` (unreachable) if none is below cap - 1. Trusting only recent
    sentences makes the field re-converge when a cell or link dies (distances climb until they meet the new
    shortest path or ``cap``)."""
    heard = np.where(present, dist_in.astype(np.int64), cap)
    best = heard.min(axis=1) if heard.shape[1] else np.full(len(is_source), cap)
    return np.where(is_source, 0, np.minimum(best + 1, cap)).astype(np.int64)


def flood_update(seq: np.ndarray, value: np.ndarray, hops: np.ndarray, in_seq: np.ndarray, in_value: np.ndarray,
                 in_hops: np.ndarray, present: np.ndarray, limit: int):
    """Hop-limited flood: a cell adopts the newest sentence (highest sequence number; fewest hops on a tie) heard
    on any port if it is newer than what it holds, one hop further. Returns new (seq, value, hops, adopted)."""
    s = np.where(present, in_seq.astype(np.int64), -1)
    h = np.where(present, in_hops.astype(np.int64), 1 << 30)
    key = s * (1 << 31) - h  # highest seq, then fewest hops
    port = np.argmax(key, axis=1)
    rows = np.arange(len(seq))
    best_seq, best_hops = s[rows, port], h[rows, port]
    adopt = (best_seq > seq) & (best_hops < limit)
    new_seq = np.where(adopt, best_seq, seq)
    new_val = np.where(adopt, in_value[rows, port], value)
    new_hops = np.where(adopt, best_hops + 1, hops)
    return new_seq, new_val, new_hops, adopt


def descend_port(dist_in: np.ndarray, present: np.ndarray, own: np.ndarray) -> np.ndarray:
    """For forwarding along a gradient: the port whose neighbour reported the smallest distance, if it is smaller
    than the cell's own; -1 where no neighbour is closer (the cell is a source or cut off)."""
    heard = np.where(present, dist_in.astype(np.int64), np.iinfo(np.int64).max)
    port = np.argmin(heard, axis=1)
    closer = heard[np.arange(len(own)), port] < own
    return np.where(closer, port, -1)


# --------------------------------------------------------------------------- programs

class Routing:
    """Gradient to the exits plus packet forwarding (a multi-hop demonstration program; wheels stay stopped).

    Config: ``exit`` (n,) bool — cells where packets are delivered; ``packet`` (n,) int16 — a packet (its value) a
    cell holds at the start, -1 for none. Each tick every cell broadcasts its hop distance to the nearest exit; a
    cell holding packets forwards one (value, hop count) on the port of its closest neighbour. Delivered packets are
    recorded in ``state["delivered"]`` (value, hops) at the exit cell.

    A neighbour's distance is trusted for ``max_age`` ticks after it was last heard: on ideal rounds every neighbour
    is heard every tick, but on a real (wire-level) network a busy link may deliver only now and then.
    """

    schema = Schema.of(dist=(1, WordType.U8), pkt=(2, WordType.I16), pkt_hops=(3, WordType.U8))

    def __init__(self, max_age: int = 0):
        self.max_age = int(max_age)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each."""
        packets = np.asarray(config.get("packet", np.full(n, -1)), dtype=np.int64)
        return {"dist": np.full(n, UNREACHABLE, dtype=np.int64),
                "heard": np.full((n, ports), UNREACHABLE, dtype=np.int64),
                "age": np.full((n, ports), np.iinfo(np.int32).max, dtype=np.int64),
                "carry": [[(int(v), 0)] if v >= 0 else [] for v in packets],
                "delivered": [[] for _ in range(n)]}

    def step(self, state, inputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds,
        m/s."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        exits = np.asarray(inputs.config.get("exit", np.zeros(n, bool)), dtype=bool)
        heard = np.where(inbox.present, inbox.values["dist"], state["heard"])
        age = np.where(inbox.present, 0, np.minimum(state["age"] + 1, np.iinfo(np.int32).max))
        trusted = age <= self.max_age
        dist = gradient_update(heard, trusted, exits)
        carry = state["carry"]
        delivered = state["delivered"]
        # take custody of packets that arrived
        got = inbox.present & (inbox.values["pkt"] >= 0)
        for i, p in zip(*np.nonzero(got)):
            carry[i].append((int(inbox.values["pkt"][i, p]), int(inbox.values["pkt_hops"][i, p])))
        for i in np.flatnonzero(exits):
            delivered[i].extend(carry[i])
            carry[i] = []
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, dist=np.minimum(dist, UNREACHABLE),
                                pkt=np.full(n, -1), pkt_hops=np.zeros(n))
        port = descend_port(heard, trusted, dist)
        for i in np.flatnonzero((port >= 0) & np.array([len(c) > 0 for c in carry])):
            value, hops = carry[i].pop(0)
            out.values["pkt"][i, port[i]] = value
            out.values["pkt_hops"][i, port[i]] = hops + 1
        return ({"dist": dist, "heard": heard, "age": age, "carry": carry, "delivered": delivered}, out,
                np.zeros((n, 2)))


class Flood:
    """Hop-limited flood of a value from the cells whose config ``origin`` is set (wheels stay stopped)."""

    schema = Schema.of(seq=(1, WordType.U16), value=(2, WordType.I16), hops=(3, WordType.U8))

    def __init__(self, limit: int):
        self.limit = int(limit)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each."""
        origin = np.asarray(config.get("origin", np.zeros(n, bool)), dtype=bool)
        return {"seq": np.where(origin, 1, 0), "value": np.where(origin, np.asarray(config.get("value", 0)), 0),
                "hops": np.zeros(n, dtype=np.int64), "fresh": origin.copy()}

    def step(self, state, inputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds,
        m/s."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        seq, value, hops, adopted = flood_update(state["seq"], state["value"], state["hops"], inbox.values["seq"],
                                                 inbox.values["value"], inbox.values["hops"], inbox.present,
                                                 self.limit)
        send = (adopted | state["fresh"]) & (hops < self.limit)  # relay what is new, in the tick it arrives
        out = Mailbox.broadcast(self.schema, send, P, seq=seq, value=value, hops=hops)
        return {"seq": seq, "value": value, "hops": hops, "fresh": np.zeros(n, bool)}, out, np.zeros((n, 2))


# --------------------------------------------------------------------------- stepping only the cells that changed

def tree_map(fn: Callable, tree, *others):
    """``fn`` applied to the leaves of ``tree`` (a program's state: leaves nested in dicts, lists, tuples or
    dataclasses), zipped with the same leaves of ``others``; the result keeps the nesting."""
    if isinstance(tree, dict):
        return {k: tree_map(fn, v, *(o[k] for o in others)) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(tree_map(fn, *vs) for vs in zip(tree, *others))
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        return dataclasses.replace(tree, **{f.name: tree_map(fn, getattr(tree, f.name), *(getattr(o, f.name)
                                                                                              for o in others))
                                            for f in dataclasses.fields(tree) if f.init})
    return fn(tree, *others)


def _leaves(tree) -> list:
    out: list = []
    tree_map(out.append, tree)
    return out


def _cell_array(a, n: int) -> np.ndarray:
    if not (isinstance(a, np.ndarray) and a.ndim >= 1 and a.shape[0] == n):
        raise TypeError(f"a stationary program's state holds per-cell arrays only (first axis {n}), not "
                        f"{type(a).__name__} {getattr(a, 'shape', '')}")
    return a


def _rows(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    return np.take(a, rows, axis=0)  # a few times faster than a[rows] for a 2-d array


def _put_rows(targets: list, values: list, rows: np.ndarray, n: int) -> None:
    """Write ``values[j]`` into the rows ``rows`` of ``targets[j]`` (arrays with first axis n), in place.

    A row of a contiguous 2-d array is copied as whole units of its bytes (16, 8, 4, 2 or 1 of them, the largest
    that divides the row: a complex128, an integer), one unit per element of a flat index, bit for bit: numpy
    copies a few large elements far faster than many small ones (an (n, 4) int16 row as one int64: 1.6 against 6.6
    us for 1268 rows; a[rows] = b took 15-20 us)."""
    flat: dict[int, np.ndarray] = {}  # by units a row: where the rows' units lie in a flattened array
    for a, b in zip(targets, values):
        b = np.asarray(b)
        k = a.size // n
        if a.ndim == 1 or not a.flags.c_contiguous or not k:
            a[rows] = b
            continue
        if b.dtype != a.dtype or not b.flags.c_contiguous or b.shape != (len(rows), *a.shape[1:]):
            b = np.ascontiguousarray(np.broadcast_to(b, (len(rows), *a.shape[1:])), dtype=a.dtype)  # as a[rows] = b
        size = a.itemsize * k
        unit = next(u for u in _UNITS if size % u.itemsize == 0)
        m = size // unit.itemsize
        if m not in flat:
            flat[m] = rows if m == 1 else (rows[:, None] * m + np.arange(m)).ravel()
        a.reshape(n, k).view(unit).reshape(-1)[flat[m]] = b.reshape(len(rows), k).view(unit).reshape(-1)


_UNITS = tuple(np.dtype(t) for t in (np.complex128, np.int64, np.int32, np.int16, np.uint8))
"""What :func:`_put_rows` copies a row as: the largest of these whose size divides the row's."""


class ChangedCells:
    """Steps a stationary program (``program.stationary``, see the module notes) on only the cells whose inputs or
    state changed since the last tick; every other cell repeats what it returned last tick, which is what the
    program would return. The outputs equal those of stepping every cell, to the last bit (tested).

    A cell is stepped when its state changed in its last step, a sentence on any of its ports differs from last
    tick's (``inbox_changed``, or found by comparison when the delivery model cannot tell), or its sensors or label
    changed, or the program's ``due`` names it. Every cell is stepped when the links or the configuration changed
    (other objects: they are not compared element by element), or when the state passed in is not the one this
    object returned (the run reset some cells).

    A program may also offer ``step_rows(state, inputs, rows, outbox, wheels)``: step only the cells ``rows`` of the
    full inputs, writing their new state, sentences and wheel speeds into this object's own ``state``, ``outbox``
    and ``wheels`` in place, and return the (n,) masks of the rows whose state and whose sentences changed (or None
    to be stepped the general way). The compiled sorter does: then no rows are gathered, compared or written back.

    A program that declares ``clocks = True`` keeps clocks in its state (a tick last heard, a count of repeats
    left) that change while nothing else does; its ``step_rows`` then takes ``quiet``, the (n,) cells whose last
    step changed nothing that a step on the same inputs computes otherwise but their clocks (it returned them as a
    third mask, or changed nothing at all) and whose sensors and labels did not change, and may tick only their clocks where it can prove that is their whole step
    (their inbox, and whether the time makes the tick more than that for them - its ``due`` names these cells
    for other reasons too, such as a heartbeat that only sends - it judges itself); it returns a fourth mask, the
    cells it did so. Such a cell stays stepped every tick while its clocks run, but for a fraction of a step's
    cost.

    A program whose ``due`` names cells by their clocks may offer ``calendar(n, config)``: an object kept from one
    tick to the next (made afresh at every tick that steps every cell, ``restart(t, state)``) whose ``due(t, state)``
    equals the program's ``due`` and which is told the cells stepped (``stepped(t, state, rows)``), so that finding
    the cells the time wakes costs the cells stepped and due, not the array.

    When more than ``full_share`` of the cells would be stepped (a lossy network, a floor in turmoil), gathering them
    costs more than it saves, and so does comparing: every cell is then stepped without comparing anything for
    1, 2, 4, ... up to ``max_backoff`` ticks in a row (the count doubles each time it happens again, and starts
    over at 1 once a tick steps fewer), after which one tick compares again.
    """

    def __init__(self, program, full_share: float = 0.5, max_backoff: int = 64):
        if not getattr(program, "stationary", False):
            raise ValueError(f"{type(program).__name__} does not declare stationary = True")
        self.program = program
        self.full_share = float(full_share)
        self.max_backoff = int(max_backoff)
        self.backoff = 1  # ticks of plain stepping the next time most cells change
        self.skip = 0  # plain ticks still to go
        self.last: dict | None = None
        self.ticks = 0
        self.stepped = 0
        """Ticks run, and cells stepped over all of them (a full step counts every cell)."""
        self.ticked = 0
        """Cells whose clocks alone ticked (a program with ``clocks``), not counted in ``stepped``; a count for
        benchmarks, not kept by :meth:`to_data`."""

    _COUNTS = ("backoff", "skip", "ticks", "stepped")

    def to_data(self) -> dict:
        """Its state as data: the plain-stepping schedule (``backoff``, ``skip``) and its counts (``ticks``,
        ``stepped``). What it kept of the last tick is a cache: without it the next tick steps every cell, which
        gives the same outputs to the last bit."""
        return {k: int(getattr(self, k)) for k in self._COUNTS}

    def load_data(self, d) -> None:
        """Go on from what :meth:`to_data` wrote (on a stepper of the same program); raises ValueError for other
        data."""
        d = state_data.fields(d, self._COUNTS, "stepper")
        values = {k: state_data.integer(d, k, "stepper") for k in self._COUNTS}
        if not 1 <= values["backoff"] <= self.max_backoff:
            raise ValueError(f"stepper.backoff: {values['backoff']} is not in [1, {self.max_backoff}]")
        self.__dict__.update(values)
        self.last = None

    def step(self, state, inputs: CellInputs, inbox_changed: np.ndarray | None = None):
        """One tick: ``(state, outbox, wheels, outbox_changed)``, the first three as :meth:`CellProgram.step` returns
        them, then the (n,) cells whose outbox differs from last tick's (all of them at the first tick), or None
        when every cell was stepped without comparing (see the class notes). The state, outbox and wheels returned
        are this object's own and are updated in place next tick: copy to keep them."""
        n = len(inputs.sensors)
        if self.skip:
            self.skip -= 1
            return self._plain(state, inputs, n)
        last = self.last
        sensors = np.asarray(inputs.sensors)
        labels = None if inputs.labels is None else np.asarray(inputs.labels)
        compare = inbox_changed is None  # the delivery model cannot tell: compare with the last inbox
        if (last is None or state is not last["state"] or inputs.connected is not last["connected"]
                or not _same_objects(inputs.config, last["config"]) or (labels is None) != (last["labels"] is None)):
            return self._full(state, inputs, sensors, labels, compare)
        if compare:
            if last["inbox"] is None:  # the last tick's inbox was not kept: its delivery model told what changed
                return self._full(state, inputs, sensors, labels, compare)
            inbox_changed = rows_differ(inputs.inbox.arrays, last["inbox"], n)
        sensed = rows_differ([sensors], [last["sensors"]], n)  # the inputs that changed, but the inbox
        if labels is not None:
            sensed |= labels != last["labels"]
        calendar = last.get("calendar")
        if calendar is not None:  # the cells the time wakes, from those due now (the program's own calendar)
            woken = calendar.due(inputs.t, state)
        else:
            due = getattr(self.program, "due", None)  # cells the time wakes (a heartbeat), whatever changed
            woken = None if due is None else due(inputs.t, state, inputs.config)
        moved = sensed if woken is None else sensed | woken
        changed = last["unsettled"] | moved | inbox_changed
        rows = np.flatnonzero(changed)
        if len(rows) > self.full_share * n:  # most cells changed: step them all, and stop comparing for a while
            self.skip = self.backoff - 1
            self.backoff = min(2 * self.backoff, self.max_backoff)
            return self._plain(state, inputs, n)
        self.backoff = 1
        self.ticks += 1
        self.stepped += len(rows)
        self._remember(inputs, sensors, labels, compare)
        outbox, wheels = last["outbox"], last["wheels"]
        if not len(rows):
            last["unsettled"] = changed
            return state, outbox, wheels, changed
        step_rows = getattr(self.program, "step_rows", None)
        clocks = getattr(self.program, "clocks", False) and step_rows is not None
        if clocks:  # the cells whose last step changed no state but clocks may tick those alone (class notes)
            ticking = last.get("ticking")
            still = ~last["unsettled"] if ticking is None else ticking | ~last["unsettled"]
            masks = step_rows(state, inputs, rows, outbox, wheels, still & ~sensed)
        else:
            masks = None if step_rows is None else step_rows(state, inputs, rows, outbox, wheels)
        if masks is not None:  # stepped in place: nothing gathered, compared or written back here
            if calendar is not None:
                calendar.stepped(inputs.t, state, rows)
            last["unsettled"], out_changed = masks[:2]
            if clocks:
                last["ticking"] = masks[2]
                ticked = int(np.count_nonzero(masks[3]))
                self.ticked += ticked
                self.stepped -= ticked
            return state, outbox, wheels, out_changed
        last.pop("ticking", None)  # stepped the general way: every cell it steps, stepped whole
        leaves = last["leaves"]  # the state's own arrays, updated in place
        old = [_rows(a, rows) for a in leaves]
        them = iter(old)
        sub_state = tree_map(lambda a: next(them), state)
        config = {k: _rows(v, rows) if k in last["per_cell"] else v for k, v in inputs.config.items()}
        sub = CellInputs(inputs.t, _rows(sensors, rows), inputs.inbox.take(rows),
                         _rows(inputs.connected, rows), config, None if labels is None else labels[rows])
        new, out, sub_wheels = self.program.step(sub_state, sub)
        new_leaves = _leaves(new)
        unsettled = np.zeros(n, dtype=bool)
        unsettled[rows] = rows_differ(new_leaves, old, len(rows))
        boxes = outbox.arrays
        new_boxes = out.arrays
        out_changed = np.zeros(n, dtype=bool)
        out_changed[rows] = rows_differ(new_boxes, [_rows(a, rows) for a in boxes], len(rows))
        _put_rows([*leaves, *boxes, wheels], [*new_leaves, *new_boxes, np.asarray(sub_wheels, dtype=float)], rows,
                  n)
        last["unsettled"] = unsettled
        if calendar is not None:
            calendar.stepped(inputs.t, state, rows)
        return state, outbox, wheels, out_changed

    def _plain(self, state, inputs, n: int):
        """Every cell stepped, nothing compared nor kept: the next tick that compares again steps every cell."""
        self.last = None
        self.ticks += 1
        self.stepped += n
        return (*self.program.step(state, inputs), None)

    def _full(self, state, inputs, sensors, labels, keep_inbox: bool):
        n = len(sensors)
        self.ticks += 1
        self.stepped += n
        new, out, wheels = self.program.step(state, inputs)
        new = tree_map(lambda a: np.array(_cell_array(a, n)), new)  # this object's own, updated in place later
        old = _leaves(state)
        fresh = _leaves(new)
        same_shape = len(old) == len(fresh) and all(np.shape(a) == np.shape(b) for a, b in zip(old, fresh))
        unsettled = rows_differ(fresh, old, n) if same_shape else np.ones(n, dtype=bool)
        outbox = Mailbox(out.schema, out.present.copy(), {k: v.copy() for k, v in out.values.items()})
        before = None if self.last is None else self.last["outbox"]
        if before is not None and before.schema == outbox.schema and before.present.shape == outbox.present.shape:
            out_changed = rows_differ(outbox.arrays, before.arrays, n)
        else:
            out_changed = np.ones(n, dtype=bool)
        per_cell = {k for k, v in inputs.config.items() if isinstance(v, np.ndarray) and v.ndim >= 1
                    and v.shape[0] == n}
        self.last = {"state": new, "leaves": fresh, "connected": inputs.connected, "config": inputs.config,
                     "per_cell": per_cell, "unsettled": unsettled, "outbox": outbox,
                     "wheels": np.array(wheels, dtype=float)}
        calendar = getattr(self.program, "calendar", None)
        if calendar is not None:  # every cell stepped: every cell filed afresh
            self.last["calendar"] = calendar(n, inputs.config)
            self.last["calendar"].restart(inputs.t, new)
        self._remember(inputs, sensors, labels, keep_inbox)
        return new, outbox, self.last["wheels"], out_changed

    def _remember(self, inputs, sensors, labels, keep_inbox: bool):
        last = self.last
        last["sensors"] = sensors.copy()
        last["labels"] = None if labels is None else labels.copy()
        last["inbox"] = [a.copy() for a in inputs.inbox.arrays] if keep_inbox else None


def step_group(program, state, inputs: CellInputs, rows: np.ndarray, outbox: Mailbox, wheels: np.ndarray):
    """Step only the cells ``rows`` (indices, ascending) of the full ``inputs``: the cells whose own clock ticks now
    (:mod:`~virtual_vehicle.cells.network.clocks`). Their new state, sentences and wheel speeds are written into
    ``state``, ``outbox`` and ``wheels`` in place; every other cell keeps its own. Returns the state (the same
    object, or, for a state with leaves that are not per-cell arrays, a new one that holds the stepped cells'
    rows). Uses the program's ``step_rows`` where it offers one (see :class:`ChangedCells`); else steps every cell
    and keeps the rows of ``rows``, which is what they would compute alone (a program's row i depends on row i of
    its inputs only)."""
    step_rows = getattr(program, "step_rows", None)
    if step_rows is not None and step_rows(state, inputs, rows, outbox, wheels) is not None:
        return state
    n = len(inputs.sensors)
    new, out, new_wheels = program.step(state, inputs)

    def keep(old, fresh):
        if isinstance(old, np.ndarray) and old.ndim >= 1 and old.shape[0] == n and old.flags.writeable:
            old[rows] = np.take(fresh, rows, axis=0)
            return old
        return fresh  # not a per-cell array: the program's own, as it returned it

    state = tree_map(keep, state, new)
    outbox.present[rows] = out.present[rows]
    for k, v in outbox.values.items():
        v[rows] = out.values[k][rows]
    wheels[rows] = np.asarray(new_wheels, dtype=float)[rows]
    return state


def _same_objects(a: dict, b: dict) -> bool:
    """Whether two configurations hold the same objects (a configuration is set once; arrays are not compared)."""
    return a is b or (a.keys() == b.keys() and all(a[k] is b[k] for k in a))


# --------------------------------------------------------------------------- contract checker

def check_program(program: CellProgram, topology, config: dict, ticks: int = 5, seed: int = 0,
                  sensors: np.ndarray | None = None) -> None:
    """Check a program against the cell-program contract on ``topology`` (ideal rounds): the output shapes and
    dtypes are right, the program is deterministic, and it is local: relabelling the cells (permuting ids, and the
    topology, per-cell configuration and ``sensors`` readings with them; a scalar configuration entry is every
    cell's) relabels its outputs exactly. A program that
    declares itself ``stationary`` must also give the same outputs when only the cells that changed are stepped
    (:class:`ChangedCells`). ``sensors``: (n, S) readings held for every tick (default: nothing seen). Raises
    AssertionError."""
    from virtual_vehicle.cells.network.delivery import IdealRounds
    from virtual_vehicle.cells.network.topology import Topology

    n, P = topology.n, topology.ports
    perm = np.random.default_rng(seed).permutation(n)
    inv = np.argsort(perm)
    # cell perm[k] of the original is cell k of the relabelled array
    nb = topology.neighbor[perm]
    relabelled = Topology(np.where(nb >= 0, inv[np.maximum(nb, 0)], -1), topology.back_port[perm],
                          topology.link_up[perm], topology.alive[perm])
    pconfig = {k: np.asarray(v)[perm] if np.ndim(v) else v for k, v in config.items()}  # a scalar: every cell's
    seen = np.zeros((n, 1), bool) if sensors is None else np.asarray(sensors, dtype=bool)

    def run(topo, cfg, seen):
        state = program.init(n, P, cfg)
        inbox = Mailbox.empty(program.schema, n, P)
        delivery = IdealRounds(topo)
        trace = []
        for k in range(ticks):
            inputs = CellInputs(k * 0.01, seen, inbox, topo.connected, cfg)
            state, out, wheels = program.step(state, inputs)
            assert out.present.shape == (n, P) and wheels.shape == (n, 2), "outputs must be (n, P) and (n, 2)"
            for f in program.schema.fields:
                assert out.values[f.name].shape == (n, P)
            trace.append((out.present.copy(), {k2: v.copy() for k2, v in out.values.items()}, np.array(wheels)))
            inbox, _ = delivery.exchange(out, k * 0.01, 0.01)
        return trace

    a = run(topology, config, seen)
    again = run(topology, config, seen)
    b = run(relabelled, pconfig, seen[perm])
    for (pa, va, wa), (pa2, va2, wa2), (pb, vb, wb) in zip(a, again, b):
        assert np.array_equal(pa, pa2) and np.array_equal(wa, wa2), "the program is not deterministic"
        assert np.array_equal(pa[perm], pb), "sending depends on cell ids: the program is not local"
        assert np.array_equal(wa[perm], wb), "wheel speeds depend on cell ids: the program is not local"
        for name in va:
            assert np.array_equal(np.where(pa, va[name], 0)[perm], np.where(pb, vb[name], 0)), \
                f"word {name!r} depends on cell ids: the program is not local"
    if getattr(program, "stationary", False):
        _check_stationary(program, topology, config, seen, ticks, seed)


def _check_stationary(program, topology, config: dict, seen: np.ndarray, ticks: int, seed: int) -> None:
    """Every tick, the full step and :class:`ChangedCells` (comparing inboxes, never falling back to a full step)
    give the same outputs, while the sensors of a random fifth of the cells read the opposite of ``seen`` (so that
    changed cells are stepped in arbitrary subsets)."""
    from virtual_vehicle.cells.network.delivery import IdealRounds

    n, P = topology.n, topology.ports
    rng = np.random.default_rng(seed)
    some = ChangedCells(program, full_share=1.0)
    runs = [[program.init(n, P, config), Mailbox.empty(program.schema, n, P), IdealRounds(topology)]
            for _ in range(2)]
    for k in range(ticks):
        outputs = []
        sensors = seen ^ (rng.random(n) < 0.2)[:, None]
        for j, run in enumerate(runs):
            inputs = CellInputs(k * 0.01, sensors, run[1], topology.connected, config)
            run[0], out, wheels, *_ = some.step(run[0], inputs) if j else program.step(run[0], inputs)
            outputs.append((out.arrays, np.array(wheels)))
            run[1], _ = run[2].exchange(out, k * 0.01, 0.01)
        (box_a, wheels_a), (box_b, wheels_b) = outputs
        assert np.array_equal(wheels_a, wheels_b) and all(np.array_equal(a, b) for a, b in zip(box_a, box_b)), \
            f"tick {k}: stepping only the cells that changed gives other outputs: the program is not stationary"
