"""The paper's Coulomb law (4.3, eqs. 20-29): each wheel pushes with ``mu N_i`` along its drive direction, in the
direction it spins, so cell i pushes with ``mu N_i F_i`` where ``F_i = sum_k sign(V_i . u_k) u_k`` over its wheels
(``F_i = [+-1, +-1]`` for wheels along x and y, eq. 21). As in the paper the wheels are assumed to slide under the
parcel in their direction of spin (the parcel is slower than the wheels); the simulator reports when that
assumption fails. ``mu`` is dimensionless.

Units: N, N m, m, m/s, s.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.optimize import lsq_linear

from virtual_vehicle.physics.laws import affine
from virtual_vehicle.physics.laws.affine import FrictionConstants, drive_constants, f64
from virtual_vehicle.physics.laws.base import FrictionLaw

EXHAUSTIVE_WHEELS = 10
"""Coulomb designs over at most this many wheels try all 3^m spin patterns."""


@njit(cache=True)
def _coulomb_drive(V, U):
    """:meth:`CoulombLaw.drive_vectors` for velocities ``V`` (m, 2) and drive directions ``U`` (m, k, 2), compiled
    (each new piece needs them; two einsums took ~5 us)."""
    F = np.zeros((V.shape[0], 2))
    for i in range(V.shape[0]):
        for k in range(U.shape[1]):
            spin = np.sign(V[i, 0] * U[i, k, 0] + V[i, 1] * U[i, k, 1])  # eq. 21: the wheel's direction of spin
            F[i, 0] += spin * U[i, k, 0]
            F[i, 1] += spin * U[i, k, 1]
    return F


@njit(cache=True)
def _coulomb_terms_and_row(V, U, P, G, h, mu, weight, origin, inv_mass, inv_inertia):
    """:func:`~virtual_vehicle.physics.laws.affine._terms_and_row` of the Coulomb drive vectors of velocities ``V``
    and directions ``U`` (eq. 21), in one compiled call."""
    return affine._terms_and_row(P, _coulomb_drive(V, U), G, h, mu, 0.0, weight, origin, inv_mass, inv_inertia)


def coulomb_constants(points, directions, weight: float, mu: float) -> FrictionConstants:
    """The paper's Coulomb constants a, b, c, d, e, f (eqs. 20-29) for cells at ``points`` ((m, 2), m) pushing in
    ``directions`` ((m, 2), the per-cell F of eq. 21), a parcel of weight ``weight`` (N) and friction coefficient
    ``mu``, all cells in contact. Coordinates are those of ``points``.

    >>> d = 0.1
    >>> k = coulomb_constants([[-d/2, -d/2], [d/2, -d/2], [-d/2, d/2], [d/2, d/2]],
    ...                       [[1, 1], [-1, 1], [1, -1], [-1, -1]], weight=10.0, mu=0.5)
    >>> k.a.round(9).tolist(), k.b.round(9).tolist(), abs(k.f) < 1e-12
    ([[-100.0, 0.0], [0.0, -100.0]], [0.0, 0.0], True)
    """
    G, h = affine.all_in_contact_map(points, weight)
    return drive_constants(points, directions, G, h, weight, mu)


def coulomb_signs(A: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Spin pattern s in {-1, 0, 1}^m minimising |A s - want| (exhaustive for small m, else rounded least squares
    improved one wheel at a time)."""
    m = A.shape[1]
    useful = np.flatnonzero(np.any(A != 0, axis=0))
    s = np.zeros(m)
    if len(useful) <= EXHAUSTIVE_WHEELS:
        Au = A[:, useful]
        best, best_err = None, np.inf
        for pattern in itertools.product((-1.0, 0.0, 1.0), repeat=len(useful)):
            err = float(np.sum((Au @ pattern - want) ** 2))
            if best is None or err < best_err - 1e-15 * max(1.0, best_err):
                best, best_err = pattern, err
        s[useful] = best
        return s
    relaxed = lsq_linear(A, want, bounds=(-1.0, 1.0), method="bvls").x
    s = np.round(relaxed)
    err = float(np.sum((A @ s - want) ** 2))
    improved = True
    while improved:
        improved = False
        for j in useful:
            for value in (-1.0, 0.0, 1.0):
                if value == s[j]:
                    continue
                trial = float(np.sum((A @ s + A[:, j] * (value - s[j]) - want) ** 2))
                if trial < err - 1e-15 * max(1.0, err):
                    s[j], err, improved = value, trial, True
    return s


@dataclass(frozen=True)
class CoulombLaw(FrictionLaw):
    """The paper's Coulomb law (4.3): each wheel pushes with ``mu N_i`` along its drive direction, in the direction
    it spins; a stopped wheel pushes nothing. ``mu`` is dimensionless."""

    name: str = "coulomb"
    assumes_sliding = True

    def drive_vectors(self, velocities, drive_directions) -> np.ndarray:
        """Per-cell F (eq. 21): ``sum_k sign(V_i . u_k) u_k``."""
        return _coulomb_drive(f64(velocities), f64(drive_directions))

    def cell_forces(self, points, normal, velocities, drive_directions, mu, state) -> np.ndarray:
        """``mu N_i F_i`` (eq. 22), whatever the parcel's twist."""
        return mu * np.asarray(normal)[:, None] * self.drive_vectors(velocities, drive_directions)

    def constants(self, solution, velocities, drive_directions, mu) -> FrictionConstants:
        """Per-support-set constants (eqs. 20-29) from the drive vectors of eq. 21."""
        F = self.drive_vectors(velocities, drive_directions)
        return drive_constants(solution.points, F, solution.force_lin, solution.force_const, solution.weight, mu)

    drive_kernel = staticmethod(_coulomb_drive)
    """See :attr:`FrictionLaw.drive_kernel`: F of eq. 21."""

    def affine_damping(self, mu: float) -> float:
        """See :meth:`FrictionLaw.affine_damping`: none (the wheels push with mu N whatever the slip)."""
        return 0.0

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        """See :meth:`FrictionLaw.constants_and_row`; the drive vectors, sums and row in one compiled call."""
        terms = _coulomb_terms_and_row(f64(velocities), f64(drive_directions), solution.points, solution.force_lin,
                                       solution.force_const, float(mu), float(solution.weight), solution.origin,
                                       1.0 / mass, 1.0 / inertia)
        return FrictionConstants(terms[:24], 0.0, solution.weight), tuple(terms[24:].tolist())

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        """Two wheels a cell and normal forces summing to W (eqs. 3-5) bound the net force by ``2 mu W`` and the
        torque by ``2 mu W R``, so ``dS/dt <= k = 2 rate``: reach ``S0 T + k T^2 / 2``, speed ``S0 + k T`` (the
        wheels push whatever the parcel's speed, so neither ``wheel_speed`` nor ``lever`` tightens it)."""
        k = 2.0 * rate
        return s0 * window + 0.5 * k * window * window, s0 + k * window

    def piece_reach(self, rate, window, curve, drive, slip):
        """The cells push with ``mu N_i F_i``, ``F_i`` fixed by the wheels' spins (eqs. 20-21), so a point's
        acceleration is at most ``rate max|F_i| + curve``: ``(rate drive + curve) T^2 / 2``, zero acceleration on
        stopped wheels."""
        return 0.5 * (rate * drive + curve) * window ** 2

    def wheel_loads(self, speed, slip):
        """``sign(speed)``: each wheel pushes with ``mu N`` in its direction of spin (eq. 21)."""
        return np.sign(speed)

    def scaled_mu(self, mu, length):
        """Dimensionless: unchanged."""
        return mu

    def design_wheels(self, A, own, want, vmax):
        """Each wheel gives ``mu N`` times the sign of its spin (eq. 21): the best spin pattern
        (:func:`coulomb_signs`) at full speed ``vmax``."""
        s = coulomb_signs(A, want)
        return vmax * s, A @ s
