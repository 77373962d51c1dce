"""The paper's viscous law (4.4, eqs. 30-38): ``f_i = mu N_i (V_i - Xdot_c + omega J (X_i - X_c))`` with
``J = [[0, 1], [-1, 0]]``; the driving part has the Coulomb form with ``F`` replaced by the wheel velocities ``V``,
plus translational damping ``-mu W Xdot_c`` (eq. 33) and rotational damping ``-mu omega sum N_i |X_i - X_c|^2``
(eq. 38). Here ``mu`` is in s/m. It acts on a lumped cell's whole slip vector, so it needs the paper's lumped cells.

Units: N, N m, m, m/s, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.optimize import lsq_linear

from virtual_vehicle.physics.laws import affine
from virtual_vehicle.physics.laws.affine import J, FrictionConstants, drive_constants, f64
from virtual_vehicle.physics.laws.base import FrictionLaw, energy_reach


def viscous_constants(points, velocities, weight: float, mu: float) -> FrictionConstants:
    """The viscous constants (eqs. 30-38) for wheel velocities ``velocities`` ((m, 2), m/s) at ``points`` (m),
    all cells in contact; ``mu`` in s/m."""
    G, h = affine.all_in_contact_map(points, weight)
    return drive_constants(points, velocities, G, h, weight, mu, damping=mu)


@njit(cache=True)
def _viscous_drive(V, U):
    """:meth:`ViscousLaw.drive_vectors` of velocities ``V`` (m, 2), compiled: the wheel velocities (eq. 30)."""
    return V.copy()


@dataclass(frozen=True)
class ViscousLaw(FrictionLaw):
    """The paper's viscous law (4.4): force proportional to normal force and slip velocity; ``mu`` in s/m."""

    name: str = "viscous"
    damped = True
    galilean = True  # eq. 30: the force is the slip's

    def drive_vectors(self, velocities, drive_directions) -> np.ndarray:
        """Per-cell wheel velocity (the V_i of eq. 30), m/s."""
        return np.asarray(velocities, dtype=float)

    def cell_forces(self, points, normal, velocities, drive_directions, mu, state) -> np.ndarray:
        """``mu N_i`` times the slip of eq. 30."""
        P = np.asarray(points, dtype=float)
        X = np.asarray(state[:2], dtype=float)
        v = np.asarray(state[3:5], dtype=float)
        slip = np.asarray(velocities, dtype=float) - v + state[5] * (P - X) @ J.T  # eq. 30
        return mu * np.asarray(normal)[:, None] * slip

    def constants(self, solution, velocities, drive_directions, mu) -> FrictionConstants:
        """Per-support-set constants (eqs. 30-38): the wrench is linear in the parcel's twist."""
        return drive_constants(solution.points, velocities, solution.force_lin, solution.force_const,
                               solution.weight, mu, damping=mu)

    drive_kernel = staticmethod(_viscous_drive)
    """See :attr:`FrictionLaw.drive_kernel`: the wheel velocities V of eq. 30."""

    def affine_damping(self, mu: float) -> float:
        """See :meth:`FrictionLaw.affine_damping`: ``mu`` itself (eqs. 33, 38)."""
        return mu

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        """See :meth:`FrictionLaw.constants_and_row`."""
        return affine.constants_and_row(solution.points, f64(velocities), solution.force_lin, solution.force_const,
                                        mu, mu, solution.weight, solution.origin, mass, inertia)

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        """The smaller of two bounds, both true whatever the supports (forces ``mu N_i u_i``, ``u_i`` the slip at
        cell i, eq. 30; normal forces summing to at most W):

        - growth: ``|u_i| <= w + S``, so ``dS/dt <= k (w + S)`` with ``k = rate``: reach
          ``(S0 + w)(e^{kT} - 1)/k - w T``, speed ``(S0 + w) e^{kT} - w``. Tight for short windows; it grows
          exponentially, so alone it shrinks a planner's windows to a few hundredths of a second.
        - energy (with ``lever`` = ``1 + m R^2 / I``): the contacts' power on the parcel is
          ``sum_i mu N_i p_i . (V_i - p_i)`` (``p_i`` the parcel's point velocity over cell i), at most
          ``mu W (w A - A^2) <= mu W w^2 / 4`` (``A^2 = sum N_i |p_i|^2 / W``): the slip dissipates all but a
          quarter of what the wheels could put in. So the kinetic energy ``E <= m S0^2 / 2 + mu W w^2 t / 4``
          (``I <= m R^2``) and, as ``S^2 <= (lever / m) 2 E``, ``S(t)^2 <= lever S0^2 + rate w^2 t / 2``: speed
          grows like the square root of time at most, and the reach is its integral
          ``(2 T / 3) (x + sqrt(x y) + y) / (sqrt(x) + sqrt(y))`` with ``y = lever S0^2``, ``x = y + rate w^2 T / 2``.
          The law is :attr:`galilean`, so seen from a frame moving with the wheels' common velocity ``w`` is their
          speed relative to it: 0 on a uniform field, where the parcel's speed relative to the field never grows
          past ``sqrt(lever) S0`` (it relaxes to the field)."""
        kt = rate * window
        slow = kt < 1e-12
        k = np.where(slow, 1.0, rate)
        dist = np.where(slow, s0 * window, (s0 + wheel_speed) * np.expm1(kt) / k - wheel_speed * window)
        speed = np.where(slow, s0, (s0 + wheel_speed) * np.exp(kt) - wheel_speed)
        if lever is None:  # the parcel's inertia unknown: the growth bound alone
            return dist, speed
        y = lever * np.square(s0)
        x = y + 0.5 * rate * wheel_speed * wheel_speed * window  # eq. 30: S^2 <= lever S0^2 + rate w^2 t / 2
        energy, fastest = energy_reach(y, x, window)
        return np.minimum(dist, energy), np.minimum(speed, fastest)

    def frame_power(self, mu_weight, wheel_slack):
        """The contacts' power on the parcel seen from any frame, rotating or not, is ``sum_i mu N_i p_i . (V_i -
        p_i)`` with ``p_i`` the parcel's point velocity over entry i and ``V_i`` its surface velocity, both
        relative to the frame there (eq. 30), at most ``mu W s^2 / 4`` where every ``|V_i| <= s`` (the slip
        dissipates all but a quarter of what the wheels could put in, as in :meth:`reach`)."""
        return 0.25 * mu_weight * np.square(wheel_slack)

    def drive_bound(self, velocities, drive_directions) -> float:
        """Not needed: :meth:`piece_reach` reads the slips."""
        return 0.0

    def piece_reach(self, rate, window, curve, drive, slip):
        """Every cell under the parcel pushes with ``mu N_i u_i``, ``u_i`` its slip (eq. 30): accelerations are at
        most ``k sigma`` at the rim (``sigma = max |u_i|``, ``k = rate``) and ``d sigma / dt <= k sigma + curve``,
        so ``sigma_0 ((e^{kT} - 1) / k - T) + curve ((e^{kT} - 1) / k - T) / k``, by its series where kT is
        small."""
        sigma = slip()
        kt = rate * window
        big = kt > 1e-4
        ks = np.where(big, rate, 1.0)
        g1 = np.where(big, np.expm1(kt) / ks - window, kt * window * (0.5 + kt / 6 + kt * kt / 24))
        g2 = np.where(big, g1 / ks, window * window * (0.5 + kt / 6 + kt * kt / 24))
        return sigma * g1 + curve * g2

    def wheel_loads(self, speed, slip):
        """The slip itself (eq. 30)."""
        return slip

    def scaled_mu(self, mu, length):
        """``mu`` is in s/m (eq. 30): divided by the square root of the length factor."""
        return mu / math.sqrt(length)

    def supports(self, cells, free_wheels=False):
        """Lumped cells only: the law acts on a cell's whole slip vector, which separate, omni or free-spinning
        wheels do not transmit."""
        if cells.separate:
            raise ValueError("separate and omni wheels push only along their own drive direction; the paper's "
                             "viscous law acts on the whole slip vector of a lumped cell: use the coulomb or "
                             "stick_slip law")
        if free_wheels:
            raise ValueError("free-spinning wheels need the coulomb or stick_slip law (the paper's viscous law acts "
                             "on a cell's whole slip vector)")

    def design_wheels(self, A, own, want, vmax):
        """The slip is the wheel speed less ``own`` (eq. 30), so the wrench is affine in the wheel speeds: bounded
        least squares within +-vmax."""
        b = -A @ own
        active = np.any(A != 0, axis=0)
        sol = lsq_linear(A[:, active], want - b, bounds=(-vmax, vmax), method="bvls", tol=1e-12)
        x = np.zeros(A.shape[1])
        x[active] = sol.x
        return x, A @ x + b
