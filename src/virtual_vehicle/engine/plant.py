"""The multi-parcel plant: every parcel on the array, and parcels pushing parcels.

Units: SI (m, s, kg, N, N s, J).

:meth:`Plant.advance` moves all parcels from ``t0`` to ``t1`` under constant wheel velocities. Time is cut into windows.
In each window a parcel that cannot come within ``margin`` of any other (a rigorous bound on how far any point of it can
move, :func:`~virtual_vehicle.physics.collide.point_reach`) is integrated on its own by the single-parcel engine
(:func:`~virtual_vehicle.engine.dynamics.integrate`: event-driven, fixed-step or stick-slip, as configured), so a run
whose parcels never meet is exactly the run without this module. Parcels that might meet are grouped (connected
components) and time-stepped together at ``dt`` with the contact problem of :mod:`virtual_vehicle.physics.collide` (for
the stick-slip law the wheels' rows join the same complementarity problem; for the Coulomb and viscous laws the wheels
give each parcel its free velocity ``nu + h a``, paper eqs. 23/29 per support set).

Events of a grouped parcel (support changes, tipping) are logged at the end of the step in which they happened, as in
fixed-step mode; contacts add ``"contact"`` (two parcels started pushing each other) and ``"release"`` events.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from virtual_vehicle.engine.batch import QuietStep, QuietStepper
from virtual_vehicle.engine.glide import GlideStepper
from virtual_vehicle.engine.ride import RideStepper
from virtual_vehicle.engine.dynamics import MODES, ParcelModel, integrate_prechecked
from virtual_vehicle.engine.stepping import Event, Trajectory, diff_event, sample_grid, sampled_at
from virtual_vehicle.engine.stickslip import account, masses, new_account, remember, wheel_problem
from virtual_vehicle.errors import TippingError
from virtual_vehicle.model.layout import CellArray
from virtual_vehicle.model.parcel import ParcelSpec
from virtual_vehicle.model.state_data import array, fields, integer, number
from virtual_vehicle.physics.collide import (
    ContactParams,
    Rows,
    lever_of,
    overlap_area,
    pair_contacts,
    point_reaches,
    push_gain,
    rigid_rotation,
    solve_rows,
    wheel_frame,
    wheel_speed_of,
)
from virtual_vehicle.physics.laws import FrictionLaw, rotating_reach

_ADDITIVE = ("wheel_work", "friction_dissipation", "step_dissipation", "contact_work", "unconverged_steps",
             "chatter_steps", "mode_changes", "undecided_steps")
SUMMED_STATS = (*_ADDITIVE, "sweeps_max", "kinetic_start")
"""Trajectory stats that :func:`join` does not simply take from the last piece."""


@dataclass(frozen=True)
class Integration:
    """How single parcels are integrated (see :func:`~virtual_vehicle.engine.dynamics.integrate`) and the step ``dt``
    (s) of fixed-step, stick-slip and grouped parcels. ``batch``: in event mode (Coulomb or viscous law, no
    ``max_step``), windows proven quiet are stepped for all parcels at once (:mod:`virtual_vehicle.engine.batch`: the
    same single DOP853 step the event-driven engine would take, all in one compiled call); under the stick-slip law,
    windows in which a parcel is proven to ride its wheels rigidly are stepped for all such parcels at once in closed
    form (:mod:`virtual_vehicle.engine.ride`), and a parcel translating over one uniform field takes its window,
    catch-ups and support events included, in closed form (:mod:`virtual_vehicle.engine.glide`)."""

    mode: str = "event"
    rtol: float = 1e-10
    atol: float = 1e-12
    max_step: float = np.inf
    dt: float = 1e-3
    batch: bool = True

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be 'event' or 'fixed', got {self.mode!r}")


@dataclass
class PlantRecord:
    """What the plant counted over a run: ``parcel_contacts`` (pairs that started pushing each other),
    ``max_penetration_m`` (deepest overlap between two parcels seen at a step, m), ``undetected_overlaps``
    (window ends where two separately integrated parcels overlapped: must stay 0), ``grouped_steps`` (time steps
    taken by groups of parcels in contact range), ``unconverged_contact_steps`` (steps whose contact problem did not
    reach its tolerance within ``max_sweeps``), ``windows``, ``quiet_steps`` (parcel windows proven quiet and
    stepped together, :mod:`virtual_vehicle.engine.batch`; stick-slip parcels riding their wheels,
    :mod:`virtual_vehicle.engine.ride`)."""

    parcel_contacts: int = 0
    max_penetration_m: float = 0.0
    undetected_overlaps: int = 0
    grouped_steps: int = 0
    unconverged_contact_steps: int = 0
    windows: int = 0
    quiet_steps: int = 0
    contacts_per_parcel: list[int] = field(default_factory=list)

    _COUNTS = ("parcel_contacts", "undetected_overlaps", "grouped_steps", "unconverged_contact_steps", "windows",
               "quiet_steps")

    def to_data(self) -> dict:
        """This record as data: its counts, ``max_penetration_m`` (m) and ``contacts_per_parcel`` as an int array."""
        return {**{k: int(getattr(self, k)) for k in self._COUNTS}, "max_penetration_m": float(self.max_penetration_m),
                "contacts_per_parcel": np.array(self.contacts_per_parcel, dtype=np.int64).reshape(-1)}

    @classmethod
    def from_data(cls, d, where: str = "record") -> "PlantRecord":
        """The record :meth:`to_data` wrote; raises ValueError for data of other keys, kinds or shapes."""
        d = fields(d, (*cls._COUNTS, "max_penetration_m", "contacts_per_parcel"), where)
        depth = number(d, "max_penetration_m", where)
        per_parcel = array(d, "contacts_per_parcel", "i", (None,), where).tolist()
        return cls(**{k: integer(d, k, where) for k in cls._COUNTS}, max_penetration_m=depth,
                   contacts_per_parcel=per_parcel)


class Plant:
    """All parcels of a run on one contact layer (cells, or one contact per wheel).

    Args:
        cells: the contact layer.
        specs: the parcels.
        law: the friction law.
        gravity: m/s^2.
        integration: single-parcel integrator settings and the time step of grouped parcels.
        contact: how parcels touch each other.
    """

    def __init__(self, cells: CellArray, specs: list[ParcelSpec], law: FrictionLaw, gravity: float = 9.81,
                 integration: Integration = Integration(), contact: ContactParams = ContactParams()):
        self.cells = cells
        self.specs = list(specs)
        self.law = law
        self.gravity = gravity
        self.integration = integration
        self.contact = contact
        self._solutions: dict[float, dict] = {}  # solved supports shared by parcels of the same weight (N)
        self.base = [self._model(spec) for spec in specs]
        self.record = PlantRecord(contacts_per_parcel=[0] * len(specs))
        self._touching: set[tuple[int, int]] = set()
        self._warm: dict[tuple[int, int, int], tuple[float, float]] = {}
        self._velocities: np.ndarray | None = None
        self._models = None
        self._mu_max = [max(s.mu, s.mu_static or 0.0) for s in specs]
        self._gain = [push_gain(s) for s in specs]
        self._radius = np.array([s.radius for s in specs])
        self._quiet = None
        if (integration.batch and integration.mode == "event" and np.isinf(integration.max_step)
                and law.time_stepper is None):
            self._quiet = QuietStepper(cells, self.specs, law, self._mu_max, gravity, integration.rtol,
                                       integration.atol)
        self._ride = None  # stick-slip parcels riding their wheels rigidly: stepped together in closed form
        if (integration.batch and integration.mode == "event" and np.isinf(integration.max_step)
                and getattr(law, "modes", False)):
            self._ride = RideStepper(cells, self.specs, law, gravity)
        self._glide = None  # stick-slip parcels translating over one uniform field: their windows in closed form
        if self._ride is not None and GlideStepper.serves(cells):
            self._glide = GlideStepper(cells, self.specs, gravity)

    def state(self) -> dict:
        """What a checkpoint keeps of the plant, as data (arrays and plain values): its record
        (:meth:`PlantRecord.to_data`), the pairs of parcels pushing each other (``touching`` (m, 2)), their contacts'
        last impulses (warm starts: ``warm`` by the contacts' ``pairs`` (m, 2) of parcels and ``features`` (m, F)
        (:class:`~virtual_vehicle.physics.collide.Contact`), their ``impulses`` (m, 2) N s, in their order) and each
        parcel's stick-slip wheel memory (``memory``: per parcel the wheels' keys (m, 2) cell, wheel, last impulses
        (m,) N s and whether each stuck) and, under the stick-slip law, the riding parcels' kept proofs (``ride``:
        :meth:`~virtual_vehicle.engine.ride.RideStepper.proofs`; None under other laws): which windows ride depends on
        them. The rest is either the setup's (cells, parcels, law) or a cache made again as needed (solved supports,
        pieces, quiet anchors)."""
        memory = []
        for model in self.base:
            lam, stuck = model.contact_memory["lam"], model.contact_memory["stuck"]
            if list(lam) != list(stuck):
                raise ValueError("a parcel's wheel memory holds impulses and stuck flags of different wheels")
            memory.append({"keys": np.array(list(lam), dtype=np.int64).reshape(-1, 2),
                           "lam": np.array(list(lam.values()), dtype=np.float64),
                           "stuck": np.array(list(stuck.values()), dtype=bool)})
        return {"record": self.record.to_data(),
                "touching": np.array(sorted(self._touching), dtype=np.int64).reshape(-1, 2),
                "warm": {"pairs": np.array([key[:2] for key in self._warm], dtype=np.int64).reshape(-1, 2),
                         "features": np.array([key[2] for key in self._warm], dtype=np.int64).reshape(
                             len(self._warm), -1 if self._warm else 0),
                         "impulses": np.array(list(self._warm.values()), dtype=np.float64).reshape(-1, 2)},
                "memory": memory, "ride": None if self._ride is None else self._ride.proofs()}

    def restore(self, state: dict) -> None:
        """Take up what :meth:`state` returned (of a plant of the same scenario); raises ValueError for data of other
        keys, dtypes or shapes. What was made from other states (the models under the wheels of then, which hold the
        wheel memory replaced here, and the quiet and ride steppers' anchors) is dropped, the riding parcels' proofs
        measured again at their anchors: a plant taken back to an earlier state goes on as the plant that was there
        did."""
        where = "plant"
        state = fields(state, ("record", "touching", "warm", "memory", "ride"), where)
        record = PlantRecord.from_data(state["record"], f"{where}.record")
        warm = fields(state["warm"], ("pairs", "features", "impulses"), f"{where}.warm")
        pairs = array(warm, "pairs", "i", (None, 2), f"{where}.warm")
        features = array(warm, "features", "i", (len(pairs), None), f"{where}.warm")
        impulses = array(warm, "impulses", "f", (len(pairs), 2), f"{where}.warm")
        memory = state["memory"]
        if (type(memory) is not list or len(memory) != len(self.base)
                or len(record.contacts_per_parcel) != len(self.base)):
            raise ValueError("the plant's state is not this plant's: its parcels differ")
        self.record = record
        self._touching = set(map(tuple, array(state, "touching", "i", (None, 2), where).tolist()))
        self._warm = {(i, j, tuple(f)): tuple(lam) for (i, j), f, lam in zip(pairs.tolist(), features.tolist(),
                                                                              impulses.tolist())}
        for k, (model, m) in enumerate(zip(self.base, memory)):
            at = f"{where}.memory[{k}]"
            m = fields(m, ("keys", "lam", "stuck"), at)
            wheels = list(map(tuple, array(m, "keys", "i", (None, 2), at).tolist()))
            model.contact_memory = {"lam": dict(zip(wheels, array(m, "lam", "f", (len(wheels),), at).tolist())),
                                    "stuck": dict(zip(wheels, array(m, "stuck", "b", (len(wheels),), at).tolist()))}
        self._velocities = self._models = None  # models made before share the wheel memory replaced here
        for stepper in (self._quiet, self._ride):  # anchors measured at states of another time
            if stepper is not None:
                stepper.forget()
        if self._ride is not None:  # the riding parcels' proofs, measured again at their anchors when next used
            proofs = fields(state["ride"], ("anchors", "wheels"), f"{where}.ride")
            anchors = array(proofs, "anchors", "f", (len(self.base), 6), f"{where}.ride")
            self._ride.take_proofs(anchors, array(proofs, "wheels", "f", (len(self.base), None, 2), f"{where}.ride"))
        elif state["ride"] is not None:
            raise ValueError(f"{where}.ride: proofs of riding parcels for a plant whose law has none")

    def _model(self, spec: ParcelSpec, share: bool = True) -> ParcelModel:
        """A fresh model of parcel ``spec`` at rest wheels, sharing solved supports with parcels of its weight (or
        keeping its own, ``share=False``)."""
        store = self._solutions.setdefault(spec.weight(self.gravity), {}) if share else None
        return ParcelModel(self.cells, spec, self._at_rest, self.law, self.gravity, store)

    @cached_property
    def _at_rest(self) -> np.ndarray:
        """The contact layer's velocities at rest (n, 2), m/s, read-only: one array for every model made at rest."""
        rest = np.zeros((self.cells.n, 2))
        rest.setflags(write=False)
        return rest

    def models(self, velocities: np.ndarray) -> "_Models":
        """The parcels' models under contact-layer velocities ``velocities`` (m/s), sharing solved geometry; each is
        made when first asked for (a long run has many parcels that are not on the array)."""
        if self._velocities is None or not np.array_equal(velocities, self._velocities):
            self._velocities = np.array(velocities, dtype=float)
            self._velocities.setflags(write=False)  # the models' own, shared by them and the quiet stepper
            self._models = _Models(self.base, self._velocities)
        return self._models

    def set_present(self, present: np.ndarray | None) -> None:
        """Take contacts out of the array or put them back (reconfiguration): ``present`` is an (n,) mask over the
        contact layer (None: all present). Solved geometry stays cached (it depends only on the supports)."""
        mask = None if present is None else np.asarray(present, dtype=bool).copy()
        for model in self.base:
            model.present = mask
        for stepper in (self._quiet, self._ride):
            if stepper is not None:
                stepper.forget()
        self._velocities = self._models = None  # models made from the old base are made again

    @property
    def shared_weights(self) -> dict[float, int]:
        """The stores of solved supports the plant keeps for parcels of one weight: weight (N) -> how many support
        patterns its store holds. A store goes when :meth:`release` lets the last parcel of its weight go."""
        return {weight: len(store) for weight, store in self._solutions.items()}

    def release(self, i: int) -> None:
        """Forget what parcel ``i``'s model has cached (its own solved supports, pieces): it has left the array, and
        a long run should hold memory for the parcels on it, not for every parcel it ever carried. The supports it
        shared go when no parcel of its weight is left to share them."""
        weight = self.specs[i].weight(self.gravity)
        store = self._solutions.get(weight)
        fresh = self._model(self.specs[i], share=False)
        if store is not None and not any(m.shared_solutions is store for k, m in enumerate(self.base) if k != i):
            del self._solutions[weight]
        old = self.base[i]
        fresh.contact_memory = old.contact_memory
        fresh.present = old.present
        self.base[i] = fresh
        old.drop_table()  # (its copies share the table: freed with them now, not at a full collection)
        if self._models is not None:
            made = self._models.made.pop(i, None)
            if made is not None:
                made.drop_table()
        for stepper in (self._quiet, self._ride):
            if stepper is not None:
                stepper.forget(i)

    # -- planning ----------------------------------------------------------------------------------------------
    @cached_property
    def _lever(self) -> np.ndarray:
        return np.array([lever_of(s) for s in self.specs])

    @cached_property
    def _mu_max_arr(self) -> np.ndarray:
        return np.array(self._mu_max, dtype=float)

    @cached_property
    def _vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """Every parcel's footprint vertices in one array (body frame, m) and where each parcel's run of them
        starts (one entry more than parcels)."""
        counts = np.array([len(s.footprint) for s in self.specs])
        return np.concatenate([s.footprint for s in self.specs]), np.concatenate([[0], np.cumsum(counts)])

    def _outlines(self, live: list[int], Y: np.ndarray) -> np.ndarray:
        """The footprints of parcels ``live`` at poses ``Y`` (their rows), as shapely polygons made in one call
        (one by one took ~0.2 ms a parcel): :func:`~virtual_vehicle.physics.collide.place`'s arithmetic, vertex by
        vertex."""
        verts, start = self._vertices
        idx = np.asarray(live)
        counts = start[idx + 1] - start[idx]
        rows = np.repeat(np.arange(len(idx)), counts)
        take = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + start[idx][rows]
        v = verts[take]
        c, s = np.cos(Y[:, 2])[rows], np.sin(Y[:, 2])[rows]
        xy = np.column_stack([Y[rows, 0] + c * v[:, 0] - s * v[:, 1], Y[rows, 1] + s * v[:, 0] + c * v[:, 1]])
        return shapely.polygons(shapely.linearrings(xy, indices=rows))

    def plan(self, ys, active, velocities, t: float, t1: float, wheel_speed: float | None = None,
             rotation: tuple[np.ndarray, float, float] | None | bool = False,
             frame: tuple[np.ndarray, float] | None = None) -> tuple[float, list[list[int]]]:
        """The next window's length (s) and the groups of parcels to step together in it. When the caller knows
        them: ``wheel_speed``, the fastest of ``velocities`` (m/s); ``frame``, their
        :func:`~virtual_vehicle.physics.collide.wheel_frame`; ``rotation``, their
        :func:`~virtual_vehicle.physics.collide.rigid_rotation` (found here when False; None: no turning frame).

        No parcel can come within ``margin`` of a parcel outside its group before the window ends (bounds of
        :func:`~virtual_vehicle.physics.collide.point_reach`). Pairs that could meet within ``min_window`` are
        grouped; the window then lasts until the first moment any other pair could meet, at most ``window`` s (or,
        when no two parcels can meet before ``t1``, all the way to ``t1``).

        Work linear in parcels: candidate pairs come from a k-d tree over the centres (pairs within the largest
        footprint radius plus reach, then each pair's own), their gaps from the outlines in one vectorised call,
        and their meet times from one bisection over all of them at once (:func:`meet_times`), never a root
        finder called pair by pair. Under a law relative to its wheels (``galilean``) speeds are measured against
        the wheels' common velocity (:func:`~virtual_vehicle.physics.collide.wheel_frame`), which carries every
        parcel alike and so closes no gap: parcels riding a uniform field get whole windows. Where the wheels
        turn rigidly instead (a rotation field) and the law bounds its wheels' power in a turning frame
        (:meth:`~virtual_vehicle.physics.laws.base.FrictionLaw.frame_power`), distances are measured in the
        field's rotating frame (:func:`~virtual_vehicle.physics.laws.rotating_reach`), which also moves every
        parcel alike: parcels riding it stay put there but for the centrifugal drift a failing grip would allow.
        That frame serves a window in which no two parcels come close (no group, no push); otherwise the
        translating one is used.
        """
        live = np.flatnonzero(np.asarray(active, dtype=bool)).tolist()
        horizon = t1 - t
        if len(live) < 2:
            return horizon, []
        cp = self.contact
        Y = np.array([ys[i] for i in live], dtype=float)
        tree = cKDTree(Y[:, :2])
        radius = self._radius[live]
        lever, mu_max = self._lever[live], self._mu_max_arr[live]
        shapes = []

        def outlines():  # the footprints where they are, made once per plan (all at once) and only when needed
            if not shapes:
                shapes.append(self._outlines(live, Y))
            return shapes[0]

        H = min(horizon, cp.window)
        soon = min(cp.min_window, H)
        bounds = self._bounds(Y, live, velocities, wheel_speed, rotation, frame)
        for k, bound in enumerate(bounds):
            plan = self._plan_with(bound, live, Y, tree, radius, outlines, H, soon, horizon, k == len(bounds) - 1)
            if plan is not None:
                return plan
        raise AssertionError("the last frame always plans")  # pragma: no cover

    def _bounds(self, Y: np.ndarray, live: list[int], velocities, wheel_speed, rotation, frame) -> list[Callable]:
        """The reach bounds :meth:`plan` tries in turn, each ``bound(idx, T, floor) -> (dist, speed)`` (m, m/s)
        over the live parcels ``idx`` (positions in ``live``), windows ``T`` (s) and push floors (m/s): the field's
        rotating frame where it serves (floors must be 0 there), then the translating frame."""
        radius, lever, mu_max = self._radius[live], self._lever[live], self._mu_max_arr[live]
        V = np.asarray(velocities, dtype=float)
        bounds = []
        if self.law.galilean:  # bound motion relative to the wheels' common velocity: it moves all parcels alike
            frame, wmax = wheel_frame(V) if frame is None else frame
            if rotation is False:
                rotation = _rotation(self.cells, V, wmax)
            power = None if rotation is None else self.law.frame_power(
                mu_max * self._masses[live] * self.gravity, rotation[2])
            if power is not None:  # the turning frame is the nearer one (_rotation's test)
                centre, omega, _ = rotation
                r = Y[:, :2] - centre
                rel = Y[:, 3:5] - omega * np.column_stack([-r[:, 1], r[:, 0]])
                inv_m = 1.0 / self._masses[live]
                energy = np.sum(rel * rel, axis=1) + self._inertias[live] * inv_m * (Y[:, 5] - omega) ** 2
                rho = np.hypot(r[:, 0], r[:, 1])

                def turning(idx, T, floor):
                    if np.any(floor):
                        raise AssertionError("a push's floor has no bound in the turning frame")
                    return rotating_reach(rho[idx], energy[idx] + 2.0 * power[idx] * inv_m[idx] * T, omega,
                                          lever[idx], T)

                bounds.append(turning)
            Yr = Y.copy()
            Yr[:, 3:5] -= frame
        else:
            Yr, wmax = Y, wheel_speed_of(V) if wheel_speed is None else wheel_speed

        def translating(idx, T, floor):
            return point_reaches(radius[idx], lever[idx], Yr[idx], T, law=self.law, mu_max=mu_max[idx],
                                 gravity=self.gravity, wheel_speed=wmax, speed_floor=floor)

        return [*bounds, translating]

    @cached_property
    def _masses(self) -> np.ndarray:
        return np.array([s.mass for s in self.specs])

    @cached_property
    def _inertias(self) -> np.ndarray:
        return np.array([s.inertia for s in self.specs])

    def _plan_with(self, bound, live, Y, tree, radius, outlines, H, soon, horizon,
                   last: bool) -> tuple[float, list[list[int]]] | None:
        """:meth:`plan` under reach bound ``bound`` (one of :meth:`_bounds`); None when it is not the ``last`` and
        some pair could meet within ``soon`` (a group, whose pushes only the last bounds)."""
        cp = self.contact
        everyone = np.arange(len(live))

        def reaches(T, floor):  # the reach of every live parcel
            return bound(everyone, T, floor[live])

        def candidates(T, floor):
            reach = reaches(T, floor)[0]
            ext = radius + reach
            pairs = tree.query_pairs(2 * float(ext.max()) + cp.margin, output_type="ndarray")
            if not len(pairs):
                return pairs, np.zeros(0)
            d = np.linalg.norm(Y[pairs[:, 0], :2] - Y[pairs[:, 1], :2], axis=1)
            pairs = pairs[d < ext[pairs[:, 0]] + ext[pairs[:, 1]] + cp.margin]
            if not len(pairs):
                return pairs, np.zeros(0)
            gaps = shapely.distance(outlines()[pairs[:, 0]], outlines()[pairs[:, 1]]) - cp.margin
            keep = gaps < reach[pairs[:, 0]] + reach[pairs[:, 1]]
            return pairs[keep], gaps[keep]

        def closing(pairs, gaps, T, floor):  # how far each pair's reaches overshoot its gap in T s (m, T per pair)
            both = np.concatenate([pairs[:, 0], pairs[:, 1]])
            r = bound(both, np.concatenate([T, T]), floor[live][both])[0]
            return r[:len(pairs)] + r[len(pairs):] - gaps

        floor = np.zeros(len(self.specs))
        own = np.zeros(len(self.specs))  # fastest point speed each parcel's wheels alone can give it within H
        labels = np.arange(len(live))
        for k in range(len(live)):  # components only grow, so this ends
            close, _ = candidates(soon, floor)  # the pairs whose reaches overshoot their gap by ``soon``
            if len(close) and not last:
                return None
            if k == 0:
                own[live] = reaches(H, floor)[1]
            graph = coo_matrix((np.ones(len(close)), (close[:, 0], close[:, 1])) if len(close) else ([], ([], [])),
                               shape=(len(live), len(live)))
            new = connected_components(graph, directed=False)[1]
            if np.array_equal(new, labels):
                break
            labels = new
            # A push can make a parcel's points faster than the pusher's: each member of a group may reach its
            # gain times the fastest speed any member's wheels can give.
            fastest = np.zeros(new.max() + 1)
            np.maximum.at(fastest, new, own[live])
            sizes = np.bincount(new)
            for j, i in enumerate(live):
                floor[i] = self._gain[i] * fastest[new[j]] if sizes[new[j]] > 1 else 0.0
        # The first moment two parcels of different groups could meet: look over doubling horizons, so that only
        # the pairs that could meet within twice that moment are ever examined (over the whole window, every pair
        # of a fast-moving crowd would be).
        limit = H if len(close) else horizon  # parcels stepped together stop at H; alone, at t1 if nothing meets
        h = soon
        while True:
            pairs, gaps = candidates(h, floor)
            across = labels[pairs[:, 0]] != labels[pairs[:, 1]] if len(pairs) else np.zeros(0, dtype=bool)
            if across.any():  # each of them can meet by h, and no pair left out can
                apart, gaps_apart = pairs[across], gaps[across]
                W = min(H, meet_times(lambda sel, T: closing(apart[sel], gaps_apart[sel], T, floor), gaps_apart, h))
                break
            if h >= limit:
                W = limit
                break
            h = min(2.0 * h, limit)
        out: dict[int, list[int]] = {}
        for j, i in enumerate(live):
            out.setdefault(int(labels[j]), []).append(i)
        return W, sorted((g for g in out.values() if len(g) > 1), key=lambda g: g[0])

    # -- advancing ---------------------------------------------------------------------------------------------
    def advance(self, ys: list[np.ndarray], active: list[bool], velocities: np.ndarray, t0: float, t1: float,
                sample_dt: float, progress: Callable[[float], None] | None = None,
                sample_times: np.ndarray | None = None, trim: bool = True) -> list[Trajectory | None]:
        """Move every active parcel from ``t0`` to ``t1`` (s) under constant contact-layer ``velocities`` (m/s).

        ``ys`` and ``active`` are updated in place (a parcel that tips becomes inactive). Returns each parcel's
        :class:`Trajectory` over the interval, sampled every ``sample_dt`` s from ``t0`` (or at ``sample_times``,
        s, within the interval) and at its end (None for a parcel that was inactive at ``t0``). With ``trim=False``
        it also keeps the states where the plant restarted its integration (``t0`` among them), for a caller that
        keeps only the samples on its grid anyway (a networked run's tracks: most ticks hold no output sample, and
        trimming each parcel's trajectory cost a few microseconds a tick). Raises ValueError when an active parcel's
        state is not six finite numbers.
        """
        out, quiet = self.advance_blocks(ys, active, velocities, t0, t1, sample_dt, progress, sample_times)
        for q in quiet:
            out[q.parcel] = q.trajectory()
        if trim:
            grid = _output_grid(t0, t1, sample_dt, sample_times)
            out = [None if tr is None else _on_grid(tr, grid) for tr in out]
        return out

    def advance_blocks(self, ys: list[np.ndarray], active: list[bool], velocities: np.ndarray, t0: float, t1: float,
                       sample_dt: float, progress: Callable[[float], None] | None = None,
                       sample_times: np.ndarray | None = None) -> tuple[list[Trajectory | None], list[QuietStep]]:
        """:meth:`advance` untrimmed, with the parcels stepped only by the quiet stepper (or only riding their wheels,
        :class:`~virtual_vehicle.engine.ride.RideSteps`) left in the stepper's block: a run that goes one control tick
        at a time takes them in from there (a Trajectory per parcel and tick cost more than the step). Returns the
        trajectories, None for those parcels and the inactive ones, and a :class:`QuietStep` for each of those
        parcels (its window is ``q.trajectory()``). Arguments and errors as :meth:`advance`'s."""
        models = self.models(velocities)
        was_active = np.flatnonzero(np.asarray(active, dtype=bool)).tolist()
        if was_active:  # checked here once: the engine takes them as they are
            try:
                Y = np.array([ys[i] for i in was_active], dtype=float)
            except ValueError:  # states of different lengths
                Y = None
            if Y is None or Y.shape != (len(was_active), 6) or not np.all(np.isfinite(Y)):
                raise ValueError("the active parcels' states must be six finite numbers [x, y, theta, vx, vy, omega]")
        parts: dict[int, list[Trajectory | QuietStep]] = {i: [] for i in was_active}  # each window's, in order
        grid = _output_grid(t0, t1, sample_dt, sample_times)
        t = float(t0)
        end = t1 - 1e-12 * max(1.0, abs(t1))
        while t < end:
            W, groups = self.plan(ys, active, velocities, t, t1, models.wheel_speed,
                                  models.rotation if self.law.galilean else None,
                                  models.frame if self.law.galilean else None)
            if t + W < end and t1 - (t + W) < 1e-6 * (t1 - t):
                W = 0.5 * (t1 - t)  # never leave a sliver of an interval for the next window
            te = t1 if t + W >= end else t + W
            inside = grid[(grid > t) & (grid < te)]
            samples = np.concatenate([[t], inside, [te]])
            grouped = {i for g in groups for i in g}
            integ = self.integration
            solo = [i for i in was_active if active[i] and i not in grouped]
            rest = solo
            if self._quiet is not None:
                for i in grouped:
                    self._quiet.forget(i)
                done, rest = self._quiet.step(models, self.base, solo, ys, models.velocities, t, te, samples,
                                              models.wheel_speed)
                self.record.quiet_steps += len(done)
                if len(done):
                    last = done.last()
                    for k, i in enumerate(done.idx):  # a quiet step completes: nothing tips
                        parts[i].append(QuietStep(i, done, k))
                        ys[i] = last[k]
            if self._ride is not None:
                for i in grouped:
                    self._ride.forget(i)
                riding, rest = self._ride.step(models, rest, ys, models.velocities, t, te, samples)
                if riding is not None:  # kept as the block the closed form wrote, as the quiet stepper's are
                    self.record.quiet_steps += len(riding)
                    last = riding.last()
                    for k, i in enumerate(riding.idx):
                        parts[i].append(QuietStep(i, riding, k))
                        ys[i] = last[k]
            if self._glide is not None:
                glided, rest = self._glide.step(models, rest, ys, t, te, samples)
                for i, tr in glided.items():
                    if tr.events:
                        for stepper in (self._quiet, self._ride):  # its anchor's piece may no longer hold
                            if stepper is not None:
                                stepper.forget(i)
                    self._take(i, tr, ys, active, parts)
            for i in rest:
                known = None if self._quiet is None else self._quiet.hand_over(i, models[i], ys[i])
                tr = integrate_prechecked(models[i], ys[i], t, te, samples, mode=integ.mode, rtol=integ.rtol,
                                          atol=integ.atol, max_step=integ.max_step, dt=integ.dt,
                                          support=known)  # all checked where they come in
                if tr.events or tr.status != "completed":
                    for stepper in (self._quiet, self._ride):  # its anchor's piece may no longer hold
                        if stepper is not None:
                            stepper.forget(i)
                self._take(i, tr, ys, active, parts)
            for g in groups:
                for i, tr in self._step_group(g, models, ys, t, te, samples).items():
                    self._take(i, tr, ys, active, parts)
            self._check_overlaps(ys, active, groups)
            self.record.windows += 1
            t = te
            if progress is not None:
                progress(t)
        out: list[Trajectory | None] = [None] * len(ys)
        quiet: list[QuietStep] = []
        for i, p in parts.items():
            if len(p) == 1 and type(p[0]) is QuietStep:
                quiet.append(p[0])
            elif p:
                out[i] = join([q.trajectory() if type(q) is QuietStep else q for q in p])
        return out, quiet

    @staticmethod
    def _take(i, tr, ys, active, parts):
        parts[i].append(tr)
        ys[i] = tr.states[-1].copy()
        if tr.status == "tipped":
            active[i] = False

    def _check_overlaps(self, ys, active, groups):
        live = np.flatnonzero(np.asarray(active, dtype=bool)).tolist()
        if len(live) < 2:
            return
        group_of = {i: k for k, g in enumerate(groups) for i in g}
        centres = np.array([ys[i] for i in live])[:, :2]  # one array, then its columns: slicing each took longer
        for a, b in cKDTree(centres).query_pairs(2 * float(self._radius[live].max()), output_type="ndarray"):
            i, j = live[a], live[b]
            if group_of.get(i, -1 - i) == group_of.get(j, -2 - j):
                continue
            if overlap_area(self.specs[i], ys[i], self.specs[j], ys[j]) > 1e-12:
                self.record.undetected_overlaps += 1

    def _step_group(self, members: list[int], models, ys, t0: float, t1: float, samples: np.ndarray):
        """Time-step a group of parcels together from ``t0`` to ``t1``; returns {parcel: Trajectory}."""
        h = self.integration.dt
        cp = self.contact
        stick = self.law.time_stepper is not None  # a time-stepped law's wheels join the contact problem
        n_steps = max(1, int(np.ceil((t1 - t0) / h - 1e-9)))
        Y = {i: np.array(ys[i], dtype=float) for i in members}
        log = {i: ([t0], [Y[i].copy()], [], "completed") for i in members}
        acc = {i: new_account() for i in members}
        pieces = {}
        live = []
        for i in members:
            try:
                pieces[i] = models[i].piece_at(Y[i])
                live.append(i)
            except TippingError as exc:
                log[i][2].append(Event(t0, "tip", tuple(map(float, Y[i])), message=str(exc)))
                log[i] = (*log[i][:3], "tipped")
        t_end = {i: t0 for i in members}
        for s in range(n_steps):
            if not live:
                break
            t = t0 + s * h
            t_next = t1 if s + 1 == n_steps else t0 + (s + 1) * h
            hh = t_next - t
            slot = {i: b for b, i in enumerate(live)}
            mass = np.array([masses(self.specs[i]) for i in live])
            nu = np.array([Y[i][3:] for i in live])
            rows = Rows()
            wheels = {}
            for b, i in enumerate(live):
                if stick:
                    J, w, bounds, lam0, keys = wheel_problem(models[i], pieces[i], Y[i], hh)
                    first = len(rows)
                    for r in range(len(w)):
                        rows.box(b, J[r], w[r], bounds[r], lam0[r])
                    wheels[i] = (first, J, w, bounds, keys)
                else:
                    nu[b] = nu[b] + hh * pieces[i].rhs(t, Y[i])[3:]  # wheels alone (eqs. 23/29 per support set)
            normals = []  # (row, i, j, contact)
            near_pairs = set()
            centres = np.array([Y[i][:2] for i in live])
            radius = self._radius[live]
            near = cKDTree(centres).query_pairs(2 * float(radius.max()) + cp.margin, output_type="ndarray")
            for x, z in sorted(map(tuple, near)):
                i, j = live[x], live[z]
                if np.hypot(*(centres[x] - centres[z])) > radius[x] + radius[z] + cp.margin:
                    continue
                for c in pair_contacts(i, self.specs[i], Y[i], j, self.specs[j], Y[j], cp.margin):
                    warm = self._warm.get((c.i, c.j, c.feature), (0.0, 0.0))
                    k, _ = rows.contact(slot[c.i], slot[c.j], c, Y[c.i][:2], Y[c.j][:2], hh, cp, warm)
                    normals.append((k, c))
                    self.record.max_penetration_m = max(self.record.max_penetration_m, -c.gap)
                    if c.gap <= 0.5 * cp.margin:
                        near_pairs.add((i, j))
            pushing = set()
            if not len(rows):
                V = nu
            else:
                limits = self.law.stepper_options() if stick else cp  # the law's solver limits join the contacts'
                lam, V, sweeps, ok = solve_rows(rows, nu, 1.0 / mass, limits.max_sweeps, cp.tolerance if not stick
                                                else min(cp.tolerance, limits.tolerance))
                self.record.unconverged_contact_steps += not ok
                self._warm = {key: v for key, v in self._warm.items() if not (key[0] in slot and key[1] in slot)}
                self._warm.update({(c.i, c.j, c.feature): (float(lam[k]), float(lam[k + 1])) for k, c in normals})
                pushing = {(min(c.i, c.j), max(c.i, c.j)) for k, c in normals if lam[k] > 0}
                for b, i in enumerate(live):
                    if i in wheels:
                        first, J, w, bounds, keys = wheels[i]
                        li = lam[first:first + len(w)]
                        slip = J @ V[b] - w
                        account(acc[i], li, slip, w, V[b] - Y[i][3:], mass[b])
                        remember(models[i], keys, li, slip, w)
                        acc[i]["sweeps_max"] = max(acc[i]["sweeps_max"], sweeps)
                        acc[i]["unconverged_steps"] += not ok
                for k, c in normals:  # work of the contact impulses on each parcel over the step
                    for body, sign in ((c.i, 1.0), (c.j, -1.0)):
                        if lam[k] or lam[k + 1]:
                            r = c.point - Y[body][:2]
                            n = c.normal * sign
                            tvec = np.array([-n[1], n[0]])
                            vb = V[slot[body]]
                            vp = vb[:2] + vb[2] * np.array([-r[1], r[0]])
                            acc[body]["contact_work"] += float(lam[k] * (n @ vp) + lam[k + 1] * (tvec @ vp))
            self._contact_events(t_next, Y, pushing, near_pairs, log)
            self.record.grouped_steps += 1
            for b, i in enumerate(live):
                Y[i] = np.concatenate([Y[i][:3] + hh * V[b], V[b]])  # semi-implicit Euler
                t_end[i] = t_next
            still = []
            for i in live:
                try:
                    new = models[i].piece_at(Y[i])
                except TippingError as exc:
                    log[i][2].append(Event(t_next, "tip", tuple(map(float, Y[i])), message=str(exc)))
                    log[i] = (*log[i][:3], "tipped")
                    self._touching = {p for p in self._touching if i not in p}
                    log[i][0].append(t_next)
                    log[i][1].append(Y[i].copy())
                    continue
                ev = diff_event(t_next, Y[i], pieces[i], new)
                if ev is not None:
                    log[i][2].append(ev)
                pieces[i] = new
                log[i][0].append(t_next)
                log[i][1].append(Y[i].copy())
                still.append(i)
            live = still
        out = {}
        for i in members:
            ts, states, events, status = log[i]
            times, sampled = sampled_at(np.array(ts), np.array(states), samples, ts[-1], states[-1])
            stats = {}
            if stick:
                y0, y1 = states[0], states[-1]
                m = masses(self.specs[i])
                stats = {**acc[i], "kinetic_start": 0.5 * float(m @ y0[3:] ** 2),
                         "kinetic_end": 0.5 * float(m @ y1[3:] ** 2)}
            out[i] = Trajectory(times, sampled, events, status, t_end[i], len(ts) - 1, 0, stats)
        return out

    def _contact_events(self, t, Y, pushing, near_pairs, log):
        """Log the pairs of this group (``log``'s parcels) that started pushing each other and those that drew apart
        (gap above margin / 2)."""
        mine = {p for p in self._touching if p[0] in log and p[1] in log}
        for i, j in sorted(pushing - mine):
            self.record.parcel_contacts += 1
            for a, b in ((i, j), (j, i)):
                self.record.contacts_per_parcel[a] += 1
                log[a][2].append(Event(t, "contact", tuple(map(float, Y[a])), partner=self.specs[b].name))
        for i, j in sorted(mine - pushing - near_pairs):
            for a, b in ((i, j), (j, i)):
                log[a][2].append(Event(t, "release", tuple(map(float, Y[a])), partner=self.specs[b].name))
        self._touching = (self._touching - mine) | (mine & near_pairs) | pushing


def meet_times(closing: Callable[[np.ndarray, np.ndarray], np.ndarray], gaps: np.ndarray, H: float,
               xtol: float = 1e-9) -> float:
    """The earliest moment (s, at most ``H``) by which any of several pairs could close its gap, never later than
    it: pairs ``k`` with gap ``gaps[k]`` (m; 0 when already within reach) whose reaches overshoot the gap by
    ``closing(sel, T)`` (m) after ``T[j]`` s for the pairs ``sel[j]``, nondecreasing in T (reach bounds grow
    with time). One bisection over all pairs at once, to ``xtol`` s; a pair whose lower end passes the smallest
    upper end of any pair cannot hold the earliest meeting and drops out, so a lattice of pairs alike costs the
    same ~30 vectorised steps as one pair."""
    if np.any(gaps <= 0):
        return 0.0
    sel = np.arange(len(gaps))
    lo = np.zeros(len(gaps))
    hi = np.full(len(gaps), float(H))
    meet = closing(sel, hi) >= 0
    if not meet.any():
        return float(H)
    sel, lo, hi = sel[meet], lo[meet], hi[meet]
    while True:
        keep = lo <= hi.min()  # the others meet after some pair surely has
        sel, lo, hi = sel[keep], lo[keep], hi[keep]
        if float(np.max(hi - lo)) <= xtol:
            return float(lo.min())
        mid = 0.5 * (lo + hi)
        hit = closing(sel, mid) >= 0
        hi = np.where(hit, mid, hi)
        lo = np.where(hit, lo, mid)


class _Models:
    """Models of every parcel under one set of velocities, made on first use."""

    def __init__(self, base: list[ParcelModel], velocities: np.ndarray):
        n = base[0].cells.n if base else len(velocities)
        if velocities.dtype != float or velocities.shape != (n, 2) or not np.all(np.isfinite(velocities)):
            raise ValueError(f"velocities must be finite floats with shape ({n}, 2)")
        self.base = base
        self.velocities = velocities
        self.made: dict[int, ParcelModel] = {}

    def __getitem__(self, i: int) -> ParcelModel:
        model = self.made.get(i)
        if model is None:
            model = self.made[i] = self.base[i].with_prechecked_velocities(self.velocities)  # checked once, above
        return model

    def __len__(self) -> int:
        return len(self.base)

    @cached_property
    def wheel_speed(self) -> float:
        """The fastest contact surface speed of these velocities (m/s), found once for the planner and the quiet
        stepper (each took ~30 us over 10^4 cells a tick)."""
        return wheel_speed_of(self.velocities)

    @cached_property
    def frame(self) -> tuple[np.ndarray, float]:
        """The wheels' common velocity and their spread about it (:func:`~virtual_vehicle.physics.collide.wheel_frame`),
        found once for the planner (it took ~0.3 ms over 10^4 cells in every window)."""
        return wheel_frame(self.velocities)

    @cached_property
    def rotation(self) -> tuple[np.ndarray, float, float] | None:
        """The rigid rotation nearest these velocities that the planner would measure in (:func:`_rotation`),
        found once; None without parcels."""
        return _rotation(self.base[0].cells, self.velocities, self.frame[1]) if self.base else None


def _rotation(cells: CellArray, velocities: np.ndarray, spread: float) -> tuple[np.ndarray, float, float] | None:
    """The rigid rotation of ``velocities`` ((n, 2) m/s) over ``cells`` and the wheels' slack from it
    (:func:`~virtual_vehicle.physics.collide.rigid_rotation`) where that slack is under half the ``spread`` (m/s) of
    the wheel speeds about their common velocity (:func:`~virtual_vehicle.physics.collide.wheel_frame`), so that
    the turning frame is the nearer one; else None (a uniform field, a sorter's)."""
    if spread <= 0.0:
        return None
    return rigid_rotation(cells.positions, velocities, cells.active_directions, beyond=0.5 * spread)


def _output_grid(t0: float, t1: float, sample_dt: float, sample_times: np.ndarray | None) -> np.ndarray:
    """The output samples of :meth:`Plant.advance` (s): ``sample_times`` when given, else every ``sample_dt``."""
    return sample_grid(t0, t1, sample_dt) if sample_times is None else np.asarray(sample_times, dtype=float)


def on_grid(times: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """(len(times),) bool: which of the increasing ``times`` are points of the increasing ``grid`` (exactly)."""
    if not len(grid):
        return np.zeros(len(times), dtype=bool)
    at = np.searchsorted(grid, times)
    return (at < len(grid)) & (grid[np.minimum(at, len(grid) - 1)] == times)


def _on_grid(tr: Trajectory, grid: np.ndarray) -> Trajectory:
    """Keep the samples on the output grid and the last one (window ends are integration restarts, not output)."""
    if not len(grid):  # most control ticks hold no output sample
        return tr if len(tr.times) == 1 else Trajectory(tr.times[-1:].copy(), tr.states[-1:].copy(), tr.events,
                                                         tr.status, tr.t_end, tr.segments, tr.rhs_evals, tr.stats)
    keep = on_grid(tr.times, grid)
    keep[-1] = True
    if keep.all():
        return tr
    return Trajectory(tr.times[keep], tr.states[keep], tr.events, tr.status, tr.t_end, tr.segments, tr.rhs_evals,
                      tr.stats)


def join(segs: list[Trajectory]) -> Trajectory:
    """One trajectory from consecutive pieces (the shared instants appear once). Energy flows and solver counts add
    up; the kinetic energy at the start is the first piece's, at the end the last's."""
    if len(segs) == 1:
        return segs[0]
    times, states, events = [segs[0].times], [segs[0].states], list(segs[0].events)
    for s in segs[1:]:
        times.append(s.times[1:])
        states.append(s.states[1:])
        events.extend(s.events)
    last = segs[-1]
    return Trajectory(np.concatenate(times), np.concatenate(states), events, last.status, last.t_end,
                      sum(s.segments for s in segs), sum(s.rhs_evals for s in segs), joined_stats(segs))


def joined_stats(segs: list[Trajectory]) -> dict:
    """The stats of consecutive pieces as :func:`join` merges them."""
    stats = dict(segs[-1].stats)
    for key in _ADDITIVE:
        if any(key in s.stats for s in segs):
            stats[key] = sum(s.stats.get(key, 0) for s in segs)
    if any("sweeps_max" in s.stats for s in segs):
        stats["sweeps_max"] = max(s.stats.get("sweeps_max", 0) for s in segs)
    if "kinetic_start" in segs[0].stats:
        stats["kinetic_start"] = segs[0].stats["kinetic_start"]
    stats.pop("mode_events", None)  # one call's list: joined, its count is kept (the changes are in the events)
    return stats
