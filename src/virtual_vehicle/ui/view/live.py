"""The run under the viewer: :class:`LiveRun`, the same control tick as ``virtual-vehicle run``
(:class:`~virtual_vehicle.run.network.NetworkRun`), stepped from outside, and a record of what the viewer did to it.

A cell killed or revived is a ``[[faults.events]]`` table at the time of the next tick (a cell killed at t = 0 is
one of ``[faults] dead_cells``); a parcel dropped at an entry is a ``[[parcels]]`` table with ``t_start`` = that time.
After each such change the run is made afresh from the changed scenario and ticked up to where it was, so the run
on screen *is* the run of the scenario it writes: ``virtual-vehicle run`` of that scenario gives the same tables,
bit for bit. Units: m, s.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import shapely
from scipy.spatial import cKDTree

from virtual_vehicle.config.scenario import FaultEvent, ParcelEntry, Scenario, dump_toml, load_scenario, parse_text
from virtual_vehicle.run.jobs import carry_on
from virtual_vehicle.run.network import NetworkRun
from virtual_vehicle.run.results import RunResult
from virtual_vehicle.ui.viz import absent_cells, dead_cells, sorter_lanes

COLOUR_BY = ("traffic", "program state", "hop distance")
"""What the cells' colour can show: sentences received per tick, the program's first per-cell state word (for the
sorter: which parcel the cell carries) or the hop distance to the nearest exit (the sorter's gradients)."""
STILL = 1e-3
"""m/s: a parcel on the array slower than this is outlined as standing still."""


class _ViewedRun(NetworkRun):
    """A networked run that keeps what the page draws: the last readings and the wheel speeds held."""

    def begin(self) -> np.ndarray:
        self.readings = super().begin()
        return self.readings

    def finish(self, command, sensors, sent, received) -> np.ndarray:
        self.wheels = super().finish(command, sensors, sent, received)
        return self.wheels


class LiveRun:
    """A networked run stepped from outside, and the record of what was done to it.

    Args:
        scenario: a bundled scenario's name, a TOML path or a :class:`Scenario` with a ``[control]`` table.

    Raises ScenarioError for a scenario that does not load or build, and ValueError for one without ``[control]``.
    """

    def __init__(self, scenario: str | Path | Scenario):
        if isinstance(scenario, Scenario):
            sc, text = scenario, None
        else:
            sc, text = load_scenario(scenario)
        if sc.control is None:
            raise ValueError("the viewer steps a networked run: the scenario needs a [control] table")
        self.text = text
        self.actions: list[dict] = []
        self.wall = 0.0  # s of real time spent ticking, replays left out
        self._stands: dict[int, tuple[float, float, float]] = {}  # parcel -> (t, x, y) where its stand began
        self._make(sc, 0)

    def _make(self, sc: Scenario, k: int) -> None:
        """The run of ``sc`` made afresh and ticked ``k`` times (the ticks before a change are not changed by it)."""
        run = _ViewedRun(sc.build())
        while run.k < k and not run.done:
            run.tick()
        self._take(sc, run)

    def _take(self, sc: Scenario, run: NetworkRun) -> None:
        self.scenario, self.run = sc, run
        run.scenario_text = self.scenario_text
        self._tree = cKDTree(run.setup.cells.positions)

    # what the run is now
    @property
    def t(self) -> float:
        """Simulated time now, s (the start of the next tick)."""
        return self.run.k * self.run.period

    @property
    def done(self) -> bool:
        """True once the run has reached its end."""
        return self.run.done

    @property
    def scenario_text(self) -> str:
        """The TOML of the scenario that this run is the run of: the file given when nothing was done, else the
        changed scenario written out."""
        return self.text if not self.actions and self.text is not None else dump_toml(self.scenario)

    def dead(self) -> np.ndarray:
        """(n,) bool: cells dead from now on (including a kill or revival recorded for the next tick)."""
        return dead_cells(self.run.setup, self.t)

    def absent(self) -> np.ndarray:
        """(n,) bool: cells taken out of the array now."""
        return absent_cells(self.run.setup, self.t)

    def waiting(self) -> list[int]:
        """Parcels due on the array by now but not let on yet (their place is taken)."""
        return [i for i in self.run.queue if self.run.arrive[i] <= self.t + 1e-12]

    def delivered(self) -> int:
        """Parcels that came on and have left the array (through an exit or, lost, over an edge)."""
        return sum(1 for e, a in zip(self.run.entered, self.run.active) if e is not None and not a)

    def cell_at(self, x: float, y: float) -> int | None:
        """The cell under (x, y) m, or None when no cell centre is within half a pitch (a cell's own square)."""
        d, c = self._tree.query([x, y])
        return int(c) if d <= 0.5 * math.sqrt(2) * self.run.setup.cells.pitch else None

    def entries(self) -> list[tuple[str, np.ndarray]]:
        """The entries parcels can be dropped at: (label, outline (k, 2) m)."""
        return [(label, poly) for label, colour, poly in sorter_lanes(self.run.setup) if label.startswith("entry")]

    def exits(self) -> int:
        """How many exits the program has (destinations 0 .. exits() - 1)."""
        return sum(1 for label, colour, poly in sorter_lanes(self.run.setup) if label.startswith("exit"))

    # stepping
    def tick(self) -> None:
        """One control tick (does nothing once the run is done)."""
        if self.run.done:
            return
        start = time.perf_counter()
        self.run.tick()
        self.wall += time.perf_counter() - start

    def advance(self, sim_seconds: float, budget: float) -> None:
        """Tick until ``sim_seconds`` more of simulated time have passed or ``budget`` s of real time are spent."""
        goal = self.t + sim_seconds
        start = time.perf_counter()
        while not self.run.done and self.t + 1e-12 < goal and time.perf_counter() - start < budget:
            self.tick()

    def result(self) -> RunResult:
        """Run to the end (if not there yet) and return the run's result, its scenario text the changed scenario."""
        while not self.run.done:
            self.tick()
        self.run.wall = self.wall
        return self.run.result()

    # steering: each change is recorded in the scenario, which is then run afresh up to now
    def _change(self, sc: Scenario, action: dict, replay: bool) -> None:
        """Record ``action``: ``sc`` is the scenario with it. A fault changes nothing before it happens, so the run
        carries on under the new scenario from its own state (a checkpoint's, bit for bit); a parcel more changes
        the run's shapes, so the new scenario's run is made afresh and ticked up to now (``replay``)."""
        if self.run.done:
            raise ValueError(f"the run has ended at t = {self.t:g} s; nothing more can happen in it")
        sc = parse_text(dump_toml(sc), "the changed scenario")  # what the run folder's scenario.toml will read back
        setup = None if replay else sc.build()
        self.actions.append(action)
        try:
            if replay:
                self._make(sc, self.run.k)
            else:
                self._take(sc, carry_on(self.run, setup))
        except Exception:
            self.actions.pop()
            raise

    def toggle(self, cell: int) -> str:
        """Kill ``cell`` when it is alive, revive it when it is dead, from the next tick on; returns ``"kill"`` or
        ``"revive"``."""
        n = self.run.setup.cells.n
        if not 0 <= cell < n:
            raise ValueError(f"no cell {cell}: the array has {n}")
        kill = not self.dead()[cell]
        sc, t = self.scenario, self.t
        faults = sc.faults
        if t == 0:  # no event at t = 0: the cell is listed dead (or not) from the start
            listed = [c for c in faults.dead_cells if c != cell] + ([cell] if kill else [])
            if not kill and cell not in faults.dead_cells:
                raise ValueError(f"cell {cell} is dead from its drawn faults; it cannot be revived at t = 0")
            faults = faults.model_copy(update={"dead_cells": listed})
        else:
            event = FaultEvent(t=t, dead_cells=[cell]) if kill else FaultEvent(t=t, revived_cells=[cell])
            faults = faults.model_copy(update={"events": [*faults.events, event]})
        self._change(sc.model_copy(update={"faults": faults}),
                     {"t": t, "kind": "kill" if kill else "revive", "cell": cell}, replay=t == 0)
        return "kill" if kill else "revive"

    def drop(self, entry: int = 0, destination: int | None = 0, name: str | None = None) -> str:
        """Put a parcel on entry ``entry`` bound for exit ``destination`` now (it waits while its place is taken):
        the size, mass and friction of the scenario's first parcel, placed where the scenario's parcels arriving
        there start, else at the entry's centre. Returns its name."""
        lanes = self.entries()
        if not 0 <= entry < len(lanes):
            raise ValueError(f"no entry {entry}: the scenario has {len(lanes)}")
        if destination is not None and not 0 <= destination < max(1, self.exits()):
            raise ValueError(f"no exit {destination}: the scenario has {self.exits()}")
        sc = self.scenario
        outline = shapely.Polygon(lanes[entry][1])
        there = [p for p in sc.parcels if outline.covers(shapely.Point(p.x, p.y))]
        template = there[0] if there else sc.parcels[0] if sc.parcels else ParcelEntry(length=0.2, width=0.2, mass=1.0)
        x, y = (there[0].x, there[0].y) if there else tuple(np.asarray(outline.centroid.coords[0]))
        taken = {p.name for p in sc.parcels}
        if name is None:
            name = next(f"v{k:02d}" for k in range(len(taken) + 1) if f"v{k:02d}" not in taken)
        if name in taken:
            raise ValueError(f"a parcel is named {name!r} already")
        parcel = template.model_copy(update={"name": name, "x": float(x), "y": float(y), "theta": 0.0, "vx": 0.0,
                                             "vy": 0.0, "omega": 0.0, "t_start": self.t, "destination": destination,
                                             "sequence": None})
        self._change(sc.model_copy(update={"parcels": [*sc.parcels, parcel]}),
                     {"t": self.t, "kind": "drop", "parcel": name, "entry": entry, "destination": destination},
                     replay=True)
        return name

    def targets(self) -> dict[str, tuple] | None:
        """Each parcel's target pose now (x, y, theta; m, m, rad) by name, including one set for the next tick; None
        when the program drives parcels to no target poses."""
        ctl = self.scenario.control
        if getattr(ctl, "targets", None) is None:
            return None
        from virtual_vehicle.cells.control import targets_at
        from virtual_vehicle.cells.programs.pose import resolve_retargets

        names = [s.name for s in self.run.setup.specs]
        now = targets_at(ctl.targets, resolve_retargets(ctl, names), self.t)
        return {name: tuple(float(v) for v in pose) for name, pose in zip(names, now)}

    def retarget(self, parcel: str, target) -> None:
        """Drive ``parcel`` (its name) to ``target`` = (x, y, theta) (m, m, rad) from the next tick on: recorded as a
        ``[[control.retargets]]`` table at that time (the target itself when it is t = 0). Raises ValueError for a
        program without target poses or a parcel not in the run."""
        targets = self.targets()
        if targets is None:
            raise ValueError(f"program {self.scenario.control.program!r} drives parcels to no target poses")
        if parcel not in targets:
            raise ValueError(f"no parcel named {parcel!r}")
        pose = tuple(float(v) for v in target)
        if len(pose) != 3 or not all(map(math.isfinite, pose)):
            raise ValueError(f"a target pose is (x, y, theta), finite, not {target!r}")
        sc, ctl, t = self.scenario, self.scenario.control, self.t
        if t == 0:  # before the first tick: the scenario's own target, nothing happens at a time
            rows = list(ctl.targets)
            rows[list(targets).index(parcel)] = pose
            ctl = ctl.model_copy(update={"targets": rows})
        else:
            from virtual_vehicle.cells.programs.pose import Retarget

            ctl = ctl.model_copy(update={"retargets": [*ctl.retargets, Retarget(t=t, parcel=parcel, target=pose)]})
        self._change(sc.model_copy(update={"control": ctl}),
                     {"t": t, "kind": "target", "parcel": parcel, "target": pose}, replay=False)

    # what the page draws
    def stalls(self) -> list[dict]:
        """The stalls going on now, judged as :func:`~virtual_vehicle.cells.programs.sort.stalls` judges a finished
        run, at the times this is called (the page's frames): standing parcels whose vehicles wait on each other in
        a cycle of holds in the cells' state now (kind ``"deadlock"``,
        :func:`~virtual_vehicle.cells.programs.sort.deadlocks`), and parcels on the array whose centre has stayed
        within a quarter pitch of where it stopped for longer than the program's ``wait_bound`` (s), grouped within
        ``gap + 2`` pitches of each other (outline to outline; kind ``"waiting"``; a program that keeps no holds
        calls a group of two or more a deadlock). Each stall: ``kind``, ``parcels`` (names) and ``t_s``, when the
        last of them stopped. Empty for a program without a ``wait_bound``."""
        ctl = self.scenario.control
        bound = getattr(ctl, "wait_bound", None)
        if bound is None:
            return []
        run, pitch = self.run, self.run.setup.cells.pitch
        stands = {}
        for i in run.on:
            x, y = run.ys[i][:2]
            t0, x0, y0 = self._stands.get(i, (self.t, x, y))
            if math.hypot(x - x0, y - y0) > 0.25 * pitch:  # moved on: a new stand starts here
                t0, x0, y0 = self.t, x, y
            stands[i] = (t0, x0, y0)
        self._stands = stands
        from virtual_vehicle.cells.programs.sort import deadlocks

        specs = run.setup.specs
        found = deadlocks(getattr(run, "state", None), getattr(run, "topology", None), ctl, run.setup.cells,
                          {specs[i].name: (specs[i], run.ys[i], t0, self.t) for i, (t0, _, _) in stands.items()})
        out = [{"kind": "deadlock", "parcels": names, "t_s": t0} for names, _, t0, _ in found or []]
        inside = {n for names, *_ in found or [] for n in names}
        still = [i for i, (t0, _, _) in stands.items() if self.t - t0 > bound and specs[i].name not in inside]
        polys = [shapely.Polygon(run.setup.specs[i].world_polygon(run.ys[i]).exterior.coords) for i in still]
        reach = (getattr(ctl, "gap", 2) + 2) * pitch
        group = list(range(len(still)))

        def root(u: int) -> int:
            while group[u] != u:
                u = group[u]
            return u

        for u in range(len(still)):
            for v in range(u):
                if polys[u].distance(polys[v]) <= reach:
                    group[root(u)] = root(v)
        for g in sorted({root(u) for u in range(len(still))}):
            members = [still[u] for u in range(len(still)) if root(u) == g]
            out.append({"kind": "deadlock" if found is None and len(members) > 1 else "waiting",
                        "parcels": [run.setup.specs[i].name for i in members],
                        "t_s": max(stands[i][0] for i in members)})
        return out

    def cell_values(self, colour_by: str) -> np.ndarray | None:
        """(n,) float per cell for ``colour_by`` (:data:`COLOUR_BY`), NaN where there is none; None when the
        program keeps no such thing."""
        run, n = self.run, self.run.setup.cells.n
        if colour_by == "traffic":  # sentences received so far (the page shows their rate)
            return run.per_cell["cell_received"].astype(float)
        state = run.state
        if colour_by == "hop distance":
            dist = state.get("dist") if isinstance(state, dict) else None
            if dist is None or np.ndim(dist) != 2 or len(dist) != n:
                return None
            from virtual_vehicle.cells.sorting import UNREACHABLE

            d = np.where(np.asarray(dist) >= UNREACHABLE, np.inf, np.asarray(dist, float)).min(axis=1)
            return np.where(np.isfinite(d), d, np.nan)
        words = state.values() if isinstance(state, dict) else [state]
        for w in words:
            if isinstance(w, np.ndarray) and w.shape == (n,):
                return w.astype(float)
        return None

