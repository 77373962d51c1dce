"""The run loop: a run cut into steps, checkpointed between them and taken up again exactly where it was
(:class:`_Job`), and the constant-field run (:class:`FieldRun`). The networked runs are
:mod:`~virtual_vehicle.run.network` and :mod:`~virtual_vehicle.run.clocked`; :mod:`~virtual_vehicle.run.sim` starts
and resumes every kind.

Units: SI (s).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from virtual_vehicle import __version__
from virtual_vehicle.config.scenario import Setup
from virtual_vehicle.engine.dynamics import Trajectory, sample_grid
from virtual_vehicle.engine.plant import join, on_grid
from virtual_vehicle.errors import VirtualVehicleError
from virtual_vehicle.model.state_data import array, number
from virtual_vehicle.run.results import ParcelResult, RunResult, coulomb_sliding_check, plant_totals
from virtual_vehicle.run.tracks import _stack

class _Job:
    """A run that can be cut into steps, checkpointed between them and resumed (subclasses: :class:`FieldRun`,
    :class:`NetworkRun`). ``step`` advances and says whether a checkpoint is due; ``result`` finishes."""

    version: str
    wall: float

    @property
    def done(self) -> bool:
        raise NotImplementedError

    def step(self, every: float | None, progress) -> bool:
        raise NotImplementedError

    def result(self) -> RunResult:
        raise NotImplementedError

    def run(self, progress=None, *, checkpoint=None, checkpoint_every=None) -> RunResult:
        """Step to the end (writing checkpoints when asked) and return the result."""
        if checkpoint is not None and not (checkpoint_every and 0 < checkpoint_every < math.inf):
            raise VirtualVehicleError(f"checkpoint_every: must be a positive, finite number of simulated seconds, got "
                                      f"{checkpoint_every}")
        every = None if checkpoint is None else float(checkpoint_every)
        start = time.perf_counter()
        while not self.done:
            due = self.step(every, progress)
            if due and not self.done:
                self.wall += time.perf_counter() - start
                start = time.perf_counter()
                self.save(checkpoint, every)
        self.wall += time.perf_counter() - start
        if progress is not None:
            progress(1.0)
        return self.result()

    KIND: str
    """The run's kind as a checkpoint names it."""

    def save(self, path, checkpoint_every: float) -> None:
        """Write this run's state to ``path`` atomically (a data file, see :mod:`virtual_vehicle.run.checkpoint`), then
        go on from exactly what :func:`~virtual_vehicle.run.sim.resume` reads back from it (caches start afresh), so
        that the checkpointed run and one resumed from any of its checkpoints are the same run to the last bit."""
        from virtual_vehicle.run.files import write_atomic

        data = self.checkpoint_bytes(checkpoint_every)
        write_atomic(Path(path), data)
        # taken up as the run of its kind: the class that names it (a subclass that names none, the viewer's, too)
        kind = next(c for c in type(self).__mro__ if "KIND" in vars(c))
        fresh, _ = _load(data, {self.KIND: kind}, setup=self.setup)
        self.__dict__.update(fresh.__dict__)

    STATE: tuple[str, ...]
    """The fields that are the run's state, each written as data (arrays and plain values) by :meth:`_state` and
    read back by :meth:`_restore`. Everything else a run holds is its model (the setup, immutable), what follows
    from the setup and :meth:`_position`, or a cache made again as needed."""

    def checkpoint_bytes(self, checkpoint_every: float) -> bytes:
        """This run's checkpoint: its scenario, where it is (:meth:`_position`, plain JSON) and its state
        (:attr:`STATE` as data, :meth:`_state`, encoded by :mod:`virtual_vehicle.run.checkpoint`); never the setup
        or any cache."""
        from virtual_vehicle.run.checkpoint import FORMAT_VERSION, encode, pack

        state = self._state()
        if set(state) != set(self.STATE):
            raise AssertionError(f"the state written is not the state declared: {sorted(set(state) ^ set(self.STATE))}")
        tree, arrays = encode(state)
        document = {"format_version": FORMAT_VERSION, "package_version": __version__, "kind": self.KIND,
                    "checkpoint_every": float(checkpoint_every), "scenario": self.setup.scenario.model_dump(mode="json"),
                    "scenario_text": self.scenario_text, "setup_digest": _setup_digest(self.setup),
                    "position": self._position(), "state": tree}
        return pack(document, arrays)

    def _position(self) -> dict:
        return {}

    def _state(self) -> dict:
        """The fields of :attr:`STATE` as data, by name."""
        raise NotImplementedError

    def _restore(self, position: dict, state, arrays: list) -> None:
        """Take up a checkpoint's position and state (its document's tree and arrays) on this run, made afresh from
        the same setup; raises ValueError (or CheckpointError) for a state that does not fit it."""
        raise NotImplementedError

    def _read_state(self, state, arrays: list) -> dict:
        """The checkpoint's state tree decoded, checked to hold exactly the fields of :attr:`STATE`."""
        from virtual_vehicle.run.checkpoint import decode

        s = decode(state, arrays)
        if type(s) is not dict or set(s) != set(self.STATE):
            got = sorted(map(str, s)) if type(s) is dict else type(s).__name__
            raise ValueError(f"it holds {got}, not the state of a {self.KIND} run {sorted(self.STATE)}")
        return s


class FieldRun(_Job):
    """A constant-field run between checkpoints: the plant, every parcel's state and the pieces of trajectory so
    far."""

    KIND = "field"

    def __init__(self, setup: Setup):
        sc = setup.scenario
        self.scenario_text: str | None = None
        self.setup = setup
        self.t = 0.0
        self.wall = 0.0
        self.grid = sample_grid(0.0, sc.duration, sc.output_dt or sc.duration / 500)  # output sample times, s
        self.plant = setup.plant()
        self.ys = [y.copy() for y in setup.states]
        self.active = [True] * len(self.ys)
        self.parts: list[list[Trajectory]] = [[] for _ in self.ys]

    @property
    def done(self) -> bool:
        """True once the plant has reached the scenario's duration."""
        return self.t >= self.setup.scenario.duration

    def step(self, every, progress) -> bool:
        """Advance to the next checkpoint (or the end); True when a checkpoint is due."""
        t_end = self.setup.scenario.duration
        t0 = self.t
        t1 = t_end if every is None or t0 + every >= t_end - 1e-9 * every else t0 + every
        eps = 1e-12 * max(1.0, t1)
        inside = self.grid[np.searchsorted(self.grid, t0 + eps, side="right"):
                           np.searchsorted(self.grid, t1 - eps, side="left")]
        window = np.concatenate([[t0], inside, [t1]])  # the pieces meet at the cuts; join drops the repeats
        report = None if progress is None else (lambda t: progress(t / t_end))
        for part, tr in zip(self.parts, self.plant.advance(self.ys, self.active, self.setup.contact_velocities,
                                                           t0, t1, 0.0, report, sample_times=window)):
            if tr is not None:
                part.append(tr)
        self.t = t1
        return True

    STATE = ("t", "wall", "ys", "active", "parts", "plant")
    """The plant's time and the wall time so far (s), every parcel's state (N, 6) and whether it is still on the
    array, the pieces of trajectory so far (:meth:`Trajectory.to_data` each), the plant's state."""

    def _state(self) -> dict:
        return {"t": float(self.t), "wall": float(self.wall), "ys": _stack(self.ys),
                "active": np.array(self.active, dtype=bool), "parts": [[tr.to_data() for tr in part] for part in
                                                                        self.parts],
                "plant": self.plant.state()}

    def _restore(self, position: dict, state, arrays: list) -> None:
        s = self._read_state(state, arrays)
        N = len(self.setup.specs)
        parts = s["parts"]
        if type(parts) is not list or len(parts) != N or not all(type(p) is list for p in parts):
            raise ValueError("state.parts: not a list of pieces per parcel")
        self.parts = [[Trajectory.from_data(d, f"state.parts[{i}]") for d in part] for i, part in enumerate(parts)]
        self.t, self.wall = number(s, "t", "state"), number(s, "wall", "state")
        self.ys = [row.copy() for row in array(s, "ys", "f", (N, 6), "state")]
        self.active = array(s, "active", "b", (N,), "state").tolist()
        self.plant.restore(s["plant"])

    def result(self) -> RunResult:
        """Join the pieces into the run's :class:`RunResult` (samples on the output grid, and each parcel's last)."""
        setup = self.setup
        results = []
        for spec, part in zip(setup.specs, self.parts):
            traj = join(part)
            keep = on_grid(traj.times, self.grid)  # the output samples, wherever the checkpoints cut
            keep[-1] = True
            traj = replace(traj, times=traj.times[keep], states=traj.states[keep])
            check = coulomb_sliding_check(setup, spec, traj) if setup.law.assumes_sliding else None
            results.append(ParcelResult(spec, traj, check))
        return RunResult(setup, results, self.wall, {"plant": plant_totals(self.plant)},
                         scenario_text=self.scenario_text)


def carry_on(job: "_Job", setup: Setup) -> "_Job":
    """A run of ``setup`` (of ``job``'s own class) that takes up exactly where ``job`` is, through its checkpoint
    state: for a setup that differs from the job's only in what has not happened yet (fault events after now), as a
    viewer records a fault while the run goes on. Raises VirtualVehicleError for a state that does not fit."""
    from virtual_vehicle.run.checkpoint import CheckpointError, unpack

    document, arrays = unpack(job.checkpoint_bytes(1.0))
    fresh = type(job)(setup)
    fresh.scenario_text = job.scenario_text
    try:
        fresh._restore(document["position"], document["state"], arrays)
    except (CheckpointError, KeyError, TypeError, ValueError) as exc:
        raise VirtualVehicleError(f"the run cannot go on under the changed scenario: {exc}") from None
    return fresh


def _load(data: bytes, kinds: dict[str, type], setup: Setup | None = None,
          where: str = "checkpoint") -> tuple["_Job", float]:
    """The run a checkpoint's bytes hold and its checkpoint interval (s), made by ``kinds`` (the run's class by its
    :attr:`~_Job.KIND`; the networked ones live above this module). ``setup``: the run's own (a checkpointing
    run going on from what it wrote); None: built from the checkpoint's scenario. Raises VirtualVehicleError."""
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.checkpoint import CheckpointError, unpack

    try:
        document, arrays = unpack(data)
    except CheckpointError as exc:
        raise VirtualVehicleError(f"cannot resume {where}: {exc}") from None
    version = document.get("package_version")
    if version != __version__:
        raise VirtualVehicleError(f"cannot resume {where}: it was written by virtual_vehicle {version}; this is "
                                  f"{__version__} (resume it with {version}, or run the scenario again)")
    kind, every = document.get("kind"), document.get("checkpoint_every")
    if kind not in kinds or type(every) is not float or not 0 < every < math.inf or type(document.get("position")) is not dict:
        raise VirtualVehicleError(f"cannot resume {where}: damaged (its run kind, interval or position)")
    if setup is None:
        try:
            setup = parse_scenario(document.get("scenario")).build()
        except VirtualVehicleError as exc:
            raise VirtualVehicleError(f"cannot resume {where}: its scenario: {exc}") from None
        if document.get("setup_digest") != _setup_digest(setup):
            raise VirtualVehicleError(f"cannot resume {where}: its scenario builds another setup than the run had (a "
                                      "setup changed after it was built cannot be resumed)")
    if kind != run_kind(setup):
        raise VirtualVehicleError(f"cannot resume {where}: a {kind} run's checkpoint whose scenario is not one")
    job = kinds[kind](setup)
    text = document.get("scenario_text")
    job.scenario_text = text if type(text) is str else None
    try:
        job._restore(document["position"], document.get("state"), arrays)
    except (CheckpointError, KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError,
            RecursionError, MemoryError) as exc:
        raise VirtualVehicleError(f"cannot resume {where}: its state does not fit its scenario "
                                  f"({type(exc).__name__}: {exc})") from None
    return job, every


def _setup_digest(setup: Setup) -> str:
    """A SHA-256 of what a run's setup starts from (wheel velocities, contact positions, parcels' start states and
    bodies), so that a resume whose scenario builds another setup than the run had is refused, not run."""
    import hashlib

    h = hashlib.sha256()
    for a in (setup.velocities, setup.contact_layer.positions, np.array(setup.states, dtype=float).reshape(-1, 6),
              np.array([[s.mass, s.inertia, s.mu, s.radius] for s in setup.specs], dtype=float).reshape(-1, 4)):
        a = np.ascontiguousarray(a, dtype=float)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def run_kind(setup: Setup) -> str:
    """The kind of run (:attr:`_Job.KIND`, as its checkpoint names it) ``setup`` makes: a constant field, or cells
    on one shared clock or each on its own (a scenario with ``[control.clock]``, as
    :func:`~virtual_vehicle.run.sim.network_job` chooses)."""
    if setup.control is None:
        return FieldRun.KIND
    return "network" if setup.control.clock is None else "clocked"
