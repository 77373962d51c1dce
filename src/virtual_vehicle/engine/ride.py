"""Parcels riding their wheels rigidly, stepped together in closed form (the stick-slip law's quiet windows).

Units: SI (m, s, kg, N, N m, rad).

Under the stick-slip law a parcel whose every wheel in contact sticks, on wheels whose surface speeds are one rigid
twist of the plane (a constant aisle field; a turn block commanding a rigid rotation), moves exactly with that twist
while its support set and its grip hold: the sticking wheels are three or more independent constraints that fix the
twist (:mod:`virtual_vehicle.physics.stick_modes`), and the field's material velocity at every fixed cell stays the
wheel's. So the motion is a rotation at the field's ``omega`` about its centre (a translation when ``omega`` is 0),
and the only events it can meet are support events and the grip breaking. The event-driven engine integrates this
mode by DOP853 every control tick; :class:`RideStepper` proves a window has none of those events and writes the
closed form for all such parcels in one vectorised call. Every other window keeps the event-driven path.

The wheels are held constant over a control tick (zero-order hold: a motor wheel is given the plant at its mean
speed over the tick, :meth:`~virtual_vehicle.run.network.TickedRun.finish`), so the twist the wheels make is constant
over a window; a window whose wheels are not one rigid twist (a ramp that is not common to all of them included) is
not a ride. A parcel's proof is kept from the anchor it was measured at (its pose and state, twist, cells, grip and
the wheel velocities under those cells): a window checks only that those wheels are unchanged and that the margins
below still hold for the motion since the anchor (a few vector operations for all parcels), and measures the proof
again where the parcel is when they do not. The windows a run rides then depend on its anchors, so the kept proofs
are run state (:meth:`RideStepper.proofs`, written in a checkpoint): a resumed run measures them again at their
anchors and rides the same windows, to the last bit.

The proof for a window of ``T`` s, from the parcel's anchor (:mod:`virtual_vehicle.engine.batch`: its clearance
``clear``, support ``slack`` and, where needed, the edge-by-edge look), with the parcel's twist that of the field:

- no cell enters or leaves and no support force changes sign: every point of the parcel moves at most its point
  speed bound ``S0 = |v| + |omega| R`` times ``T`` (``r = S0 T`` exactly: the speeds are constant in a rigid
  motion) and the centre of mass at most ``d = |v| T``;
- the grip holds: the wrench the sticking wheels must supply is that of the motion's acceleration, zero in
  translation and the centripetal force ``F = m omega x v`` (size ``m |omega| |v|``, constant; no torque about the
  centre) in rotation (eqs. 3-19 give the normal forces, the per-wheel Coulomb bound ``mu_s N`` of eqs. 20-22 the
  zonotope). It must lie in the sticking wheels' zonotope, tested against the facets measured at the anchor
  (:func:`~virtual_vehicle.physics.stick_modes.zonotope_grip`: ``g`` along the anchor's force direction ``d0``,
  ``a`` for other directions, ``b`` for torque). With ``D`` the centre's distance from the anchor by the window's
  end and ``s`` the anchor's slack, every normal force (affine in the centre, eq. 19, and positive for ``s`` more)
  stays above ``(1 - D / s)`` times the anchor's, so the zonotope holds ``(1 - D / s)`` times the anchor's; the
  levers ``r x u`` all move by the same ``-Delta x u`` when the centre moves by ``Delta``, which is the anchor's
  zonotope with the wrench taken about the anchor's centre instead: ``(F, Delta x F)``, ``|Delta| <= D``. ``F``'s
  direction ``d`` turns by at most ``|omega| T`` in the window. So the grip holds while
  ``m |omega| |v| (g + a (|d - d0| + |omega| T) + b D) < 1 - D / s``: exact (the facet test) at the anchor as
  ``D, T -> 0``. (The zonotope's inradius, used before, is set by its torque facets (N m): about a tenth of
  ``mu_s`` times the weight on 0.1 m cells, ten times below what a pure force can have.)

The parcel's twist must be the field's (its slip on every wheel below the engine's slip tolerance); the closed form
then carries the field's twist itself, as the event-driven engine does when it projects the twist onto the sticking
wheels' constraints. The energy account of such a window is zero wheel work and zero dissipation: the stick forces'
power is the wrench times the twist, ``m (omega x v) . v = 0``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from virtual_vehicle.engine import _kernel
from virtual_vehicle.engine.batch import QuietStepper, QuietSteps, _padded_row
from virtual_vehicle.engine.dynamics import ROUNDING_NOISE
from virtual_vehicle.engine.stepping import Trajectory
from virtual_vehicle.model.parcel import ALL_PRESENT, _within

RIDE_TOL = 1e-10
"""A parcel rides the field when its twist differs from the field's by less than this, relative to the speed scale
(each wheel's slip then is too: a tenth of the engine's tolerance for zero slip)."""


def rigid_motion(Y: np.ndarray, times: np.ndarray, t: float) -> np.ndarray:
    """States (q, T, 6) of parcels at states ``Y`` (q, 6) at time ``t`` (s) moving rigidly with their twists, sampled
    at ``times`` (T,): each turns at its constant ``omega`` (rad/s) about its centre of rotation, its velocity turning
    with it (a translation when ``omega`` is 0). ``sin(a) / a`` and ``(1 - cos a) / a`` are taken by their series
    where ``a = omega tau`` is small, so the translation is the limit, not a division by zero."""
    tau = (np.asarray(times, dtype=float) - t)[None, :]  # (1, T)
    w = Y[:, 5, None]
    a = w * tau
    small = np.abs(a) < 1e-4
    safe = np.where(small, 1.0, a)
    s_over = np.where(small, 1.0 - a * a / 6.0, np.sin(safe) / safe)  # sin(a) / a
    c_over = np.where(small, a / 2.0 - a ** 3 / 24.0, (1.0 - np.cos(safe)) / safe)  # (1 - cos a) / a
    vx, vy = Y[:, 3, None], Y[:, 4, None]
    out = np.empty((len(Y), tau.shape[1], 6))
    # X(tau) = X + (sin a / omega) v + ((1 - cos a) / omega) (omega-hat x v), the arc of the rigid twist
    out[..., 0] = Y[:, 0, None] + tau * (s_over * vx - c_over * vy)
    out[..., 1] = Y[:, 1, None] + tau * (s_over * vy + c_over * vx)
    out[..., 2] = Y[:, 2, None] + a
    cos_a, sin_a = np.cos(a), np.sin(a)
    out[..., 3] = cos_a * vx - sin_a * vy  # the velocity turns with the body
    out[..., 4] = sin_a * vx + cos_a * vy
    out[..., 5] = w
    out[:, 0] = Y  # the window's start exactly
    return out


@njit(cache=True)
def slipping_under(points, order, start, lo0, lo1, size, nx, ny, present, active, directions, V, Y, inner, out):
    """Whether each parcel at state ``Y[k]`` (x, y, theta m m rad, vx, vy m/s, omega rad/s) slips on a wheel of a
    cell certainly under it (its centre within ``inner[k]`` m of the parcel's centre: the footprint's inradius,
    0 for none) by more than a millionth of the speed scale, into ``out``: such a parcel does not ride its wheels
    (every wheel in contact must stick, to 1e-10 of the speed scale), so measuring its proof would be wasted. The
    grid's arrays as :func:`~virtual_vehicle.model.parcel._within` takes them; ``active`` (n, 2), ``directions``
    (n, 2, 2) and ``V`` (n, 2) m/s the contact layer's wheels and velocities."""
    for k in range(Y.shape[0]):
        out[k] = False
        if not inner[k] > 0.0:
            continue
        x, y, vx, vy, om = Y[k, 0], Y[k, 1], Y[k, 3], Y[k, 4], Y[k, 5]
        ids = _within(points, order, start, lo0, lo1, size, nx, ny, present, x, y, inner[k])
        for c in range(ids.shape[0]):
            i = ids[c]
            px, py = vx - om * (points[i, 1] - y), vy + om * (points[i, 0] - x)  # the parcel's velocity there
            dx, dy = px - V[i, 0], py - V[i, 1]
            scale = 1e-6 * max(1e-3, abs(px) + abs(py), abs(V[i, 0]) + abs(V[i, 1]))
            for w in range(2):
                if active[i, w] and abs(dx * directions[i, w, 0] + dy * directions[i, w, 1]) > scale:
                    out[k] = True
            if out[k]:
                break
    return out


@njit(cache=True)
def cells_change(points, order, start, lo0, lo1, size, nx, ny, present, kind, half, normals, offsets, n_edges,
                 vertices, n_vertices, radius, Y, Y_end, out):
    """Whether the cells under each parcel (footprint margin > 0, of the cells ``present``) at state ``Y[k]`` differ
    from those under it at ``Y_end[k]``, into ``out``: a parcel moving from one to the other has a support event
    on the way, so it does not ride the window and measuring its proof would be wasted (a proof that holds keeps
    every cell off the footprint's edges all the way). The grid's arrays as
    :func:`~virtual_vehicle.model.parcel._within` takes them; each parcel's outline as the stepper's columns hold
    it (:func:`~virtual_vehicle.engine._kernel.outline`) and its ``radius`` (m): a cell under it at either state lies
    within that of its centre there."""
    for k in range(Y.shape[0]):
        out[k] = False
        ne, nv = n_edges[k], n_vertices[k]
        for y in (Y[k], Y_end[k]):
            ids = _within(points, order, start, lo0, lo1, size, nx, ny, present, y[0], y[1], radius[k])
            at = points[ids]
            a = _kernel.cell_margins(kind[k], half[k], normals[k, :ne], offsets[k, :ne], vertices[k, :nv], at,
                                     Y[k])[0]
            b = _kernel.cell_margins(kind[k], half[k], normals[k, :ne], offsets[k, :ne], vertices[k, :nv], at,
                                     Y_end[k])[0]
            for c in range(ids.shape[0]):
                if (a[c] > 0.0) != (b[c] > 0.0):
                    out[k] = True
                    break
            if out[k]:
                break
    return out


class RideSteps(QuietSteps):
    """The windows of parcels that rode their wheels over one window, kept as the one block the closed form wrote
    (a networked run takes them in as they are; :meth:`trajectory` makes each one's
    :class:`~virtual_vehicle.engine.dynamics.Trajectory` only when asked). As :class:`QuietSteps`, with each parcel's
    state before its twist was made the field's (``start``, (q, 6)), mass (kg), inertia (kg m^2) and count of cached
    pieces when it was stepped, from which its stats are made: zero wheel work and dissipation, its kinetic energy
    at both ends (J)."""

    __slots__ = ("start", "mass", "inertia", "pieces")
    summed = True

    def __init__(self, idx: list[int], times: np.ndarray, states: np.ndarray, start: np.ndarray, mass: np.ndarray,
                 inertia: np.ndarray, pieces: list[int], solves: list[int]):
        super().__init__(idx, times, states, np.arange(len(idx)), 0, solves)
        self.start, self.mass, self.inertia, self.pieces = start, mass, inertia, pieces

    def trajectory(self, k: int) -> Trajectory:
        """Parcel ``idx[k]``'s ride over the window: one closed-form step, no events, completed."""
        y0, y1 = self.start[k], self.states[k, -1]
        mass, inertia = self.mass[k], self.inertia[k]
        stats = {"wheel_work": 0.0, "friction_dissipation": 0.0, "step_dissipation": 0.0, "contact_work": 0.0,
                 "sweeps_max": 0, "unconverged_steps": 0,
                 "kinetic_start": 0.5 * float(mass * (y0[3] ** 2 + y0[4] ** 2) + inertia * y0[5] ** 2),
                 "kinetic_end": 0.5 * float(mass * (y1[3] ** 2 + y1[4] ** 2) + inertia * y1[5] ** 2),
                 "mode_changes": 0, "mode_events": [], "pieces_cached": self.pieces[k], "solves": self.solves[k]}
        return Trajectory(self.times, self.states[k], [], "completed", float(self.times[-1]), 1, 0, stats)


class RideStepper(QuietStepper):
    """Steps the windows in which stick-slip parcels ride their wheels rigidly (module docstring), with the quiet
    stepper's anchors (clearance, support slack, edges) measured at each window's start.

    A parcel whose kept proof fails, but whose last anchor's cells are still under it and whose solution still
    holds there, is measured again, with its ride data, for all such parcels in one compiled call over per-parcel arrays
    (:func:`~virtual_vehicle.engine._kernel.ride_measure`): the same anchor :func:`~virtual_vehicle.engine.batch.anchor`
    makes, to the last bit, kept in the columns only (the anchor object keeps its cells and solution). The others
    are measured one by one in Python.

    Args:
        cells: the contact layer.
        specs: every parcel of the plant.
        law: the stick-slip law (its :meth:`wheel_arrays`).
        gravity: m/s^2.
    """

    def __init__(self, cells, specs, law, gravity: float):
        mu_max = [max(s.mu, s.mu_static or 0.0) for s in specs]
        super().__init__(cells, specs, law, mu_max, gravity, 0.0, 0.0)
        self.specs = list(specs)
        self.mass = np.array([s.mass for s in specs])
        self.inertia = np.array([s.inertia for s in specs])
        n = len(specs)
        self._twist = np.zeros((n, 3))  # the field's twist (vx, vy at the anchor's centre; omega), m/s, rad/s
        self._rides = np.zeros(n, dtype=bool)  # the wheels under the anchor are one rigid twist of rank 3
        self._grip = np.zeros((n, 3))  # the sticking wheels' zonotope's g, a (1/N), b (1/(N m)) at the anchor
        self._facing = np.zeros((n, 2))  # the unit direction of the anchor's centripetal force (zero without one)
        self._arm = np.zeros(n)  # m: the farthest wheel from the anchor's centre
        self._scale = np.zeros(n)  # m/s: the speed scale of the slip tolerance
        self._stuck: dict[int, tuple] = {}  # per parcel: the wheel memory of a ride (no impulses; those in contact)
        # what the compiled measure reads of each parcel: its outline, reach and rounding noise (fixed) ...
        outlines = [_kernel.outline(s) for s in specs]
        self._kind = np.array([o[0] for o in outlines], dtype=np.int64)
        self._half = np.array([o[2] for o in outlines]).reshape(n, 2)
        self._n_edges = np.array([len(o[4]) for o in outlines], dtype=np.int64)
        self._n_vertices = np.array([len(o[5]) for o in outlines], dtype=np.int64)
        edges = self._n_edges.max(initial=0)
        self._normals, self._offsets = np.zeros((n, edges, 2)), np.zeros((n, edges))
        self._vertices = np.zeros((n, self._n_vertices.max(initial=0), 2))
        for i, o in enumerate(outlines):
            self._normals[i, :len(o[4])], self._offsets[i, :len(o[4])], self._vertices[i, :len(o[5])] = o[3], o[4], o[5]
        self._buffer = np.array([max(cells.pitch, 0.25 * s.radius) for s in specs])
        self._reach = np.array([s.radius + b for s, b in zip(specs, self._buffer.tolist())])
        self._noise_len = np.array([ROUNDING_NOISE * max(self.length, s.radius) for s in specs])
        self._noise_force = np.array([ROUNDING_NOISE * s.weight(gravity) for s in specs])
        # the footprint's inradius about its centre (m; 0: a polygon, not looked at): cells within it are under it
        self._inner = np.zeros(n)
        for i, o in enumerate(outlines):
            if o[0] == _kernel.RECTANGLE:
                self._inner[i] = min(o[2])
            elif o[0] == _kernel.CONVEX and len(o[4]):
                self._inner[i] = max(0.0, min(o[4]))
        self._mu = np.array([float(s.mu) for s in specs])
        self._mu_s = np.array([float(s.mu if s.mu_static is None else s.mu_static) for s in specs])
        # ... and its last anchor's solution, where it is the first of its pattern's (else ``_known`` False)
        self._known = np.zeros(n, dtype=bool)
        self._n_support = np.zeros(n, dtype=np.int64)
        self._holding = np.zeros((n, 0))
        self._spring_lin, self._force_lin = np.zeros((n, 0, 2)), np.zeros((n, 0, 2))
        self._force_const, self._origin = np.zeros((n, 0)), np.zeros((n, 2))
        self._on = np.zeros((n, 0), dtype=bool)  # the wheels in contact its wheel memory was made for
        # the proofs kept (run state, :meth:`proofs`): a parcel whose anchor was measured at state ``_anchor_y``
        # under the wheel velocities ``_wheels`` (m/s, its anchor's cells', padded) rides on it while those wheels
        # stand and the proof's margins hold for the motion since; restored proofs are measured again at their
        # anchors when next looked at (``_pending``: parcel -> (state, wheels))
        self._kept = np.zeros(n, dtype=bool)
        self._anchor_y = np.zeros((n, 6))
        self._wheels = np.zeros((n, 0, 2))
        self._pending: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def forget(self, i: int | None = None) -> None:
        super().forget(i)
        if i is None:
            self._known[:] = self._kept[:] = False
            self._pending.clear()
            self._stuck.clear()
        else:
            self._known[i] = self._kept[i] = False
            self._pending.pop(i, None)
            self._stuck.pop(i, None)

    def proofs(self) -> dict:
        """The kept proofs as data (run state): ``anchors`` (n, 6), the state each parcel's anchor was measured at
        (NaN rows: none kept), and ``wheels`` (n, k, 2) m/s, the wheel velocities under its cells then (NaN-padded
        to the widest row)."""
        rows = {i: self._wheels[i, :len(self.anchors[i].support)] for i in np.flatnonzero(self._kept).tolist()}
        rows.update({i: w for i, (_, w) in self._pending.items()})
        anchors = np.full((len(self._kept), 6), np.nan)
        wheels = np.full((len(self._kept), max(map(len, rows.values()), default=0), 2), np.nan)
        for i, w in rows.items():
            anchors[i] = self._anchor_y[i] if i not in self._pending else self._pending[i][0]
            wheels[i, :len(w)] = w
        return {"anchors": anchors, "wheels": wheels}

    def take_proofs(self, anchors: np.ndarray, wheels: np.ndarray) -> None:
        """Take up the proofs :meth:`proofs` wrote (after :meth:`forget`): each is measured again at its anchor's
        state under its wheels when its parcel is next stepped, so the run rides the windows it would have."""
        for i in np.flatnonzero(~np.isnan(anchors[:, 0])).tolist():
            w = wheels[i]
            self._pending[i] = (anchors[i].copy(), w[~np.isnan(w[:, 0])].copy())

    def _resume(self, idx: np.ndarray, models, velocities: np.ndarray) -> None:
        """Measure again the restored proofs of parcels ``idx`` at their anchors, under the wheels they had."""
        for i in [i for i in idx.tolist() if i in self._pending]:
            y, w = self._pending.pop(i)
            if self.measure(i, models, y) is None:
                continue
            support = self.anchors[i].support
            V = np.array(velocities, dtype=float)
            V[support] = w[:len(support)]
            self._ride_data(i, V)
            self._keep(i, y, V)

    def _slipping(self, idx: np.ndarray, Y: np.ndarray, velocities: np.ndarray, present) -> np.ndarray:
        """Which parcels ``idx`` at states ``Y`` slip on a wheel certainly under them (:func:`slipping_under`), of the
        cells ``present`` (None: all)."""
        grid, cells = self.cells.grid, self.cells
        present = ALL_PRESENT if present is None else present
        return slipping_under(grid.points, grid.order, grid.start, float(grid.lo[0]), float(grid.lo[1]),
                              float(grid.size), int(grid.shape[0]), int(grid.shape[1]), present, cells.wheel_active,
                              cells.drive_directions, np.ascontiguousarray(velocities, dtype=float), Y,
                              self._inner[idx], np.empty(len(idx), dtype=np.bool_))

    def _crossing(self, idx: np.ndarray, Y: np.ndarray, times: np.ndarray, t: float, present) -> np.ndarray:
        """Which parcels ``idx`` at states ``Y`` (at ``t``, s) moving with their twists have other cells under them at
        the window's end ``times[-1]`` (:func:`cells_change`), of the cells ``present`` (None: all)."""
        grid = self.cells.grid
        present = ALL_PRESENT if present is None else present
        Y, Y_end = np.ascontiguousarray(Y), np.ascontiguousarray(rigid_motion(Y, np.array([t, times[-1]]), t)[:, 1])
        return cells_change(grid.points, grid.order, grid.start, float(grid.lo[0]), float(grid.lo[1]),
                            float(grid.size), int(grid.shape[0]), int(grid.shape[1]), present, self._kind[idx],
                            self._half[idx], self._normals[idx], self._offsets[idx], self._n_edges[idx],
                            self._vertices[idx], self._n_vertices[idx], self.radius[idx], Y, Y_end,
                            np.empty(len(idx), dtype=np.bool_))

    def _keep(self, i: int, y: np.ndarray, velocities: np.ndarray) -> None:
        """Keep parcel ``i``'s proof, its anchor measured at state ``y`` under ``velocities`` (m/s)."""
        self._kept[i] = True
        self._anchor_y[i] = y
        self._wheels = _padded_row(self._wheels, i, velocities[self.anchors[i].support], 0.0)

    def _wheels_stand(self, idx: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Whether the wheel velocities under the kept anchors of parcels ``idx`` are still those they were
        measured under (each compared exactly)."""
        w = self._wheels.shape[1]
        ids = self._support[idx, :w]
        now = np.take(velocities, ids, axis=0, mode="clip")
        same = (now == self._wheels[idx]) | (ids >= self.cells.n)[..., None]
        return same.all(axis=(1, 2))

    def _remember(self, i: int, support: np.ndarray, on: np.ndarray) -> None:
        """Make the wheel memory a ride of parcel ``i`` on cells ``support`` leaves (no impulses; the wheels in
        contact, ``on``, stick), once for these wheels."""
        key = support.tobytes() + on.tobytes()
        if self._stuck.get(i, (None,))[0] != key:
            row, k = np.nonzero(self.cells.wheel_active[support])
            keys = list(zip(support[row].tolist(), k.tolist()))
            self._stuck[i] = (key, dict.fromkeys(keys, 0.0), dict(zip(keys, on.tolist())))
        self._on = _padded_row(self._on, i, on, False)

    def _ride_data(self, i: int, velocities: np.ndarray) -> None:
        """Whether the wheels under parcel ``i``'s anchor are one rigid twist that fixes the parcel (rank 3), and
        if so that twist and the grip's measures at the anchor (module docstring); and what the compiled measure
        needs of the anchor's solution to measure the parcel again while it holds."""
        a = self.anchors[i]
        spec = self.specs[i]
        self._rides[i] = False
        P, U, w, _, _, FL, FC, origin, mus, _ = self.law.wheel_arrays(self.cells, a.support, a.solution, velocities,
                                                                      spec.mu, spec.mu_static)
        rides, twist, grip, facing, arm, scale, on = _kernel.ride_data(P, U, w, FL, FC, origin, mus,
                                                                       a.pose[:2].copy(), RIDE_TOL)
        self._rides[i], self._twist[i], self._grip[i], self._facing[i] = rides, twist, grip, facing
        self._arm[i], self._scale[i] = arm, scale
        self._remember(i, a.support, on)
        sol = a.solution
        self._known[i] = a.first
        if a.first:
            self._n_support[i] = len(a.support)
            self._holding = _padded_row(self._holding, i, sol._holding, 0.0)
            self._spring_lin = _padded_row(self._spring_lin, i, np.asarray(sol.spring_lin, dtype=float), 0.0)
            self._force_lin = _padded_row(self._force_lin, i, np.asarray(sol.force_lin, dtype=float), 0.0)
            self._force_const = _padded_row(self._force_const, i, np.asarray(sol.force_const, dtype=float), 0.0)
            self._origin[i] = sol.origin

    def _measure_known(self, idx: np.ndarray, Y: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Measure again, in one compiled call, those of parcels ``idx`` (states ``Y``) whose last anchor's cells
        and solution still stand (class docstring), keeping their anchors' measures and ride data in the columns;
        which were."""
        q = len(idx)
        if not self._known[idx].any():
            return np.zeros(q, dtype=bool)
        grid, cells = self.cells.grid, self.cells
        present = self.anchors[int(idx[np.flatnonzero(self._known[idx])[0]])].model.present
        near = np.full((q, max(self._near.shape[1], 1)), cells.n, dtype=np.int64)
        n_near = np.zeros(q, dtype=np.int64)
        measures = np.zeros((q, 12))
        flags = np.zeros((q, 3), dtype=bool)
        on_now = np.zeros((q, max(self._on.shape[1], 1)), dtype=bool)
        _kernel.ride_measure(grid.points, grid.order, grid.start, grid.lo[0], grid.lo[1], grid.size, grid.shape[0],
                             grid.shape[1], ALL_PRESENT if present is None else present, cells.positions,
                             cells.wheel_active, cells.drive_directions, np.ascontiguousarray(velocities, dtype=float),
                             idx, Y, self._reach, self._buffer, self._noise_len, self._noise_force, self._mu,
                             self._mu_s, self._kind, self._half, self._normals, self._n_edges, self._offsets,
                             self._vertices, self._n_vertices, self._known, self._support, self._n_support,
                             self._holding, self._spring_lin, self._force_lin, self._force_const, self._origin,
                             self._on, RIDE_TOL, near, n_near, measures, flags, on_now)
        done = flags[:, 0]
        sel = np.flatnonzero(done)
        i = idx[sel]
        self._pose[i] = Y[sel, :3]
        self._clear[i], self._slack[i] = measures[sel, 0], measures[sel, 1]
        self._made[i], self._drive[i] = -1, 0.0  # as measure() leaves an anchor without constants
        if len(sel):
            if near.shape[1] > self._near.shape[1]:
                self._near = _padded_row(self._near, int(i[0]), near[sel[0]], cells.n)
            self._near[i] = near[sel, :self._near.shape[1]]
        self._near_count[i] = n_near[sel]
        self._rides[i], self._twist[i] = flags[sel, 1], measures[sel, 2:5]
        self._grip[i], self._facing[i] = measures[sel, 5:8], measures[sel, 8:10]
        self._arm[i], self._scale[i] = measures[sel, 10], measures[sel, 11]
        for k in sel[~flags[sel, 2]].tolist():  # the wheels in contact changed: their ride's memory is made again
            p = int(idx[k])
            cells = self._support[p, :self._n_support[p]].copy()
            self._remember(p, cells, on_now[k, :len(self._stuck[p][1])].copy())
        return done

    def _off(self, idx: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far (m/s) the twists of parcels ``idx`` at states ``Y`` are from their wheels' rigid twist (as their
        anchors found it), bounding every wheel's slip; and the states with that twist (the field's at the centre)."""
        P0 = self._pose[idx]
        dx, dy = Y[:, 0] - P0[:, 0], Y[:, 1] - P0[:, 1]
        tw = self._twist[idx]
        om = tw[:, 2]
        Yf = Y.copy()
        Yf[:, 3], Yf[:, 4], Yf[:, 5] = tw[:, 0] - om * dy, tw[:, 1] + om * dx, om  # omega x (centre - anchor)
        arm = self._arm[idx] + np.hypot(dx, dy)
        return np.hypot(Y[:, 3] - Yf[:, 3], Y[:, 4] - Yf[:, 4]) + np.abs(Y[:, 5] - om) * arm, Yf

    def _riding(self, idx: np.ndarray, Y: np.ndarray, window: float) -> tuple[np.ndarray, np.ndarray]:
        """Which parcels ``idx`` (anchored, their ride data current) at states ``Y`` are proven to ride for
        ``window`` s, and their states with the field's twist."""
        rides = self._rides[idx].copy()
        P0 = self._pose[idx]
        moved = np.hypot(Y[:, 0] - P0[:, 0], Y[:, 1] - P0[:, 1])
        off, Yf = self._off(idx, Y)
        rides &= off <= RIDE_TOL * self._scale[idx]
        vx, vy, om = Yf[:, 3], Yf[:, 4], Yf[:, 5]
        R = self.radius[idx]
        speed = np.hypot(vx, vy)
        d = speed * window  # how far the centre moves (m)
        r = (speed + np.abs(om) * R) * window  # how far any point moves (m)
        D = moved + d
        slack = self._slack[idx]
        rides &= slack > D  # no normal force changes sign, no cell lifts off or touches down
        share = D / np.where(slack > 0, slack, np.inf)  # each normal force stays within (1 -+ share) of the anchor's
        # the grip (module docstring): the centripetal force m omega x v, its direction within ``turned`` of the
        # anchor's over the window, taken about the anchor's centre, inside (1 - share) times the anchor's zonotope
        force = self.mass[idx] * np.abs(om) * speed  # N (eq. 3: m a, a = omega x v)
        facing = np.sign(om)[:, None] * np.column_stack([-vy, vx]) / np.where(speed > 0, speed, 1.0)[:, None]
        turned = np.hypot(*(facing - self._facing[idx]).T) + np.abs(om) * window
        g, a, b = self._grip[idx].T
        rides &= force * (g + a * turned + b * D) < 1.0 - share
        swept = moved + np.abs(Y[:, 2] - P0[:, 2]) * R
        clear = self._clear[idx] > swept + r
        look = np.flatnonzero(rides & ~clear & (D < self._room[idx]) & self._convex[idx])
        if len(look):
            # the arc leaves the straight line v T by at most |omega| |v| T^2 / 2; as an acceleration bound the
            # edge check splits it between the centre and the turning (it takes |dtheta| <= |omega| T + the rest)
            lever = self.lever[idx[look]]
            bend = 0.5 * np.abs(om[look]) * speed[look] * window ** 2
            clear[look] = self.edges_clear(idx[look], Yf[look], window, r[look], lever * bend, R[look], lever)
        return rides & clear, Yf

    def step(self, models, idx: list[int], ys, velocities: np.ndarray, t: float, te: float,
             samples: np.ndarray) -> tuple[RideSteps | None, list[int]]:
        """Advance those of the parcels ``idx`` (states ``ys[i]``, no other parcel within reach) that ride their wheels
        from ``t`` to ``te`` (s) under contact-layer ``velocities`` (m/s), sampled at ``samples`` (the window's ends
        among them): returns the block of those stepped here (None when none) and the parcels left for the
        event-driven engine. ``models`` are the plant's models under these velocities (``models[i]`` parcel i's; their
        ``base`` and the copies ``made`` so far); a riding parcel's stick-slip wheel memory is left as the engine
        leaves it (every wheel in contact sticking, no impulse remembered)."""
        if not idx:
            return None, []
        times = np.concatenate([[t], samples[(samples > t) & (samples < te)], [te]])
        window = te - t
        Y = np.array([ys[i] for i in idx], dtype=float)
        start = Y.copy()
        ia = np.asarray(idx, dtype=np.int64)
        # a kept proof first (its wheels as they were, its margins holding for the motion since its anchor); the
        # others are measured where they are now, and that proof kept. The proofs are run state (:meth:`proofs`), so
        # a run resumed from a checkpoint decides the same windows as the run that went on, to the last bit
        self._resume(ia, models, velocities)
        ok = np.zeros(len(idx), dtype=bool)
        kept = np.flatnonzero(self._kept[ia])
        if len(kept):
            kept = kept[self._wheels_stand(ia[kept], velocities)]
        if len(kept):
            rides, Yf = self._riding(ia[kept], Y[kept], window)
            ok[kept] = rides
            Y[kept[rides]] = Yf[rides]
        again = np.flatnonzero(~ok)
        if len(again):  # a parcel slipping on a wheel under it, or moving onto other cells, cannot ride: not measured
            present = models.base[idx[0]].present
            again = again[~self._slipping(ia[again], Y[again], velocities, present)]
            again = again[~self._crossing(ia[again], Y[again], times, t, present)]
        ja, Ya = ia[again], Y[again]
        have = self._measure_known(ja, Ya, velocities)
        for k in np.flatnonzero(~have).tolist():
            i = int(ja[k])
            if self.measure(i, models, Ya[k]) is not None:
                self._ride_data(i, velocities)
                have[k] = True
            else:  # it tips there: no anchor to measure again
                self._known[i] = self._kept[i] = False
        for k in np.flatnonzero(have).tolist():
            self._keep(int(ja[k]), Ya[k], velocities)
        sel = np.flatnonzero(have)
        if len(sel):
            rides, Yf = self._riding(ja[sel], Ya[sel], window)
            ok[again[sel]] = rides
            Y[again[sel[rides]]] = Yf[rides]
        quiet = np.flatnonzero(ok)
        rest = [idx[k] for k in np.flatnonzero(~ok)]
        if not len(quiet):
            return None, rest
        states = rigid_motion(Y[quiet], times, t)
        riding = ia[quiet].tolist()
        base, made = models.base, models.made
        for i in riding:
            _, lam, stuck = self._stuck[i]
            memory = base[i].contact_memory  # (shared with the copies made from it)
            if memory["stuck"] is not stuck:
                memory["lam"], memory["stuck"] = lam, stuck
        pieces = [made[i].pieces_cached if i in made else 0 for i in riding]  # a copy made now would hold none
        solves = [base[i].solves for i in riding]
        return RideSteps(riding, times, states, start[quiet], self.mass[riding], self.inertia[riding], pieces,
                         solves), rest


__all__ = ["RideStepper", "RideSteps", "rigid_motion", "RIDE_TOL"]
