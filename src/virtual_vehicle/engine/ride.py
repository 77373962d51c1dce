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
speed over the tick, :meth:`~virtual_vehicle.run.sim.TickedRun.finish`), so the twist the wheels make is constant
over a window; a window whose wheels are not one rigid twist (a ramp that is not common to all of them included) is
not a ride. Each window is proven from the parcel's state at its start alone (the anchor is measured there), so the
windows a run rides do not depend on its history: a run resumed from a checkpoint rides the same ones.

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

from virtual_vehicle.engine import _kernel
from virtual_vehicle.engine.batch import QuietStepper
from virtual_vehicle.engine.stepping import Trajectory

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
    """Steps the windows in which stick-slip parcels ride their wheels rigidly (module docstring), with the quiet
    stepper's anchors (clearance, support slack, edges) measured at each window's start.

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
        self._stuck: dict[int, tuple] = {}  # per parcel: the wheel memory of a ride (no impulses; those in contact)

    def _ride_data(self, i: int, velocities: np.ndarray) -> None:
        """Whether the wheels under parcel ``i``'s anchor are one rigid twist that fixes the parcel (rank 3), and
        if so that twist and the grip's measures at the anchor (module docstring)."""
        a = self.anchors[i]
        spec = self.specs[i]
        self._rides[i] = False
        P, U, w, _, _, FL, FC, origin, mus, _ = self.law.wheel_arrays(self.cells, a.support, a.solution, velocities,
                                                                      spec.mu, spec.mu_static)
        rides, twist, inradius, spread, arm, scale, on = _kernel.ride_data(P, U, w, FL, FC, origin, mus,
                                                                           a.pose[:2].copy(), RIDE_TOL)
        self._rides[i], self._twist[i], self._inradius[i] = rides, twist, inradius
        self._spread[i], self._arm[i], self._scale[i] = spread, arm, scale
        key = a.support.tobytes() + on.tobytes()
        if self._stuck.get(i, (None,))[0] != key:
            # the wheel memory a ride leaves (no impulses; those in contact stick), made once for these wheels
            row, k = np.nonzero(self.cells.wheel_active[a.support])
            keys = list(zip(a.support[row].tolist(), k.tolist()))
            self._stuck[i] = (key, dict.fromkeys(keys, 0.0), dict(zip(keys, on.tolist())))

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
        held = (1.0 - share) * self._inradius[idx] - D * (1.0 + share) * self._spread[idx]
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
        # measured where each parcel is now, every window: the proof then depends on the state alone, not on where
        # the parcel was measured before (a run resumed from a checkpoint, whose caches start empty, decides the
        # same windows as the run that went on, to the last bit)
        have = np.zeros(len(idx), dtype=bool)
        for k, i in enumerate(idx):
            if self.measure(i, models, Y[k]) is not None:
                self._ride_data(i, velocities)
                have[k] = True
        ok = np.zeros(len(idx), dtype=bool)
        sel = np.flatnonzero(have)
        if len(sel):
            ok[sel], Yf = self._riding(np.asarray(idx)[sel], Y[sel], window)
            Y[sel] = Yf
        quiet = np.flatnonzero(ok)
        rest = [idx[k] for k in np.flatnonzero(~ok)]
        if not len(quiet):
            return [], rest
        states = rigid_motion(Y[quiet], times, t)
        done = []
        for n, k in enumerate(quiet.tolist()):
            i = idx[k]
            model, spec = models[i], self.specs[i]
            _, lam, stuck = self._stuck[i]
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


__all__ = ["RideStepper", "rigid_motion", "RIDE_TOL"]
