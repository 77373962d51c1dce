"""Quiet windows stepped together: many separately moving parcels in one compiled call of Dormand-Prince steps.

Units: SI (m, s, kg, N, rad).

A networked run advances the plant one control tick at a time, and most ticks of most parcels are *quiet*: no cell
enters or leaves the footprint, none lifts off or touches down, and the centre of mass stays inside the supports. For
such a window the event-driven engine (:func:`~virtual_vehicle.engine.dynamics.integrate`) finds no event and takes one
DOP853 step over it, but spends most of a millisecond setting that step up. :class:`QuietStepper` proves windows quiet
and takes that same step for all quiet parcels in one call (:func:`~virtual_vehicle.engine._kernel.quiet_steps`, the
engine's own compiled step and dense output, so the states are the engine's to the last bit), with each parcel's piece
constants (:func:`~virtual_vehicle.engine.dynamics.constants_row`) as the rows of an array.

The proof is a bound, not a sample. Let ``r`` bound how far any point of a parcel can move in the window (the
planner has already ruled out pushes from other parcels). Two bounds hold, and the smaller is used:

- the friction law's alone (:func:`~virtual_vehicle.physics.collide.reach_bounds`), which also bounds every point's
  speed by ``S_max`` over the window;
- the piece's (the law's :meth:`~virtual_vehicle.physics.laws.base.FrictionLaw.piece_reach`), valid while the
  piece holds (which is what is being proven: the first moment it would stop holding comes after the window, by
  continuity). With ``k = mu g (1 + m R^2 / I)``, ``S0 = |v| + |omega| R`` now and
  ``c = S_max^2 / R`` bounding the centripetal acceleration ``omega^2 R`` and ``|omega| |v|``:

  - viscous (eq. 30): every cell under the parcel pushes with ``mu N_i u_i``, ``u_i`` its slip. The parcel's
    accelerations are at most ``k sigma`` at its rim (``sigma = max |u_i|``), and ``d sigma / dt <= k sigma + c``
    (the slip at a fixed cell changes with the parcel's acceleration and, as the parcel moves, with
    ``omega J v``). So ``r = S0 T + (sigma_0 + c / k)((e^{kT} - 1) / k - T)``: a parcel riding its wheels
    (``sigma_0`` ~ 0) reaches little further than ``S0 T``.
  - Coulomb (eqs. 20-21): the cells push with ``mu N_i F_i``, ``F_i`` fixed by the wheels' spins, so a point's
    acceleration is at most ``k max |F_i| + c``: ``r = S0 T + (k max|F_i| + c) T^2 / 2``, zero acceleration on
    stopped wheels.

At an *anchor* state the stepper measures:

- ``clear``: the smallest ``|margin|`` of any cell near the footprint (m), at most the search buffer. A margin is
  1-Lipschitz in how far the footprint points move (a cell crosses the outline only where a footprint point passes
  over it), so no cell enters or leaves while the footprint points have moved less than ``clear`` since the anchor.
- ``slack``: how far (m) the centre of mass can move before any spring force (affine in it, gradient ``G_k``) or any
  supporting half-plane changes sign: ``min(|N_k| / |G_k|, hull slack)``, less rounding noise.

Footprint points have moved at most ``P = |dX_c| + |d theta| R`` since the anchor; the window is quiet when
``slack > |dX_c| + r`` and ``clear > P + r``. Then the piece holds throughout and the motion is one smooth ODE.
Where ``clear`` is too small (a cell a millimetre behind or beside an edge), a convex footprint gets a second,
edge-by-edge look (:meth:`QuietStepper.edges_clear`): each edge moves along its normal by the velocity's component
there, give or take what acceleration and turning add, so only the edges moving toward a cell count against it. It
needs every cell that could matter in the anchor's list: ``|dX_c| + r`` below the search buffer.
Windows not proven quiet, and quiet ones whose single step fails the error test, go to the event-driven engine.
An anchor lasts while its parcel's windows stay quiet; the constants are remade when the wheel velocities under the
supports change.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from virtual_vehicle.engine import _kernel
from virtual_vehicle.engine.dynamics import ROUNDING_NOISE, ParcelModel, Trajectory
from virtual_vehicle.errors import TippingError
from virtual_vehicle.physics.collide import reach_bounds, wheel_speed_of
from virtual_vehicle.physics.contact import SupportSolution
from virtual_vehicle.physics.laws import FrictionConstants


@dataclass
class _Anchor:
    """Where a parcel's clearances were measured, and the piece that holds until they run out."""

    pose: np.ndarray  # (3,) x, y (m), theta (rad)
    clear: float  # m
    slack: float  # m
    support: np.ndarray  # cell ids
    solution: SupportSolution
    model: ParcelModel  # the parcel's model that measured it (its count of solves, shared by its copies)
    room: float = 0.0  # m: the buffer less rounding noise; cells further than radius + buffer are not in ``near``
    noise: float = 0.0  # m: rounding noise in positions
    near: np.ndarray | None = None  # convex footprint: the cells within radius + buffer (ids); else None
    halfplanes: tuple[np.ndarray, np.ndarray] | None = None  # convex footprint: its edges' normals and offsets
    constants: FrictionConstants | None = None  # the piece's, for the wheels last seen under it (None: not yet)
    row: tuple[float, ...] = ()  # and its constants row
    first: bool = False  # the solution is the first of its pattern's shared solutions (ParcelModel.solution_and_first)


def anchor(model: ParcelModel, y: np.ndarray, length: float, previous: _Anchor | None = None) -> _Anchor | None:
    """The anchor of ``model``'s parcel at state ``y``; None when it has no piece there (it tips). ``length`` (m) is
    the scale of rounding noise in positions (the array's largest coordinate, at least 1 m). ``previous``: the
    parcel's last anchor, whose solution is taken again when it lies on the same cells, was the first of its
    pattern's shared solutions and holds here: the one the pattern cache would find (a parcel measured again where
    its clearances ran out mostly does, quiet windows having kept its cells and contacts)."""
    spec, cells = model.spec, model.cells
    buffer = max(cells.pitch, 0.25 * spec.radius)
    y = np.ascontiguousarray(y, dtype=float)
    ids, margins, nearest = model.margins_near(y, spec.radius + buffer)
    support = ids[margins > 0]  # the cells under the footprint, as the event values find them
    if (previous is not None and previous.first and np.array_equal(previous.support, support)
            and previous.solution.holds(y[:2] - previous.solution.origin)):
        sol, first = previous.solution, True
    else:
        try:
            sol, first = model.solution_and_first(support, y[:2])
        except TippingError:
            return None
    length = max(length, spec.radius)
    clear = min(buffer, nearest) - ROUNDING_NOISE * length
    xi = y[:2] - sol.origin
    noise = ROUNDING_NOISE * length
    slack = _kernel.support_slack(sol.basis, sol.plane_lin, sol.plane_const, sol.spring_lin, sol.hull_normals,
                                  sol.hull_offsets, xi[0], xi[1], ROUNDING_NOISE * model.weight, noise)
    return _Anchor(np.array(y[:3], dtype=float), clear, slack, support, sol, model, room=buffer - noise, noise=noise,
                   near=ids if spec.convex else None, halfplanes=spec.halfplanes if spec.convex else None, first=first)


def _padded_row(column: np.ndarray, i: int, values: np.ndarray, fill) -> np.ndarray:
    """``column`` (a row by parcel, padded with ``fill``) with row ``i`` set to ``values``, widened first when they
    are longer than any row before (then a new array): the column."""
    m = len(values)
    if m > column.shape[1]:
        wider = np.full((len(column), m, *column.shape[2:]), fill, dtype=column.dtype)
        wider[:, :column.shape[1]] = column
        column = wider
    column[i, :m] = values
    column[i, m:] = fill
    return column


class QuietSteps:
    """Parcels stepped together over one quiet window, kept as the one block the step wrote (a networked run takes
    them in as they are; :meth:`trajectory` makes each one's :class:`~virtual_vehicle.engine.dynamics.Trajectory`).

    Attributes:
        idx: the parcels (the plant's indices), in order.
        times: (T,) the samples (s), the window's start and end among them, shared by all.
        states: (q, T, 6) read-only; parcel ``idx[k]``'s samples are ``states[rows[k]]``.
        rows: where each parcel's samples lie in ``states``.
        evals: right-hand-side evaluations each parcel's step took.
        solves: each parcel's count of solved supports when it was stepped.
    """

    __slots__ = ("idx", "times", "states", "rows", "evals", "solves")
    summed = False
    """Whether its trajectories' stats hold any of the summed stats (:data:`~virtual_vehicle.engine.plant.SUMMED_STATS`):
    a quiet step's hold the count of solves only."""

    def __init__(self, idx: list[int], times: np.ndarray, states: np.ndarray, rows: list[int], evals: int,
                 solves: list[int]):
        self.idx, self.times, self.states, self.rows, self.evals, self.solves = idx, times, states, rows, evals, solves

    def __len__(self) -> int:
        return len(self.idx)

    def trajectory(self, k: int) -> Trajectory:
        """Parcel ``idx[k]``'s trajectory over the window: one step, no events, completed."""
        return Trajectory(self.times, self.states[self.rows[k]], [], "completed", float(self.times[-1]), 1, self.evals,
                          {"solves": self.solves[k]})

    def last(self) -> np.ndarray:
        """(q, 6) each parcel's state at the window's end, a new array."""
        return self.states[self.rows, -1]


class QuietStep(NamedTuple):
    """One parcel's quiet window: parcel ``parcel`` (the plant's index) is ``steps``'s ``k``-th, its samples kept in
    that block (making its :class:`~virtual_vehicle.engine.dynamics.Trajectory` only when asked: a networked run takes
    most of them in from the block)."""

    parcel: int
    steps: QuietSteps
    k: int

    def trajectory(self) -> Trajectory:
        """The window as a trajectory: one step, no events, completed."""
        return self.steps.trajectory(self.k)


class AnchorColumns(NamedTuple):
    """The anchors' measures by parcel, as :class:`QuietStepper`'s checks read them for all parcels at once (a row
    by parcel; cell rows padded with the sentinel id ``cells.n``)."""

    support: np.ndarray
    """(parcels, k) each anchor's cells under the footprint (ids)."""
    near: np.ndarray
    """(parcels, k) a convex footprint's cells within radius + buffer of its anchor (ids), for the edge checks."""
    near_count: np.ndarray
    """(parcels,) how many of ``near``'s row are the anchor's."""
    drive: np.ndarray
    """(parcels,) the law's drive bound under each anchor's wheels (Coulomb: the largest ``|F_i|``), 0 until made."""
    made: np.ndarray
    """(parcels,) the :attr:`QuietStepper.changes` count after which each anchor's constants were made (-1: not yet;
    the checks make them)."""


class QuietStepper:
    """Steps the quiet windows of separately moving parcels together (see the module docstring).

    Args:
        cells: the contact layer.
        specs: every parcel of the plant.
        law: the friction law (event-driven).
        mu_max: each parcel's largest friction coefficient.
        gravity: m/s^2.
        rtol, atol: the event-driven engine's tolerances, applied to the single step exactly as it applies them.
    """

    def __init__(self, cells, specs, law, mu_max, gravity: float, rtol: float, atol: float):
        self.cells = cells
        self.length = max(1.0, cells.extent)
        self.law = law
        self.gravity = gravity
        self.rtol, self.atol = rtol, atol
        self.radius = np.array([s.radius for s in specs])
        self.lever = np.array([1.0 + s.mass * s.radius ** 2 / s.inertia for s in specs])  # 1 + m R^2 / I
        self.lever_mu = np.asarray(mu_max, dtype=float) * self.lever
        self.anchors: dict[int, _Anchor] = {}
        self._columns(len(specs))

    def _columns(self, n: int) -> None:
        """The anchors' measures as columns by parcel (``n`` parcels), which the checks read for all parcels at once
        (lists of ~200 anchors' attributes took ~0.2 ms a tick), and when the wheels under each last changed."""
        self._pose = np.zeros((n, 3))  # each anchor's pose, clearance, slack, room, Coulomb drive, convexity
        self._clear, self._slack, self._room, self._drive = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        self._convex = np.zeros(n, dtype=bool)
        self._support = np.zeros((n, 0), dtype=np.int64)  # each anchor's cells, padded with the sentinel cell
        # convex footprints, for the edge-by-edge checks of many parcels in one call: the cells within radius +
        # buffer of the anchor (padded likewise) and how many; each parcel's half-planes (body frame, padded) and
        # how many (0: not yet written), and its rounding noise in positions (m)
        self._near = np.zeros((n, 0), dtype=np.int64)
        self._near_count = np.zeros(n, dtype=np.int64)
        self._edge_normals, self._edge_offsets = np.zeros((n, 0, 2)), np.zeros((n, 0))
        self._edge_count = np.zeros(n, dtype=np.int64)
        self._noise = np.zeros(n)
        self._made = np.full(n, -1, dtype=np.int64)  # the wheel change its row was made after (-1: none yet)
        self._rows = np.zeros((n, 0))  # each anchor's piece's constants row (dynamics.constants_row)
        self._changes = 0  # wheel changes seen: each tick whose velocities differ from the last seen
        self._changed_at = np.zeros(self.cells.n + 1, dtype=np.int64)  # each cell's latest; the last, a sentinel
        self._changed_at[-1] = -1
        self._seen: np.ndarray | None = None  # the velocities last seen

    @property
    def columns(self) -> AnchorColumns:
        """The anchors' measures as the checks read them, by parcel (read-only views)."""
        def frozen(a: np.ndarray) -> np.ndarray:
            v = a.view()
            v.setflags(write=False)
            return v

        return AnchorColumns(*(frozen(a) for a in (self._support, self._near, self._near_count, self._drive,
                                                    self._made)))

    @property
    def changes(self) -> int:
        """How many times the wheel velocities shown to :meth:`see` changed (the first showing counts as one)."""
        return self._changes

    @property
    def changed_at(self) -> np.ndarray:
        """(cells + 1,) read-only: the :attr:`changes` count at which each cell's wheels last changed; the last entry,
        the sentinel cell's that pads the columns, stays -1."""
        v = self._changed_at.view()
        v.setflags(write=False)
        return v

    @property
    def seen(self) -> np.ndarray | None:
        """The wheel velocities (m/s) last seen: a read-only array as it was given, else a copy; None before any."""
        return self._seen

    def forget(self, i: int | None = None) -> None:
        """Drop parcel ``i``'s anchor (all anchors when None): it was moved another way, or the array changed."""
        if i is None:
            self.anchors.clear()
        else:
            self.anchors.pop(i, None)

    def measure(self, i, models, y) -> _Anchor | None:
        """Measure parcel ``i``'s anchor at state ``y`` (``models[i]`` its model; :func:`anchor`) and keep it in
        :attr:`anchors` and the columns; None (and no anchor) when the parcel tips there. Measured again on the same
        cells and solved pattern, the anchor keeps the constants made for them (and their drive)."""
        old = self.anchors.get(i)
        a = anchor(models[i], y, self.length, old)
        if a is None:
            self.anchors.pop(i, None)
            return None
        self.anchors[i] = a
        if (old is not None and old.constants is not None and old.solution.force_lin is a.solution.force_lin
                and np.array_equal(old.support, a.support)):
            # measured again on the same cells and the same solved pattern (so the same origin): the constants
            # stand while the wheels under them turn as they did (the stamps tell), and are not remade
            a.constants, a.row = old.constants, old.row  # (and the column keeps the Coulomb drive they make)
        else:
            self._made[i], self._drive[i] = -1, 0.0  # none yet: the checks make them
        self._pose[i] = a.pose
        self._clear[i], self._slack[i], self._room[i] = a.clear, a.slack, a.room
        self._convex[i] = a.halfplanes is not None
        self._support = _padded_row(self._support, i, a.support, self.cells.n)
        if a.near is not None:
            self._near = _padded_row(self._near, i, a.near, self.cells.n)
            self._near_count[i] = len(a.near)
            if not self._edge_count[i]:  # the parcel's own outline and scale: written once
                normals, offsets = a.halfplanes
                self._edge_normals = _padded_row(self._edge_normals, i, normals, 0.0)
                self._edge_offsets = _padded_row(self._edge_offsets, i, offsets, 0.0)
                self._edge_count[i], self._noise[i] = len(offsets), a.noise
        return a

    def hand_over(self, i: int, model: ParcelModel, y: np.ndarray | None = None) -> np.ndarray | None:
        """Give ``model`` (parcel ``i``'s, under the wheels last seen) its anchor's piece, when the anchor's constants
        are those of these wheels (the checks remake them first): the support, solution and constants the event
        engine would find for those cells, which it then looks up as it looks up its own pieces (by the cells, and
        only where the solution holds) instead of making it again. Returns the anchor's cells when it was measured
        at state ``y``'s very pose (most parcels the checks turn away are measured again where they are): the cells
        :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.support_at` finds there, which the engine then need not find
        again; else None."""
        a = self.anchors.get(i)
        if a is None:
            return None
        if a.constants is not None and self._changed_at[self._support[i]].max() <= self._made[i]:
            model.adopt(a.support, a.solution, a.constants, a.row)
        return a.support if y is not None and a.pose.tolist() == y[:3].tolist() else None

    def see(self, velocities: np.ndarray) -> None:
        """Note the cells whose wheel velocities differ from those last seen (all of them the first time). A
        read-only array is kept as it is (a plant's, the same object while its wheels stay: nothing to compare);
        any other is copied."""
        seen = self._seen
        if velocities is seen and not seen.flags.writeable:
            return
        if seen is not None and seen.shape == velocities.shape:
            # each cell's two velocities as one complex number: one comparison a cell (equal iff both are)
            now = np.ascontiguousarray(velocities, dtype=np.float64)
            diff = now.view(np.complex128)[:, 0] != seen.view(np.complex128)[:, 0]
            changed = bool(diff.any())
        else:
            diff, changed = slice(None), True
        if changed:
            self._changes += 1
            self._changed_at[:-1][diff] = self._changes
        if not velocities.flags.writeable and velocities.flags.c_contiguous and velocities.dtype == np.float64:
            self._seen = velocities
        elif changed:
            self._seen = np.array(velocities, dtype=float)

    def refresh(self, i, a: _Anchor, base, velocities) -> None:
        """Remake parcel ``i``'s anchor ``a``'s constants (and the law's drive bound) for the wheels ``velocities``
        (m/s) under it now, from its model ``base[i]``; the checks do this when the wheels under it changed."""
        v = velocities[a.support]
        model = base[i]
        self._made[i] = self._changes
        a.constants, a.row = model.constants_and_row(a.support, a.solution, v)
        row = a.row
        if self._rows.shape[1] != len(row):  # made at the first refresh: the row's length is the law's
            self._rows = np.zeros((len(self._rows), len(row)))
        self._rows[i] = row
        self._drive[i] = self.law.drive_bound(v, self.cells.active_directions[a.support])  # Coulomb: max |F_i|

    def reach(self, idx, Y: np.ndarray, window: float, velocities: np.ndarray,
              wheel_speed: float) -> tuple[np.ndarray, np.ndarray]:
        """How far (m) any point of each parcel ``idx`` (states ``Y``, pieces of their anchors) can move in
        ``window`` s while its piece holds: the smaller of the law's bound and the piece's (module docstring). Also
        returns the part of the piece's bound that acceleration adds to ``S0 T`` (m; inf on line arrays): the double
        integral of the rim acceleration bound ``|a| + |alpha| R <= k sigma`` (viscous; ``k max|F_i|`` Coulomb),
        of which ``|a|`` takes at most the share ``1 / (1 + m R^2 / I)`` and ``|alpha| R`` the rest."""
        R = self.radius[idx]
        k = self.lever_mu[idx] * self.gravity
        s0 = np.hypot(Y[:, 3], Y[:, 4]) + np.abs(Y[:, 5]) * R
        r_law, s_max = reach_bounds(s0, self.lever_mu[idx], window, law=self.law, gravity=self.gravity,
                                    wheel_speed=wheel_speed, lever=self.lever[idx])
        if self.cells.is_line:  # a row may hold the parcel laterally: the law's bound only
            return r_law, np.full(len(idx), np.inf)
        c = s_max * s_max / R

        def slip():  # the largest slip speed (m/s) under each parcel now, for a law whose bound reads it
            ids = self._support[idx]  # (parcels, cells), padded with the sentinel cell: read as any, then masked
            arm = np.take(self.cells.positions, ids, axis=0, mode="clip") - Y[:, None, :2]
            spin = Y[:, 5, None]
            v = np.take(velocities, ids, axis=0, mode="clip")
            slips = np.hypot(v[..., 0] - Y[:, 3, None] + spin * arm[..., 1],
                             v[..., 1] - Y[:, 4, None] - spin * arm[..., 0])
            return np.where(ids < self.cells.n, slips, 0.0).max(axis=1, initial=0.0)

        accel = self.law.piece_reach(k, window, c, self._drive[idx], slip)
        return np.minimum(r_law, s0 * window + accel), accel

    def _check(self, idx, ks, Y, anchors, window, base, velocities, wheel_speed) -> np.ndarray:
        """Which of the parcels ``idx[k]`` for k in ``ks`` are proven quiet (False without an anchor), their
        constants brought up to date with ``velocities`` first."""
        ok = np.zeros(len(ks), dtype=bool)
        have = [n for n, k in enumerate(ks) if anchors[k] is not None]
        if not have:
            return ok
        sel = ks[have]
        parcels = np.asarray(idx)[sel]
        changed = self._changed_at[self._support[parcels]].max(axis=1) > self._made[parcels]
        for n in np.flatnonzero(changed):  # the wheels under it changed (or it is new): remake its constants
            self.refresh(idx[sel[n]], anchors[sel[n]], base, velocities)
        ok[have] = self._quiet(parcels, Y[sel], window, velocities, wheel_speed)
        return ok

    def _quiet(self, idx, Y, window, velocities, wheel_speed) -> np.ndarray:
        """Which of the parcels ``idx`` (an array) at states ``Y`` are proven quiet for ``window`` s from their
        anchors (as the columns keep them)."""
        R = self.radius[idx]
        P0 = self._pose[idx]  # the anchors' measures, as _anchor keeps them
        moved = np.hypot(Y[:, 0] - P0[:, 0], Y[:, 1] - P0[:, 1])
        swept = moved + np.abs(Y[:, 2] - P0[:, 2]) * R
        r, accel = self.reach(idx, Y, window, velocities, wheel_speed)
        held = self._slack[idx] > moved + r
        cells_clear = self._clear[idx] > swept + r
        look = np.flatnonzero(held & ~cells_clear & (moved + r < self._room[idx]) & np.isfinite(accel)
                              & self._convex[idx])
        if len(look):  # too near some cell for one radius: ask which way each edge moves
            cells_clear[look] = self.edges_clear(idx[look], Y[look], window, r[look], accel[look], R[look],
                                                 self.lever[idx[look]])
        return held & cells_clear

    def edges_clear(self, idx, Y, window, r, accel, R, lever) -> np.ndarray:
        """Whether no cell near each convex parcel ``idx`` (an array; anchored, as the columns keep them) can cross
        its outline in ``window`` s, edge by edge.

        A cell ``p`` has margin ``h_e = b_e - N_e . (p - X)`` against edge e (world outward normal ``N_e``, offset
        ``b_e``); it is inside iff every ``h_e > 0``. Moving by ``dX`` and turning by ``dtheta`` changes ``h_e`` by
        ``N_e . dX - (N_e' - N_e) . (p - X')``, and ``|N_e' - N_e| <= |dtheta|``. Over the window ``N_e . dX`` lies
        within ``A = accel / (1 + m R^2 / I)`` of ``N_e . v t``, ``|dtheta| <= |omega| T + (accel - A) / R`` and
        ``|dX| <= min(r, |v| T + A)`` (:meth:`reach`: |a| bounded by mu g sigma, |alpha| by mu m g sigma R / I,
        eq. 30; the same with ``max|F_i|`` for eq. 21). So with ``B = A + |dtheta| (|p - X| + |dX|)``, every
        ``h_e`` stays above ``h_e + min(0, N_e . v T) - B`` and below ``h_e + max(0, N_e . v T) + B``: the cell
        stays inside if the smallest lower bound is positive, outside if the smallest upper bound is negative (an
        edge it stays beyond). Unlike the one-radius clearance, this lets a parcel run past cells just behind or
        beside it."""
        return _kernel.edges_clear_many(self.cells.positions, self._near[idx], self._near_count[idx],
                                        self._edge_normals[idx], self._edge_offsets[idx], self._edge_count[idx],
                                        np.ascontiguousarray(Y), window, r, accel, R, lever, self._noise[idx])

    def compile_checks(self, model: ParcelModel, y: np.ndarray) -> None:
        """Compile (or load from numba's cache) the compiled checks :meth:`step` runs, with the argument types it
        gives them, at a time of the caller's choosing: anchor parcel 0 (``model``'s) at state ``y`` and ask its
        edges whether the cells stay clear of them for 10 ms (the branch a step takes only near cells)."""
        self.measure(0, [model], y)
        self.edges_clear(np.zeros(1, dtype=np.int64), y[None], 0.01, np.zeros(1), np.zeros(1), self.radius,
                         self.lever)

    def step(self, models, base, idx: list[int], ys, velocities: np.ndarray, t: float, te: float,
             samples: np.ndarray, wheel_speed: float | None = None) -> tuple[QuietSteps, list[int]]:
        """Advance the parcels ``idx`` (states ``ys[i]``, no other parcel within reach) from ``t`` to ``te`` (s) under
        contact-layer ``velocities`` (m/s): returns those stepped here (sampled at ``samples``, the window's ends among
        them) and the parcels left for the event-driven engine. ``models[i]`` is parcel i's model under these velocities
        (asked for only to make an anchor), ``base[i]`` any model of it (for the friction constants). ``wheel_speed``:
        the fastest of ``velocities`` (m/s, :func:`~virtual_vehicle.physics.collide.wheel_speed_of`), when the caller
        knows it."""
        times = np.concatenate([[t], samples[(samples > t) & (samples < te)], [te]])
        if not idx:
            return QuietSteps([], times, np.empty((0, len(times), 6)), [], 0, []), []
        window = te - t
        if wheel_speed is None:
            wheel_speed = wheel_speed_of(velocities)
        Y = np.array([ys[i] for i in idx], dtype=float)
        Y = np.where(np.abs(Y) < 1e-100, 0.0, Y)  # as integrate() does
        self.see(velocities)
        anchors = [self.anchors.get(i) for i in idx]
        for k, i in enumerate(idx):
            if anchors[k] is None:
                anchors[k] = self.measure(i, models, Y[k])
        ok = self._check(idx, np.arange(len(idx)), Y, anchors, window, base, velocities, wheel_speed)
        failed = np.flatnonzero(~ok)
        moved = failed[(self._pose[np.asarray(idx)[failed]] != Y[failed, :3]).any(axis=1)].tolist()
        stale = [k for k in moved if anchors[k] is not None]
        for k in stale:  # an old anchor may have run out: measure again where the parcel is
            anchors[k] = self.measure(idx[k], models, Y[k])
        if stale:
            ok[stale] = self._check(idx, np.array(stale), Y, anchors, window, base, velocities, wheel_speed)
        quiet = np.flatnonzero(ok)
        rest = [idx[k] for k in np.flatnonzero(~ok)]
        states = np.empty((len(quiet), len(times), 6))  # each parcel's samples are a view of it
        if not len(quiet):
            return QuietSteps([], times, states, [], 0, []), rest
        accepted, evals = _kernel.quiet_steps(self._rows[np.asarray(idx)[quiet]], Y[quiet], t, te, self.rtol,
                                              self.atol, times, states)
        for shared in (states, times):
            shared.setflags(write=False)  # one array behind many trajectories
        rows = np.flatnonzero(accepted).tolist()
        rest.extend(idx[k] for k in quiet[~accepted].tolist())
        kept = quiet[rows].tolist()
        return QuietSteps([idx[k] for k in kept], times, states, rows, evals,
                          [anchors[k].model.solves for k in kept]), rest

