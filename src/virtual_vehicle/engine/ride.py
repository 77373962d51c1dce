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
speed over the tick, :meth:`~virtual_vehicle.run.sim.NetworkedRun.finish`), so the twist the wheels make is constant
over a window; the check is made again whenever the wheels under the parcel change, and a window whose wheels are
not one rigid twist (a ramp that is not common to all of them included) is not a ride.

The proof for a window of ``T`` s, from the parcel's anchor (:mod:`virtual_vehicle.engine.batch`: its clearance
``clear``, support ``slack`` and, where needed, the edge-by-edge look), with the parcel's twist that of the field:

- no cell enters or leaves and no support force changes sign: every point of the parcel moves at most its point
  speed bound ``S0 = |v| + |omega| R`` times ``T`` (``r = S0 T`` exactly: the speeds are constant in a rigid
  motion) and the centre of mass at most ``d = |v| T``;
- the grip holds: the wrench the sticking wheels must supply is that of the motion's acceleration, zero in
  translation and the centripetal ``m |omega| |v|`` (constant in size, zero torque) in rotation (eqs. 3-19 give the
  normal forces, the per-wheel Coulomb bound ``mu_s N`` of eqs. 20-22 the zonotope). It lies in the sticking wheels'
  zonotope while its length is below the zonotope's inradius ``rho`` (:func:`~virtual_vehicle.physics.stick_modes.
  zonotope_inradius`), measured at the anchor. With ``D`` the centre's distance from the anchor by the window's end
  and ``s`` the anchor's slack, every normal force (affine in the centre, eq. 19, and positive for ``s`` more) stays
  within ``(1 -+ D / s)`` of the anchor's, and a zonotope whose generators are scaled by at least ``c`` holds ``c``
  times the original; the levers ``r x u`` of the rows move by at most ``D``, which moves each generator by at most
  ``mu_s N_j D``. So the grip holds while ``m |omega| |v| < (1 - D / s) rho - D (1 + D / s) sum mu_s N_j``.

The parcel's twist must be the field's (its slip on every wheel below the engine's slip tolerance); the closed form
then carries the field's twist itself, as the event-driven engine does when it projects the twist onto the sticking
wheels' constraints. The energy account of such a window is zero wheel work and zero dissipation: the stick forces'
power is the wrench times the twist, ``m (omega x v) . v = 0``.
"""

from __future__ import annotations

import numpy as np

from virtual_vehicle.engine.batch import QuietStepper
from virtual_vehicle.engine.stepping import Trajectory
from virtual_vehicle.physics.stick_modes import zonotope_inradius

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


class RideStepper(QuietStepper):
    """Steps the windows in which stick-slip parcels ride their wheels rigidly (module docstring), reusing the quiet
    stepper's anchors (clearance, support slack, edges) and its record of which wheels changed when.

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
        n = len(specs)
        self._twist = np.zeros((n, 3))  # the field's twist (vx, vy at the anchor's centre; omega), m/s, rad/s
        self._rides = np.zeros(n, dtype=bool)  # the wheels under the anchor are one rigid twist of rank 3
        self._inradius = np.zeros(n)  # N: the sticking wheels' zonotope's at the anchor, less rounding
        self._spread = np.zeros(n)  # N: sum of mu_s N_j (how far the generators move per metre the levers change)
        self._arm = np.zeros(n)  # m: the farthest wheel from the anchor's centre
        self._scale = np.zeros(n)  # m/s: the speed scale of the slip tolerance
        self._ride_pose = np.zeros((n, 2))  # m: where the ride data were measured (an anchor's centre)
        self._ride_slack = np.zeros(n)  # m: that anchor's support slack
        self._ride_piece: dict[int, tuple] = {}  # per parcel: the support and solved pattern they were measured on
        self._stuck: dict[int, tuple] = {}  # per parcel: the wheel memory of a ride (no impulses; those in contact)

    def _ride_data(self, i: int, model, velocities: np.ndarray) -> None:
        """Whether the wheels under parcel ``i``'s anchor are one rigid twist that fixes the parcel (rank 3), and
        if so that twist and the grip's measures at the anchor (module docstring)."""
        a = self.anchors[i]
        spec = self.specs[i]
        self._made[i] = self._changes
        self._rides[i] = False
        P, U, w, _, _, FL, FC, origin, mus, _ = self.law.wheel_arrays(self.cells, a.support, a.solution, velocities,
                                                                      spec.mu, spec.mu_static)
        X = a.pose[:2]
        self._ride_pose[i], self._ride_slack[i] = X, a.slack
        self._ride_piece[i] = (a.support, a.solution.force_lin)
        N = FL @ (X - origin) + FC  # eq. 19: each wheel's cell's normal force at the anchor (N)
        on = (mus > 0) & (N > 0)
        row, k = np.nonzero(self.cells.wheel_active[a.support])
        keys = list(zip(a.support[row].tolist(), k.tolist()))
        # the wheel memory a ride leaves, made once per anchor (the engine replaces these dicts, never changes them)
        self._stuck[i] = (dict.fromkeys(keys, 0.0), dict(zip(keys, on.tolist())))
        if on.sum() < 3:
            return
        r = P[on] - X
        u = U[on]
        J = np.column_stack([u, r[:, 0] * u[:, 1] - r[:, 1] * u[:, 0]])  # the wheels' rows [u, r x u]
        nu, _, rank, _ = np.linalg.lstsq(J, w[on], rcond=None)
        scale = max(1e-3, float(np.abs(w).max(initial=0.0)))
        if rank < 3 or np.abs(J @ nu - w[on]).max() > RIDE_TOL * scale:
            return  # not one rigid twist, or one that leaves the parcel a free direction
        G = np.ascontiguousarray((mus[on] * N[on])[:, None] * J)
        self._twist[i] = nu
        self._inradius[i] = zonotope_inradius(G) - 1e-9 * np.abs(G).sum()
        self._spread[i] = float((mus[on] * N[on]).sum())
        self._arm[i] = float(np.hypot(r[:, 0], r[:, 1]).max())
        self._scale[i] = scale
        self._rides[i] = True

    def measure(self, i, models, y):
        """:meth:`QuietStepper.measure`, keeping the ride data where the new anchor lies on the same cells and solved
        pattern as the anchor they were measured at (the same normal-force map: the grip's bound holds from there)."""
        made = self._made[i]
        a = super().measure(i, models, y)
        kept = self._ride_piece.get(i)
        if (a is not None and kept is not None and kept[1] is a.solution.force_lin
                and np.array_equal(kept[0], a.support)
                and np.hypot(*(a.pose[:2] - self._ride_pose[i])) < 0.5 * self._ride_slack[i]):
            self._made[i] = made  # (measured again once the parcel has used up half the grip's room from there)
        return a

    def forget(self, i: int | None = None) -> None:
        """Drop parcel ``i``'s anchor (all when None), and with it what was found of its wheels."""
        super().forget(i)
        if i is None:
            self._made[:] = -1
        else:
            self._made[i] = -1

    def _off(self, idx: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far (m/s) the twists of parcels ``idx`` at states ``Y`` are from their wheels' rigid twist (as their
        ride data found it), bounding every wheel's slip; and the states with that twist (the field's at the centre)."""
        P0 = self._ride_pose[idx]
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
        rides &= self._slack[idx] > D  # no normal force changes sign, no cell lifts off or touches down
        # the grip, from where the ride data were measured (on the same normal-force map): each normal force stays
        # within (1 -+ share) of its value there
        Dr = np.hypot(Y[:, 0] - self._ride_pose[idx, 0], Y[:, 1] - self._ride_pose[idx, 1]) + d
        slack = self._ride_slack[idx]
        rides &= slack > Dr
        share = Dr / np.where(slack > 0, slack, np.inf)
        held = (1.0 - share) * self._inradius[idx] - Dr * (1.0 + share) * self._spread[idx]
        rides &= self.mass[idx] * np.abs(om) * speed < held
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
             samples: np.ndarray) -> tuple[list[tuple[int, Trajectory]], list[int]]:
        """Advance those of the parcels ``idx`` (states ``ys[i]``, no other parcel within reach) that ride their wheels
        from ``t`` to ``te`` (s) under contact-layer ``velocities`` (m/s), sampled at ``samples`` (the window's ends
        among them): returns (parcel, trajectory) for each stepped here and the parcels left for the event-driven
        engine. ``models[i]`` is parcel i's model under these velocities; its stick-slip wheel memory is left as the
        engine leaves it (every wheel in contact sticking, no impulse remembered)."""
        if not idx:
            return [], []
        times = np.concatenate([[t], samples[(samples > t) & (samples < te)], [te]])
        window = te - t
        Y = np.array([ys[i] for i in idx], dtype=float)
        self.see(velocities)
        arr = np.asarray(idx)
        for k, i in enumerate(idx):
            if i not in self.anchors:
                self.measure(i, models, Y[k])
        ok = self._check(arr, np.arange(len(idx)), Y, models, velocities, window)
        # measured again where its parcel is, and asked again: an anchor that may have run out for a parcel that
        # rides its wheels, or one whose cells are no longer surely the parcel's (a parcel that does not ride is
        # not measured again every window, only as it crosses cells)
        fk = np.array([k for k in np.flatnonzero(~ok).tolist() if idx[k] in self.anchors], dtype=np.int64)
        stale = []
        if len(fk):
            p = arr[fk]
            P0 = self._pose[p]
            swept = np.hypot(Y[fk, 0] - P0[:, 0], Y[fk, 1] - P0[:, 1]) + np.abs(Y[fk, 2] - P0[:, 2]) * self.radius[p]
            off, _ = self._off(p, Y[fk])
            again = (self._clear[p] <= swept) | (self._rides[p] & (off <= RIDE_TOL * self._scale[p]))
            again &= (P0 != Y[fk, :3]).any(axis=1)
            stale = fk[again].tolist()
        for k in stale:
            self.measure(idx[k], models, Y[k])
        if stale:
            ok[stale] = self._check(arr, np.array(stale), Y, models, velocities, window)
        quiet = np.flatnonzero(ok)
        rest = [idx[k] for k in np.flatnonzero(~ok)]
        if not len(quiet):
            return [], rest
        states = rigid_motion(Y[quiet], times, t)
        done = []
        for n, k in enumerate(quiet.tolist()):
            i = idx[k]
            model, spec = models[i], self.specs[i]
            lam, stuck = self._stuck[i]
            memory = model.contact_memory
            if memory["stuck"] is not stuck:
                memory["lam"], memory["stuck"] = lam, stuck
            y0, y1 = ys[i], states[n, -1]
            stats = {"wheel_work": 0.0, "friction_dissipation": 0.0, "step_dissipation": 0.0, "contact_work": 0.0,
                     "sweeps_max": 0, "unconverged_steps": 0,
                     "kinetic_start": 0.5 * float(spec.mass * (y0[3] ** 2 + y0[4] ** 2) + spec.inertia * y0[5] ** 2),
                     "kinetic_end": 0.5 * float(spec.mass * (y1[3] ** 2 + y1[4] ** 2) + spec.inertia * y1[5] ** 2),
                     "mode_changes": 0, "mode_events": [], "pieces_cached": model.pieces_cached,
                     "solves": model.solves}
            done.append((i, Trajectory(times, states[n], [], "completed", float(te), 1, 0, stats)))
        return done, rest

    def _check(self, arr, ks, Y, models, velocities, window) -> np.ndarray:
        """Which of the parcels ``arr[k]`` for k in ``ks`` are proven to ride (False without an anchor), their ride
        data brought up to date with ``velocities`` first; ``Y``'s rows of those proven get the field's twist."""
        ok = np.zeros(len(ks), dtype=bool)
        have = np.array([int(arr[k]) in self.anchors for k in ks], dtype=bool)
        if not have.any():
            return ok
        sel = ks[have]
        parcels = arr[sel]
        changed = self._changed_at[self._support[parcels]].max(axis=1) > self._made[parcels]
        for i in parcels[changed].tolist():
            self._ride_data(i, models[i], velocities)
        rides, Yf = self._riding(parcels, Y[sel], window)
        ok[have] = rides
        Y[sel[rides]] = Yf[rides]
        return ok


__all__ = ["RideStepper", "rigid_motion", "RIDE_TOL"]
