"""Stick-slip friction (the paper's Section 5 future work), solved as a complementarity problem at every time step.

Units: SI (m, s, kg, N, N s, J).

Each roller wheel is one friction contact: it pushes only along its drive direction ``u`` and lets the parcel slide
freely along its axle. With the cell's normal force ``N`` (paper 4.1, lift-off included), the impulse ``lam`` a wheel
gives in a step of length ``h`` satisfies

    |lam| <= B = mu N h,    slip s = J nu+ - w,    and   s > 0 => lam = -B,  s < 0 => lam = +B,  |lam| < B => s = 0,

where ``nu+`` is the parcel's twist after the step, ``J = [u_x, u_y, r x u]`` (``r`` from the centre of mass to the
wheel) and ``w`` the wheel's surface speed. ``mu`` is the static coefficient for a wheel that stuck in the previous step
and the kinetic one for a wheel that slid (judged by its slip after the step, not its impulse: see
:func:`remember`). With ``nu+ = nu + M^-1 J^T lam`` this is a box-constrained LCP, the optimality condition of
``min 1/2 lam^T A lam + (J nu - w)^T lam`` over the box (``A = J M^-1 J^T``); it is solved by projected
Gauss-Seidel, warm-started from the previous step, to a tolerance, with no regularisation. Then
``x+ = x + h nu+`` (semi-implicit Euler).

A parcel can therefore stick and move at exactly the wheel speed. While every wheel slides in its direction of spin,
each pushes with ``mu N`` along ``u``: the paper's Coulomb law (4.3). Energy is accounted exactly: the change of
kinetic energy over a step is the wheels' work ``sum lam w`` minus the friction dissipation ``-sum lam s`` (>= 0)
minus the step's own dissipation ``1/2 |nu+ - nu|_M^2`` (>= 0, vanishing as ``h -> 0``).
"""

from __future__ import annotations

import numpy as np

from virtual_vehicle.engine.stepping import Trajectory, fixed_steps
from virtual_vehicle.physics.laws import StickSlipLaw

__all__ = ["StickSlipLaw", "solve_contacts", "run_stick_slip"]


def _contacts(model, piece, y):
    """Per-wheel contact data at state y: Jacobian rows (m, 3), wheel speeds (m,), normal forces (m,), keys."""
    cells = model.cells
    support = piece.support
    N = piece.normal_forces(y)
    on = N > 0
    ids = support[on]
    N = N[on]
    r = cells.positions[ids] - y[:2]
    rows, speeds, normals, keys = [], [], [], []
    for k in range(2):
        has = cells.wheel_active[ids, k]  # a separate-wheel contact has only its own wheel
        u = cells.drive_directions[ids[has], k]
        rr = r[has]
        rows.append(np.column_stack([u[:, 0], u[:, 1], rr[:, 0] * u[:, 1] - rr[:, 1] * u[:, 0]]))
        speeds.append(np.einsum("ij,ij->i", model.velocities[ids[has]], u))
        normals.append(N[has])
        keys.extend((int(i), k) for i in ids[has])
    return np.vstack(rows), np.concatenate(speeds), np.concatenate(normals), keys


def masses(spec) -> np.ndarray:
    """(3,) generalised masses of a parcel: kg, kg, kg m^2."""
    return np.array([spec.mass, spec.mass, spec.inertia])


def wheel_problem(model, piece, y, h):
    """One step's wheel rows for ``model``'s parcel at state ``y``: Jacobians (m, 3), wheel speeds (m,) m/s, impulse
    bounds ``mu N h`` (m,) N s with the static coefficient for wheels that stuck in the previous step, warm start
    (m,), and the wheels' keys (cell, wheel)."""
    spec = model.spec
    mu_s = spec.mu_static if spec.mu_static is not None else spec.mu
    J, w, N, keys = _contacts(model, piece, y)
    memory = model.contact_memory  # persists across calls: a run split into control ticks stays one run
    stuck = memory["stuck"]
    bounds = np.array([mu_s if stuck.get(key, False) else spec.mu for key in keys]) * N * h
    lam0 = np.array([memory["lam"].get(key, 0.0) for key in keys])
    return J, w, bounds, lam0, keys


STUCK_SLIP = 1e-9
"""A wheel whose slip after a step is at most this fraction of the speed scale (its surface speed, the parcel's
speed there, 1 mm/s) stuck in that step."""


def remember(model, keys, lam, slip, w) -> None:
    """Store each wheel's impulse and whether it stuck for the next step. A wheel stuck when its slip after the step
    (``slip``, m/s, with surface speeds ``w``) is zero, whatever its impulse: a redundant sticking wheel may sit at
    its bound in the solver's force distribution while the wrench the sticking wheels supply is well inside what
    they can hold, and judged by its impulse it would lose its static bound although it never slid (the grip then
    broke early and the law did not converge when mu_static > mu; the exact rule is the zonotope's,
    :mod:`virtual_vehicle.physics.stick_modes`)."""
    scale = np.maximum(np.maximum(np.abs(w), np.abs(slip + w)), 1e-3)
    model.contact_memory["stuck"] = dict(zip(keys, (np.abs(slip) <= STUCK_SLIP * scale).tolist()))
    model.contact_memory["lam"] = dict(zip(keys, lam.tolist()))


def new_account() -> dict:
    """An empty energy account (J) and solver record for one parcel."""
    return {"wheel_work": 0.0, "friction_dissipation": 0.0, "step_dissipation": 0.0, "contact_work": 0.0,
            "sweeps_max": 0, "unconverged_steps": 0}


def account(acc: dict, lam, slip, w, dnu, mass) -> None:
    """Add one step's energy flows: the wheels' work ``lam . w``, friction dissipation ``-lam . slip`` (>= 0) and
    the step's own dissipation ``1/2 |dnu|_M^2`` (>= 0)."""
    acc["wheel_work"] += float(lam @ w)
    acc["friction_dissipation"] += float(-(lam @ slip))
    acc["step_dissipation"] += 0.5 * float(mass @ dnu ** 2)


def solve_contacts(J, w, bounds, nu, minv, lam0, max_sweeps: int, tol: float):
    """Projected Gauss-Seidel for the box LCP of one step. Returns (lam, nu_plus, sweeps, converged).

    ``J`` (m, 3), ``w`` (m,) wheel speeds, ``bounds`` (m,) impulse limits, ``nu`` (3,) twist before the step,
    ``minv`` (3,) inverse mass and inertia, ``lam0`` (m,) warm start.
    """
    lam = np.clip(lam0, -bounds, bounds)
    nu_p = nu + minv * (J.T @ lam)
    Jl = J.tolist()
    wl = w.tolist()
    bl = bounds.tolist()
    ll = lam.tolist()
    m0, m1, m2 = (float(v) for v in minv)
    v0, v1, v2 = (float(v) for v in nu_p)
    diag = [m0 * a * a + m1 * b * b + m2 * c * c for a, b, c in Jl]
    scale = max(max(bl, default=0.0), 1e-300)
    for sweep in range(1, max_sweeps + 1):
        change = 0.0
        for j, (a, b, c) in enumerate(Jl):
            if bl[j] == 0.0:
                continue
            s = a * v0 + b * v1 + c * v2 - wl[j]
            new = ll[j] - s / diag[j]
            new = -bl[j] if new < -bl[j] else bl[j] if new > bl[j] else new
            d = new - ll[j]
            if d:
                ll[j] = new
                v0 += m0 * a * d
                v1 += m1 * b * d
                v2 += m2 * c * d
                change = max(change, abs(d))
        if change <= tol * scale:
            return np.array(ll), np.array([v0, v1, v2]), sweep, True
    return np.array(ll), np.array([v0, v1, v2]), max_sweeps, False


def run_stick_slip(model, y0, t0, t1, sample_times, progress, *, dt):
    """Time-step one parcel under :class:`~virtual_vehicle.physics.laws.StickSlipLaw` from ``t0`` to ``t1`` (s) at
    step ``dt`` (s).

    Returns a :class:`~virtual_vehicle.engine.stepping.Trajectory` whose ``stats`` hold the energy account (J):
    ``wheel_work``, ``friction_dissipation``, ``step_dissipation``, ``kinetic_start``, ``kinetic_end``, and the
    solver's ``sweeps_max`` and ``unconverged_steps``.
    """
    limits = model.law.stepper_options()
    mass = masses(model.spec)
    minv = 1.0 / mass
    acc = new_account()

    def step(piece, t, y, h):
        J, w, bounds, lam0, keys = wheel_problem(model, piece, y, h)
        nu = y[3:]
        lam, nu_p, sweeps, ok = solve_contacts(J, w, bounds, nu, minv, lam0, limits.max_sweeps, limits.tolerance)
        acc["sweeps_max"] = max(acc["sweeps_max"], sweeps)
        acc["unconverged_steps"] += not ok
        slip = J @ nu_p - w
        account(acc, lam, slip, w, nu_p - nu, mass)
        remember(model, keys, lam, slip, w)
        return np.concatenate([y[:3] + h * nu_p, nu_p])  # semi-implicit Euler

    times, states, events, status, t, steps = fixed_steps(model, y0, t0, t1, dt, sample_times, progress, step)
    y = states[-1]
    stats = {**acc, "kinetic_start": 0.5 * float(mass @ np.asarray(y0, dtype=float)[3:] ** 2),
             "kinetic_end": 0.5 * float(mass @ y[3:] ** 2), "pieces_cached": model.pieces_cached,
             "solves": model.solves}
    return Trajectory(times, states, events, status, t, steps, 0, stats)
