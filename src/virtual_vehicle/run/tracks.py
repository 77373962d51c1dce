"""A parcel's track as a ticked run goes (:class:`ParcelTrack`): only the samples on the output grid and the latest
state are kept, with the events (as columns, :class:`EventLog`) and the energy and solver counts added up tick by
tick, so that a long run does not hold a piece of trajectory a tick.

Units: SI (s, m, rad).
"""

from __future__ import annotations

from array import array as _array
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from virtual_vehicle.engine.dynamics import Trajectory
from virtual_vehicle.engine.plant import SUMMED_STATS, joined_stats, on_grid
from virtual_vehicle.engine.stepping import CHANGED_SETS, Event
from virtual_vehicle.model.state_data import array, fields, integer


def _stack(states: list[np.ndarray]) -> np.ndarray:
    """Parcels' states (each (6,)) as one (N, 6) float array."""
    return np.array(states, dtype=np.float64).reshape(len(states), 6)


_SUMMED = frozenset(SUMMED_STATS)


class EventLog(Sequence):
    """A long run's events of one parcel kept as columns, not objects: a support event takes about 670 bytes as an
    object (its dict, state tuple and cell tuples), about 100 here (its time, kind, six state numbers and changed
    cells in growing typed arrays, text only where there is any), so that a run of an hour holds its events in a
    sixth of the memory. A sequence of events: reading one (by index, slice or iteration) makes it an :class:`Event`
    again, equal to the one taken in; :meth:`append` and :meth:`extend` take events in (one made by
    :meth:`Event.support_between` has its changed cells worked out then). Compares equal to any sequence of the same
    events. Times in s, states ``[x, y, theta, vx, vy, omega]``."""

    __slots__ = ("_t", "_kind", "_state", "_cells", "_text")
    _KINDS: list[str] = []  # the kinds seen, shared by every log (a kind is kept as its index here)
    _CODES: dict[str, int] = {}

    def __init__(self, events=()):
        self._t, self._kind, self._state = _array("d"), _array("H"), _array("d")
        self._cells = tuple((_array("q"), _array("q", [0])) for _ in CHANGED_SETS)  # (values, ends) per changed set
        self._text: dict[int, tuple[str, str]] = {}  # event index -> (message, partner), where either is not ""
        self.extend(events)

    @classmethod
    def _code(cls, kind: str) -> int:
        code = cls._CODES.get(kind)
        if code is None:
            if type(kind) is not str:
                raise TypeError(f"an event's kind is a str, not {type(kind).__name__}")
            code = cls._CODES[kind] = len(cls._KINDS)
            cls._KINDS.append(kind)
        return code

    def append(self, event: Event) -> None:
        """Take one event in."""
        state = event.state
        if len(state) != 6:
            raise ValueError(f"an event's state has 6 numbers, not {len(state)}")
        self._kind.append(self._code(event.kind))
        self._t.append(event.t)
        self._state.extend(state)
        for (values, ends), name in zip(self._cells, CHANGED_SETS):
            ids = getattr(event, name)  # (a lazily made event works its changed cells out here)
            if ids:
                values.extend(ids)
            ends.append(len(values))
        if event.message or event.partner:
            self._text[len(self._t) - 1] = (event.message, event.partner)

    def extend(self, events) -> None:
        """Take events in, in order."""
        for e in events:
            self.append(e)

    def __len__(self) -> int:
        return len(self._t)

    def _event(self, k: int) -> Event:
        message, partner = self._text.get(k, ("", ""))
        changed = [tuple(values[ends[k]:ends[k + 1]]) for values, ends in self._cells]
        return Event(self._t[k], self._KINDS[self._kind[k]], tuple(self._state[6 * k:6 * k + 6]), *changed,
                     message=message, partner=partner)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self._event(j) for j in range(*k.indices(len(self)))]
        n = len(self)
        if not -n <= k < n:
            raise IndexError("event index out of range")
        return self._event(k % n)

    def __iter__(self):
        return (self._event(k) for k in range(len(self)))

    def __eq__(self, other) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, str):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other))

    __hash__ = None

    def __repr__(self) -> str:
        return f"EventLog({len(self)} events)"

    def to_columns(self) -> dict:
        """The events as :meth:`Event.to_columns` writes them, from the columns (no event is made)."""
        k = len(self)
        text = [self._text.get(j, ("", "")) for j in range(k)]
        out = {"t": np.array(self._t, dtype=np.float64), "kind": [self._KINDS[c] for c in self._kind],
               "state": np.array(self._state, dtype=np.float64).reshape(k, 6)}
        for name, (values, ends) in zip(CHANGED_SETS, self._cells):
            out[name] = {"counts": np.diff(np.array(ends, dtype=np.int64)), "flat": np.array(values, dtype=np.int64)}
        out["message"], out["partner"] = [m for m, _ in text], [p for _, p in text]
        return out

    @classmethod
    def from_columns(cls, d, where: str = "events") -> EventLog:
        """The log of the events :meth:`Event.to_columns` (or :meth:`to_columns`) wrote; ValueError as
        :meth:`Event.from_columns`."""
        return cls(Event.from_columns(d, where))


class ParcelTrack:
    """One parcel's trajectory as a networked run goes: only the samples on the output grid and the latest state
    are kept (a run of an hour at 100 Hz would otherwise hold a piece per tick), events, status and the energy and
    solver counts (added up as :func:`~virtual_vehicle.engine.plant.join` does)."""

    def __init__(self):
        self.times: list[float] = []
        self.states: list[np.ndarray] = []
        self.events = EventLog()  # as columns: a long run keeps every parcel's events
        self._piece = None  # the latest piece, whose last state, status, end and stats carry on
        self._quiet = None  # or (steps, k): the latest piece was a quiet step, not yet made a Trajectory
        self.segments = 0
        self.rhs_evals = 0
        self.stats_pieces: list[dict] = []

    def settle(self) -> None:
        """Make the latest piece and the stats piece Trajectories if they are still kept as quiet steps (a checkpoint
        writes Trajectories, not the stepper's blocks)."""
        self.piece
        self._stats_first()

    @property
    def piece(self) -> Trajectory | None:
        """The latest piece (None before the first)."""
        if self._quiet is not None:
            steps, k = self._quiet
            self._piece, self._quiet = steps.trajectory(k), None
        return self._piece

    @property
    def started(self) -> bool:
        """Whether the track has taken in a tick yet."""
        return self._piece is not None or self._quiet is not None

    def _sample(self, times: np.ndarray, states: np.ndarray) -> None:
        """Keep the samples at ``times`` (s, on the output grid) with their ``states`` (an array of this track's own,
        whose rows it keeps) after the last kept."""
        for t, y in zip(times.tolist(), states):
            if not self.times or t > self.times[-1]:
                self.times.append(t)
                self.states.append(y)

    def add(self, tr: Trajectory, grid: np.ndarray, on: np.ndarray | None = None) -> None:
        """Take in the parcel's trajectory over one tick (as the plant returns it untrimmed): of its samples, those
        on the output ``grid`` (s) and its last state. ``on``: which of its times lie on the grid, when known."""
        if len(grid):  # most control ticks hold no output sample
            if on is None:
                on = on_grid(tr.times, grid)
            self._sample(tr.times[on], tr.states[on])
        self.events.extend(tr.events)
        self.segments += tr.segments
        self.rhs_evals += tr.rhs_evals
        self._piece, self._quiet = tr, None
        if tr.stats:
            first = self._stats_first()
            if first and not (_SUMMED.isdisjoint(tr.stats) and _SUMMED.isdisjoint(first[0].stats)):
                self.stats_pieces = join_stats([*first, tr])
            else:
                self.stats_pieces = [tr]  # the latest stands

    def add_quiet(self, steps, k: int, grid: np.ndarray, on: np.ndarray | None = None) -> None:
        """:meth:`add` for a tick the quiet stepper alone took, as ``steps.trajectory(k)`` (one step, no events, the
        stats the count of solves only; or a ride, ``steps.summed``: its stats joined when read), without making that
        Trajectory unless it is asked for."""
        if len(grid):
            if on is None:
                on = on_grid(steps.times, grid)
            self._sample(steps.times[on], steps.states[steps.rows[k], on])
        self.segments += 1
        self.rhs_evals += steps.evals
        self._quiet = ref = steps, k
        if steps.summed:
            self._add_ride_stats(steps, k)
            return
        head = self.stats_pieces[0] if self.stats_pieces else None
        if type(head) is _RideJoin:
            head = self._stats_first()[0]
        if head is not None and type(head) is not tuple and not _SUMMED.isdisjoint(head.stats):
            self.stats_pieces = join_stats([head, self.piece])  # (a quiet step's own stats hold nothing summed)
        else:
            self.stats_pieces = [ref]  # the latest stands, made a Trajectory when it is read

    def _add_ride_stats(self, steps, k: int) -> None:
        """The stats of a ride (``steps.trajectory(k)``, :class:`~virtual_vehicle.engine.ride.RideSteps`) joined to
        those so far as :meth:`add` joins them, without making that Trajectory: kept as ``_RideJoin(base, steps, k)``,
        the join of ``base`` (None: nothing) and the ride. A ride adds nothing to the summed stats and takes its others
        from the last piece, so after a first piece that holds its kinetic energy at the start, the join of a run of
        rides is that piece's join with the last of them alone."""
        head = self.stats_pieces[0] if self.stats_pieces else None
        if head is None:
            self.stats_pieces = [_RideJoin(None, steps, k)]
            return
        if type(head) is _RideJoin:
            base = head.steps.trajectory(head.k) if head.base is None else head.base
        else:
            base = self._stats_first()[0]
        if "kinetic_start" in base.stats:
            self.stats_pieces = [_RideJoin(base, steps, k)]
        else:  # its kinetic energy at the start would be the first ride's: joined now
            self.stats_pieces = join_stats([*self._stats_first(), steps.trajectory(k)])

    def _stats_first(self) -> list:
        """``stats_pieces[:1]``, a quiet step or a join with a ride there made its Trajectory."""
        first = self.stats_pieces[:1]
        if first and type(first[0]) is tuple:
            steps, k = first[0]
            first = self.stats_pieces = [steps.trajectory(k)]
        elif first and type(first[0]) is _RideJoin:
            base, steps, k = first[0]
            ride = steps.trajectory(k)
            first = self.stats_pieces = [ride] if base is None else join_stats([base, ride])
        return first

    def to_data(self) -> dict:
        """The track as data: the samples kept (``times`` (k,) s, ``states`` (k, 6)), the events as columns
        (:meth:`Event.to_columns`), the latest ``piece`` and the ``stats_pieces`` (:meth:`Trajectory.to_data` each,
        a quiet step made its Trajectory first) and the counts."""
        self.settle()
        return {"times": np.array(self.times, dtype=np.float64), "states": _stack(self.states),
                "events": self.events.to_columns(),
                "piece": None if self._piece is None else self._piece.to_data(),
                "segments": int(self.segments), "rhs_evals": int(self.rhs_evals),
                "stats_pieces": [tr.to_data() for tr in self.stats_pieces]}

    @classmethod
    def from_data(cls, d, where: str = "track") -> "ParcelTrack":
        """The track :meth:`to_data` wrote; raises ValueError for data of other keys, dtypes or shapes."""
        d = fields(d, ("times", "states", "events", "piece", "segments", "rhs_evals", "stats_pieces"), where)
        track = cls()
        times = array(d, "times", "f", (None,), where)
        track.times, track.states = times.tolist(), list(array(d, "states", "f", (len(times), 6), where))
        track.events = EventLog.from_columns(d["events"], f"{where}.events")
        track._piece = None if d["piece"] is None else Trajectory.from_data(d["piece"], f"{where}.piece")
        track.segments, track.rhs_evals = integer(d, "segments", where), integer(d, "rhs_evals", where)
        pieces = d["stats_pieces"]
        if type(pieces) is not list or len(pieces) > 1:
            raise ValueError(f"{where}.stats_pieces: not a list of at most one piece")
        track.stats_pieces = [Trajectory.from_data(p, f"{where}.stats_pieces") for p in pieces]
        return track

    def trajectory(self) -> Trajectory:
        """The parcel's trajectory so far: the samples kept on the output grid and the latest state, the events, and
        the counts and stats added up over the ticks."""
        times, states = list(self.times), list(self.states)
        end = float(self.piece.times[-1])
        if not times or end > times[-1]:
            times.append(end)
            states.append(self.piece.states[-1].copy())
        stats = self._stats_first()[0].stats if self.stats_pieces else dict(self.piece.stats)
        return Trajectory(np.array(times), np.array(states).reshape(-1, 6), self.events, self.piece.status,
                          self.piece.t_end, self.segments, self.rhs_evals, stats)


class _RideJoin(NamedTuple):
    """A track's stats so far, kept unmade: the join (:func:`join_stats`) of ``base`` (a Trajectory; None: nothing)
    and the ride ``steps.trajectory(k)``."""

    base: Trajectory | None
    steps: object
    k: int


def join_stats(pieces: list[Trajectory]) -> list[Trajectory]:
    """The stats of consecutive pieces added up (as :func:`~virtual_vehicle.engine.plant.join` does), as one stand-in
    piece (its samples are not used)."""
    first, last = pieces[0], pieces[-1]
    return [Trajectory(first.times[:1], first.states[:1], [], last.status, last.t_end, 0, 0, joined_stats(pieces))]
