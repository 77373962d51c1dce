"""Field design (paper Section 5, "how to design wheel-velocity fields for desired motions"): the wheel speeds under
one parcel that give it a desired twist or wrench, within the wheels' speed limit.

Units: SI (m, s, N, N m, rad, m/s, rad/s).

- A *twist* (vx, vy, omega) is asked of the wheels directly: each supporting cell drives at the parcel's rigid-body
  velocity over it (:class:`~virtual_vehicle.model.fields.Twist`). Under the viscous law (eq. 30) and the stick-slip law
  a parcel moving with that twist feels no force, so the twist is the steady state; the Coulomb law of the paper has
  no such state (its force does not depend on the parcel's speed), so use a wrench there.
- A *wrench* (fx, fy, tau about the centre of mass) is linear in what each wheel does: wheel k of supporting cell i
  adds ``mu N_i s_ik [u, r_i x u]`` with ``u`` its drive direction and ``r_i`` the lever from the centre of mass
  (eqs. 22, 24 and 30, 34). Viscous: ``s`` is the wheel speed less the parcel's own speed along ``u``, so the
  wrench is affine in the wheel speeds, solved as bounded least squares (scipy's ``lsq_linear``) within +-vmax.
  Coulomb (and stick-slip while the wheels slide, which is the Coulomb law): ``s`` is the sign of the wheel's spin,
  -1, 0 or 1; small supports (up to 10 wheels) are searched exhaustively, larger ones by bounded least squares
  rounded and improved one wheel at a time (a local optimum, reported with its residual).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virtual_vehicle.engine.dynamics import ParcelModel
from virtual_vehicle.model.fields import Twist
from virtual_vehicle.model.layout import CellArray
from virtual_vehicle.model.parcel import ParcelSpec
from virtual_vehicle.physics.laws import LAWS, FrictionLaw

_GEOMETRY = LAWS["coulomb"]
"""The law of the models that only find supports and normal forces here (which do not depend on the law)."""


@dataclass
class Design:
    """Designed wheel speeds for one parcel.

    Attributes:
        velocities: (n, 2) cell surface velocities, m/s (zero away from the parcel).
        wheel_speeds: (n, 2) surface speed of each wheel along its drive direction, m/s.
        support: ids of the cells under the parcel.
        requested: the twist or wrench asked for. achieved: the wrench (N, N, N m) the design gives the parcel in its
            current state (for a twist design: the twist delivered, after ``scale``).
        residual: |achieved - requested| (wrench designs; 0 for twist designs).
        scale: a twist design is scaled down by this factor (<= 1) to keep every wheel within ``vmax``.
    """

    velocities: np.ndarray
    wheel_speeds: np.ndarray
    support: np.ndarray
    requested: np.ndarray
    achieved: np.ndarray
    residual: float
    scale: float = 1.0


def twist_design(cells: CellArray, spec: ParcelSpec, state, twist, vmax: float = np.inf) -> Design:
    """Wheel speeds under the parcel at ``state`` for the twist ``twist`` = (vx, vy m/s of its centre of mass,
    omega rad/s), scaled down uniformly if a wheel would exceed ``vmax`` (m/s)."""
    state = np.asarray(state, dtype=float)
    model = ParcelModel(cells, spec, np.zeros((cells.n, 2)), _GEOMETRY)
    support = model.support_at(state)
    want = np.asarray(twist, dtype=float)
    field = Twist((float(state[0]), float(state[1])), tuple(want)).velocities(cells)
    speeds = np.zeros((cells.n, 2))
    speeds[support] = np.einsum("ij,ikj->ik", field[support], cells.active_directions[support])
    peak = float(np.max(np.abs(speeds))) if len(support) else 0.0
    scale = 1.0 if peak <= vmax else vmax / peak
    speeds *= scale
    velocities = np.einsum("ik,ikj->ij", speeds, cells.active_directions)
    return Design(velocities, speeds, support, want, scale * want, 0.0, scale)


def wrench_matrix(cells: CellArray, spec: ParcelSpec, state, gravity: float = 9.81):
    """(3, 2m) map from what the m supporting cells' wheels do to the wrench on the parcel (N, N, N m per unit),
    the supporting cells, and the normal forces (N) at ``state`` (paper eqs. 3-19 with lift-off)."""
    state = np.asarray(state, dtype=float)
    model = ParcelModel(cells, spec, np.zeros((cells.n, 2)), _GEOMETRY, gravity)
    piece = model.piece_at(state)
    support, N = piece.support, piece.normal_forces(state)
    U = cells.active_directions[support]  # (m, 2, 2)
    r = cells.positions[support] - state[:2]
    cols = []
    for i in range(len(support)):
        for k in range(2):
            u = U[i, k]
            cols.append(spec.mu * N[i] * np.array([u[0], u[1], r[i, 0] * u[1] - r[i, 1] * u[0]]))
    return np.array(cols).T, support, N


def wrench_design(cells: CellArray, spec: ParcelSpec, state, wrench, law: FrictionLaw, vmax: float,
                  gravity: float = 9.81) -> Design:
    """Wheel speeds (within +-``vmax`` m/s) under the parcel at ``state`` whose wrench on it is as close as possible
    to ``wrench`` = (fx, fy N, tau N m about the centre of mass), for the ``law`` (see the module notes)."""
    if not vmax > 0:
        raise ValueError("vmax must be positive (m/s)")
    state = np.asarray(state, dtype=float)
    want = np.asarray(wrench, dtype=float)
    A, support, N = wrench_matrix(cells, spec, state, gravity)
    U = cells.active_directions[support].reshape(-1, 2)
    r = np.repeat(cells.positions[support] - state[:2], 2, axis=0)
    v_cell = state[3:5] + state[5] * np.column_stack([-r[:, 1], r[:, 0]])  # parcel velocity over each cell
    own = np.einsum("ij,ij->i", v_cell, U)  # the parcel's own speed along each wheel
    x, achieved = law.design_wheels(A, own, want, vmax)
    speeds = np.zeros((cells.n, 2))
    speeds[support] = x.reshape(-1, 2)
    velocities = np.einsum("ik,ikj->ij", speeds, cells.active_directions)
    return Design(velocities, speeds, support, want, achieved, float(np.linalg.norm(achieved - want)))

