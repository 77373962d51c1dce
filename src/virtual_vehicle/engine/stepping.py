"""What a parcel's integration records, and the driver of fixed-step methods: :class:`Event`, :class:`Trajectory`,
output sample grids, and :func:`fixed_steps`, shared by the event engine's fixed mode
(:mod:`virtual_vehicle.engine.dynamics`) and the stick-slip stepper (:mod:`virtual_vehicle.engine.stickslip`).

Units: SI (s, m, rad; states ``[x, y, theta, vx, vy, omega]``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from virtual_vehicle.errors import TippingError
from virtual_vehicle.model.state_data import array, fields, from_ragged, integer, number, ragged, text, texts


@dataclass(frozen=True)
class Event:
    """Something that changed the dynamics of one parcel.

    ``kind`` is ``"support"`` (cells entered / left the footprint, lifted off / touched down), ``"tip"`` (the
    parcel's centre of mass left its supports; the parcel falls off the array and is no longer simulated), or, in
    multi-parcel runs (:mod:`virtual_vehicle.engine.plant`), ``"contact"`` / ``"release"`` (it started / stopped pushing
    against the parcel named ``partner``); a law with modes (stick-slip) adds ``"stick"`` (wheels caught up with the
    parcel) and ``"slip"`` (wheels broke away), the wheels named "entry:wheel" in ``message``.
    Times in s, state as ``[x, y, theta, vx, vy, omega]``.
    """

    t: float
    kind: str
    state: tuple[float, ...]
    entered: tuple[int, ...] = ()
    left: tuple[int, ...] = ()
    lifted: tuple[int, ...] = ()
    touched: tuple[int, ...] = ()
    message: str = ""
    partner: str = ""

    @classmethod
    def support(cls, t: float, state: tuple[float, ...], entered: tuple[int, ...], left: tuple[int, ...],
                lifted: tuple[int, ...], touched: tuple[int, ...]) -> Event:
        """``Event(t, "support", state, entered, left, lifted, touched)``: the same frozen object, made without the
        dataclass's nine guarded field assignments (half of the ~1 us a support change's record took). The
        arguments are taken as they are: ``t`` a float (s), the others tuples."""
        ev = object.__new__(cls)
        ev.__dict__.update(t=t, kind="support", state=state, entered=entered, left=left, lifted=lifted,
                           touched=touched, message="", partner="")
        return ev

    @classmethod
    def support_between(cls, t: float, state: tuple[float, ...], old: tuple, new: tuple) -> Event:
        """The support event from a piece keyed ``old`` to one keyed ``new`` (each (supporting cell ids, ids of those
        in contact), as tuples or sets): :meth:`support` of the cells that changed between them, which are worked
        out only when first read (most of a run's support events are only counted, and a compiled event loop makes
        hundreds a call). ``t`` a float (s), ``state`` a tuple."""
        ev = object.__new__(cls)
        ev.__dict__.update(t=t, kind="support", state=state, message="", partner="", _keys=(old, new))
        return ev

    def __getattr__(self, name: str):
        """The changed cells of an event made by :meth:`support_between`, worked out on first read."""
        keys = self.__dict__.get("_keys")
        if keys is None or name not in CHANGED_SETS:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        self._settle()
        return self.__dict__[name]

    def _settle(self) -> None:
        """Work out the changed cells of an event made by :meth:`support_between` (nothing for any other)."""
        keys = self.__dict__.pop("_keys", None)
        if keys is not None:
            (old_s, old_c), (new_s, new_c) = ((frozenset(s), frozenset(c)) for s, c in keys)
            self.__dict__.update(entered=_ordered(new_s - old_s), left=_ordered(old_s - new_s),
                                 lifted=_ordered((old_c - new_c) & new_s), touched=_ordered((new_c - old_c) & old_s))

    def __getstate__(self):
        self._settle()
        return self.__dict__

    @classmethod
    def to_columns(cls, events: list[Event]) -> dict:
        """A list of events as data (a run's state is data): ``t`` (k,) s, ``state`` (k, 6), ``entered``, ``left``,
        ``lifted``, ``touched`` as ragged int columns (:func:`~virtual_vehicle.model.state_data.ragged`), and
        ``kind``, ``message`` and ``partner`` as lists of k strings (any text, which a numpy text array is not)."""
        return {"t": np.array([e.t for e in events], dtype=np.float64),
                "kind": [e.kind for e in events],
                "state": np.array([e.state for e in events], dtype=np.float64).reshape(len(events), 6),
                **{name: ragged(getattr(e, name) for e in events) for name in ("entered", "left", "lifted", "touched")},
                "message": [e.message for e in events], "partner": [e.partner for e in events]}

    @classmethod
    def from_columns(cls, d, where: str = "events") -> list[Event]:
        """The events :meth:`to_columns` wrote; raises ValueError for data of other keys, dtypes or shapes."""
        d = fields(d, ("t", "kind", "state", "entered", "left", "lifted", "touched", "message", "partner"), where)
        t = array(d, "t", "f", (None,), where)
        k = len(t)
        columns = [t.tolist(), texts(d, "kind", k, where),
                   [tuple(row) for row in array(d, "state", "f", (k, 6), where).tolist()],
                   *(from_ragged(d[name], k, f"{where}.{name}") for name in CHANGED_SETS),
                   texts(d, "message", k, where), texts(d, "partner", k, where)]
        return [cls(*row) for row in zip(*columns)]


CHANGED_SETS = ("entered", "left", "lifted", "touched")
"""The names of an :class:`Event`'s changed cell sets (cell ids), in the order its columns are written."""
for _name in CHANGED_SETS:  # no class defaults, so that an event made by Event.support_between asks __getattr__
    delattr(Event, _name)  # (the dataclass's __init__ keeps its own defaults)


@dataclass
class Trajectory:
    """What happened to one parcel: samples, events, and how the run ended.

    Attributes:
        times: (k,) sample times, s. states: (k, 6) states at those times.
        events: support changes, tipping and (a law with modes) wheels gripping or slipping, in time order.
        status: ``"completed"`` (reached the end time) or ``"tipped"``.
        t_end: time the parcel stopped being simulated, s.
        segments: smooth pieces integrated (event mode) or steps taken (fixed mode).
        rhs_evals: right-hand-side evaluations.
    """

    times: np.ndarray
    states: np.ndarray
    events: list[Event]
    status: str
    t_end: float
    segments: int = 0
    rhs_evals: int = 0
    stats: dict = field(default_factory=dict)

    def to_data(self) -> dict:
        """This trajectory as data: its arrays, its events as columns (:meth:`Event.to_columns`), its status and
        counts, and its stats (names to plain numbers). A stick-slip call's own list of mode changes
        (``stats["mode_events"]``) is not written: joining pieces drops it too, keeping its count ``mode_changes``
        (the changes themselves are in its events, as ``"stick"`` and ``"slip"``)."""
        return {"times": self.times, "states": self.states, "events": Event.to_columns(self.events),
                "status": self.status, "t_end": float(self.t_end), "segments": int(self.segments),
                "rhs_evals": int(self.rhs_evals),
                "stats": {k: v.item() if isinstance(v, np.generic) else v for k, v in self.stats.items()
                          if k != "mode_events"}}

    @classmethod
    def from_data(cls, d, where: str = "trajectory") -> Trajectory:
        """The trajectory :meth:`to_data` wrote; raises ValueError for data of other keys, dtypes or shapes."""
        d = fields(d, ("times", "states", "events", "status", "t_end", "segments", "rhs_evals", "stats"), where)
        times = array(d, "times", "f", (None,), where)
        stats = d["stats"]
        if type(stats) is not dict or not all(type(k) is str and type(v) in (int, float, bool)
                                              for k, v in stats.items()):
            raise ValueError(f"{where}.stats: not a dict of names to numbers")
        return cls(times, array(d, "states", "f", (len(times), 6), where), Event.from_columns(d["events"],
                                                                                              f"{where}.events"),
                   text(d, "status", where), number(d, "t_end", where), integer(d, "segments", where),
                   integer(d, "rhs_evals", where), dict(stats))


def diff_event(t, y, old, new) -> Event | None:
    """The support event between two pieces (each with ``sets``: (support, contact) id sets), or None."""
    old_sets, new_sets = old.sets, new.sets
    if old_sets == new_sets:  # (the cells that changed are worked out when the event is read)
        return None
    return Event.support_between(float(t), tuple(np.asarray(y, dtype=float).tolist()), old_sets, new_sets)


def _ordered(ids: frozenset[int]) -> tuple[int, ...]:
    return tuple(sorted(ids)) if ids else ()


def sample_grid(t0: float, t1: float, sample_dt: float) -> np.ndarray:
    """Output sample times (s): ``t0, t0 + sample_dt, ...`` up to ``t1``, and ``t1`` itself."""
    n_samples = int(np.floor((t1 - t0) / sample_dt * (1 + 1e-12))) + 1
    times = t0 + sample_dt * np.arange(n_samples)
    if times[-1] < t1 - 1e-12 * max(1.0, abs(t1)):
        times = np.append(times, t1)
    return times


def fixed_steps(model, y0, t0, t1, dt, sample_times, progress, advance):
    """Drive a fixed-step method: ``advance(piece, t, y, h) -> y_next`` takes one step of length h from state y.
    Support changes are logged at the end of the step in which they happened; tipping ends the run.
    Returns (times, states, events, status, t_end, steps)."""
    if not dt > 0:
        raise ValueError("dt must be positive")
    events: list[Event] = []
    t, y = float(t0), np.array(y0, dtype=float)
    ts, ys = [t], [y.copy()]
    steps = 0
    status = "completed"
    try:
        piece = model.piece_at(y)
        n_steps = int(np.ceil((t1 - t0) / dt - 1e-9))
        for i in range(n_steps):
            y = advance(piece, t, y, min(dt, t1 - t))
            t = t0 + (i + 1) * dt if i + 1 < n_steps else t1
            steps += 1
            new = model.piece_at(y)
            ev = diff_event(t, y, piece, new)
            if ev is not None:
                events.append(ev)
            piece = new
            ts.append(t)
            ys.append(y.copy())
            if progress is not None and i % 256 == 0:
                progress(t)
    except TippingError as exc:
        events.append(Event(t, "tip", tuple(map(float, y)), message=str(exc)))
        status = "tipped"
    times, states = sampled_at(np.array(ts), np.array(ys), sample_times, t, y)
    return times, states, events, status, t, steps


def sampled_at(ts: np.ndarray, ys: np.ndarray, sample_times: np.ndarray, t: float, y: np.ndarray):
    """Samples of a fixed-step run: states interpolated linearly at the sample times reached, plus the last state."""
    keep = sample_times[sample_times <= t]
    samples = np.column_stack([np.interp(keep, ts, ys[:, j]) for j in range(6)]) if len(keep) else np.zeros((0, 6))
    times = list(keep)
    states = list(samples)
    if not times or t > times[-1]:
        times.append(t)
        states.append(y)
    return np.array(times), np.array(states).reshape(-1, 6)
