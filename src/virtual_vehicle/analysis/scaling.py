"""Scalability (paper Section 1): the same scenario from micro-scale cells to metre cells, and what stays the same.

Units: SI throughout (m, s, kg); scale factors are dimensionless.

Gravity is the same at every scale, so a family of similar runs keeps the Froude number ``V^2 / (g L)`` and the
friction coefficients fixed: with lengths scaled by ``s``, times and speeds scale by ``sqrt(s)``, masses by any
factor ``m`` (every force on a parcel is proportional to its weight), inertias by ``m s^2``, spins by
``1 / sqrt(s)``. The paper's Coulomb law (eq. 22: ``mu N`` per wheel, ``mu`` dimensionless) and the stick-slip law
are then similar as they stand; the viscous law (eq. 30, ``mu`` in s/m) needs ``mu`` scaled by ``1 / sqrt(s)``.
In units of the pitch ``L`` and the time ``sqrt(L / g)`` every trajectory of the family is the same curve.

:func:`scale_scenario` makes a member of the family from any constant-field scenario; :func:`dimensionless`
turns a trajectory into those units. A networked run is not scaled: its network keeps real time (baud rate, polls),
which does not scale with the parcels, so similarity does not hold for it.
"""

from __future__ import annotations

import math

import numpy as np

from virtual_vehicle.config.scenario import Scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.physics.laws import law_named

# Dimensions as (length, time, mass) exponents, by field name within each table.
_L, _T, _V, _W = (1, 0, 0), (0, 1, 0), (1, -1, 0), (0, -1, 0)  # length, time, speed, spin
_M, _I = (0, 0, 1), (2, 0, 1)
_ARRAY = {"pitch": _L, "origin": _L, "points": _L, "wheel_offsets": _L, "wheel_radius": _L}
_BELT = {"start": _L, "end": _L, "width": _L, "speed": _V, "spacing": _L}
_FIELD = {"velocity": _V, "velocities": _V, "center": _L, "speed": _V, "point": _L, "along": _V, "omega": _W,
          "twist": (_V, _V, _W), "outline": _L}
_PARCEL = {"length": _L, "width": _L, "vertices": _L, "com": _L, "mass": _M, "inertia": _I, "x": _L, "y": _L,
           "vx": _V, "vy": _V, "omega": _W, "t_start": _T}
_TOP = {"duration": _T, "output_dt": _T}
_INTEGRATOR = {"dt": _T, "max_step": _T, "atol": _L}
_CONTACTS = {"margin": _L, "slop": _L, "window": _T, "min_window": _T}
_SENSORS = {"offsets": _L}


def _factor(dim, s: float, m: float) -> float:
    a, b, c = dim
    return s ** a * math.sqrt(s) ** b * m ** c


def _scaled(value, dim, s: float, m: float):
    if value is None:
        return None
    if isinstance(dim, tuple) and dim and isinstance(dim[0], tuple):  # per-component dimensions
        return [_scaled(v, d, s, m) for v, d in zip(value, dim)]
    if isinstance(value, (list, tuple)):
        return [_scaled(v, dim, s, m) for v in value]
    return float(value) * _factor(dim, s, m)


def _table(data: dict, dims: dict, s: float, m: float) -> dict:
    return {k: (_scaled(v, dims[k], s, m) if k in dims else v) for k, v in data.items()}


def _field(data: dict, s: float, m: float) -> dict:
    out = _table(data, _FIELD, s, m)
    if "regions" in data:
        out["regions"] = [{"outline": _scaled(r["outline"], _L, s, m), "field": _field(r["field"], s, m)}
                          for r in data["regions"]]
    if data.get("default") is not None:
        out["default"] = _field(data["default"], s, m)
    return out


def scale_scenario(scenario: Scenario, length: float, mass: float = 1.0, name: str | None = None) -> Scenario:
    """The member of ``scenario``'s similarity family with every length times ``length`` and every mass times
    ``mass`` (both > 0): times and speeds times ``sqrt(length)``, inertias times ``mass length^2``, spins divided by
    ``sqrt(length)``, the viscous ``mu`` (s/m) divided by ``sqrt(length)``; gravity, headings and dimensionless
    coefficients unchanged; the integrator's ``atol`` scaled as a length. Raises ScenarioError for what cannot be
    scaled (networked runs, motor-driven wheels) and for a scaled value outside a field's limits (naming it).

    >>> from virtual_vehicle.config.scenario import load_scenario
    >>> small = scale_scenario(load_scenario("paper_2x2_inward")[0], 0.01, 1e-3)
    >>> small.array.pitch, round(small.duration, 6)
    (0.001, 0.2)
    """
    if not (math.isfinite(length) and length > 0 and math.isfinite(mass) and mass > 0):
        raise ScenarioError("scale", f"length and mass factors must be positive numbers, got {length}, {mass}")
    if scenario.control is not None:
        raise ScenarioError("control", "networked runs are not similar at other scales (the network keeps real "
                            "time); scale a constant-field scenario")
    if scenario.wheels.model == "motor":
        raise ScenarioError("wheels.model", "motor-driven wheels have their own time constants; scale ideal wheels")
    s, m = float(length), float(mass)
    data = scenario.model_dump(exclude_none=True)
    data = _table(data, _TOP, s, m)
    data["name"] = name or f"{scenario.name}_x{s:g}"
    data["array"] = _table(data["array"], _ARRAY, s, m)
    data["array"]["belts"] = [_table(b, _BELT, s, m) for b in data["array"].get("belts", [])]
    data["field"] = _field(data["field"], s, m)
    law = law_named(scenario.friction.law)
    parcels = []
    for p in data["parcels"]:
        q = _table(p, _PARCEL, s, m)
        if "mu" in p:
            q["mu"] = law.scaled_mu(p["mu"], s)  # in the law's units: dimensionless, or s/m (eq. 30)
        parcels.append(q)
    data["parcels"] = parcels
    data["integrator"] = _table(data["integrator"], _INTEGRATOR, s, m)
    data["contacts"] = _table(data["contacts"], _CONTACTS, s, m)
    data["sensors"] = _table(data["sensors"], _SENSORS, s, m)
    return parse_scenario(data)


def dimensionless(times: np.ndarray, states: np.ndarray, length: float, gravity: float = 9.81):
    """``times`` (s) and ``states`` ((k, 6): x, y (m), theta (rad), vx, vy (m/s), omega (rad/s)) in units of the
    length ``length`` (m) and the time ``sqrt(length / gravity)`` (s). Returns (tau, states)."""
    T = math.sqrt(length / gravity)
    factors = np.array([1 / length, 1 / length, 1.0, T / length, T / length, T])
    return np.asarray(times, dtype=float) / T, np.asarray(states, dtype=float) * factors


def similarity_study(scenario: Scenario, factors, progress=None) -> list[dict]:
    """Run ``scenario`` scaled by each (length, mass) pair of ``factors`` and compare every parcel's trajectory, in
    units of the pitch and ``sqrt(pitch / g)``, with that of the first pair. Returns one row per pair: the factors,
    the pitch (m), a parcel's mass (kg), the wall time (s), the largest dimensionless deviation from the first run
    (``max_deviation``, over positions, heading and velocities at the common samples) and, for plotting, the
    dimensionless samples of the first parcel (``tau``, ``states``)."""
    from virtual_vehicle.run.sim import run

    rows, reference = [], None
    for k, (s, m) in enumerate(factors):
        member = scale_scenario(scenario, s, m)
        result = run(member.build())
        L = member.array.pitch or result.setup.cells.pitch
        curves = [dimensionless(p.trajectory.times, p.trajectory.states, L, member.gravity) for p in result.parcels]
        if reference is None:
            reference = curves
        deviation = 0.0
        for (tau, st), (tau0, st0) in zip(curves, reference):
            n = min(len(tau), len(tau0))
            if n and not np.allclose(tau[:n], tau0[:n], rtol=1e-9, atol=1e-9):
                raise ScenarioError("scale", "the scaled runs were sampled at different dimensionless times")
            deviation = max(deviation, float(np.max(np.abs(st[:n] - st0[:n]))) if n else 0.0)
        rows.append({"length_factor": s, "mass_factor": m, "pitch_m": L, "mass_kg": member.parcels[0].mass,
                     "duration_s": member.duration, "wall_s": result.wall_time, "max_deviation": deviation,
                     "tau": curves[0][0], "states": curves[0][1]})
        if progress is not None:
            progress(k + 1)
    return rows
