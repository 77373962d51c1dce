"""Stick-slip friction (paper Section 5) as a per-step complementarity problem (fixed mode; event mode runs it
exactly, tests/test_stick_events.py): sticking at exactly the wheel speed,
stopping on stopped wheels, exact energy accounting, and the paper's Coulomb law while every wheel slides."""

import numpy as np
import pytest

from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.engine.stickslip import solve_contacts
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws

G = 9.81


def model(cells, spec, field, law=None):
    return ParcelModel(cells, spec, field.velocities(cells), law or laws.StickSlipLaw(), G)


def test_uniform_field_accelerates_then_rides_at_exactly_wheel_speed():
    mu, w, dt = 0.5, 0.3, 1e-3
    cells = layout.grid(30, 6, 0.1)
    m = model(cells, parcel.rectangle(0.35, 0.25, 1.0, mu), fields.Uniform((w, 0.0)))
    tr = integrate(m, [0.3, 0.25, 0, 0, 0, 0], 0, 1.0, dt=dt, sample_dt=dt, mode="fixed")
    v = tr.states[:, 3]
    assert v.max() <= w + 1e-12  # no overshoot
    t_star = w / (mu * G)
    after = tr.times > t_star + 2 * dt
    np.testing.assert_allclose(v[after], w, atol=1e-12)  # stuck: exactly the wheel speed
    before = tr.times < t_star - 2 * dt
    np.testing.assert_allclose(v[before], mu * G * tr.times[before], atol=mu * G * dt)  # Coulomb acceleration
    x_exact = 0.3 + np.where(tr.times < t_star, 0.5 * mu * G * tr.times**2, w * tr.times - 0.5 * w * t_star)
    np.testing.assert_allclose(tr.states[:, 0], x_exact, atol=2 * w * dt)
    assert np.abs(tr.states[:, [1, 2, 4, 5]] - [0.25, 0, 0, 0]).max() < 1e-12
    assert tr.stats["unconverged_steps"] == 0


def test_stopped_wheels_decelerate_and_stop():
    mu, v0, dt = 0.4, 0.5, 1e-3
    cells = layout.grid(30, 6, 0.1)
    m = model(cells, parcel.rectangle(0.35, 0.25, 2.0, mu), fields.Uniform((0.0, 0.0)))
    tr = integrate(m, [0.3, 0.25, 0, v0, 0, 0], 0, 0.5, dt=dt, sample_dt=dt, mode="fixed")
    t_stop = v0 / (mu * G)
    v = tr.states[:, 3]
    assert v.min() >= -1e-12  # never reverses (to the solver's tolerance)
    np.testing.assert_allclose(v[tr.times > t_stop + dt], 0.0, atol=1e-12)
    np.testing.assert_allclose(tr.states[-1, 0], 0.3 + v0**2 / (2 * mu * G), atol=v0 * dt)


def test_energy_is_accounted_for_exactly():
    """With rotation, lift-offs and support changes: kinetic energy gained = wheel work - friction dissipation -
    step dissipation, each dissipation >= 0, so the parcel never gains more than the wheels supplied."""
    cells = layout.grid(10, 8, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.3, 0.45, mu_static=0.6)
    m = model(cells, spec, fields.Inward((0.45, 0.35), 0.4))
    tr = integrate(m, [0.3, 0.25, 0.4, 0.2, -0.1, 1.5], 0, 1.5, dt=5e-4, mode="fixed")
    s = tr.stats
    gained = s["kinetic_end"] - s["kinetic_start"]
    assert s["friction_dissipation"] >= 0 and s["step_dissipation"] >= 0
    np.testing.assert_allclose(gained, s["wheel_work"] - s["friction_dissipation"] - s["step_dissipation"],
                               atol=1e-12 * max(1.0, abs(s["wheel_work"])))
    assert gained <= s["wheel_work"] + 1e-12
    assert len(tr.events) > 0 and tr.status == "completed"


def test_reduces_to_the_papers_coulomb_law_while_sliding():
    """Wheels much faster than the parcel never let it stick: the trajectory converges (first order in dt) to the
    event-driven Coulomb solution."""
    d = 0.1
    cells = layout.grid(2, 2, d, origin=(-d / 2, -d / 2))
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.5)
    field = fields.Inward((0, 0), 2.0)
    y0 = [0.02, -0.01, 0.1, 0, 0, 0]
    ref = integrate(model(cells, spec, field, laws.CoulombLaw()), y0, 0, 0.5, sample_dt=0.01).states
    errs = []
    for dt in (2e-3, 5e-4, 1.25e-4):
        st = integrate(model(cells, spec, field), y0, 0, 0.5, dt=dt, sample_dt=0.01, mode="fixed").states
        errs.append(np.abs(st - ref)[:, :2].max())
    assert errs[0] > errs[1] > errs[2] and errs[2] < 2e-4, errs
    assert errs[0] / errs[2] > 8  # ~first order over a factor 16 in dt


def test_static_friction_holds_what_kinetic_friction_would_not():
    """Two wheels on one contact pull against each other: the rigid parcel cannot follow both. Projected
    Gauss-Seidel finds the exact box-LCP solution (compared with brute force over the slip states)."""
    J = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    w = np.array([0.2, -0.2])
    minv = np.array([1.0, 1.0, 1.0])
    nu = np.zeros(3)
    # bounds large enough: the parcel sticks between them at the speed that balances the two impulses
    lam, nu_p, _, ok = solve_contacts(J, w, np.array([10.0, 10.0]), nu, minv, np.zeros(2), 1000, 1e-14)
    assert ok and abs(lam.sum() - nu_p[0]) < 1e-12
    # bounds small: both slide, each at its bound, opposite signs: the net impulse is zero
    lam, nu_p, _, ok = solve_contacts(J, w, np.array([0.01, 0.01]), nu, minv, np.zeros(2), 1000, 1e-14)
    assert ok and np.allclose(lam, [0.01, -0.01]) and abs(nu_p[0]) < 1e-15


def test_mu_static_is_validated():
    with pytest.raises(ValueError, match="mu_static"):
        parcel.rectangle(0.3, 0.2, 1.0, 0.5, mu_static=0.4)


def test_a_run_split_into_ticks_is_the_same_run():
    """Sticking with mu_static > mu must survive control-tick boundaries: integrating tick by tick (as the
    co-simulation does, through with_velocities) gives the single run's trajectory."""
    cells = layout.grid(10, 8, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.3, 0.3, mu_static=0.6)
    V = fields.Inward((0.45, 0.35), 0.2).velocities(cells)
    y0 = np.array([0.42, 0.33, 0.2, 0.0, 0.0, 0.0])
    whole = integrate(ParcelModel(cells, spec, V, laws.StickSlipLaw(), G), y0, 0, 0.5, dt=1e-3, sample_dt=0.01,
                      mode="fixed")
    base = ParcelModel(cells, spec, V, laws.StickSlipLaw(), G)
    y = y0
    for k in range(50):
        y = integrate(base.with_velocities(V), y, k * 0.01, (k + 1) * 0.01, dt=1e-3, sample_dt=0.01,
                      mode="fixed").states[-1]
    np.testing.assert_allclose(y, whole.states[-1], atol=1e-10)


def test_summary_reports_energy_and_solver_health():
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import run

    sc, _ = load_scenario("stick_slip_pickup")
    p = run(sc.build()).summary()["parcels"][0]
    e = p["energy_J"]
    assert p["stick_slip_unconverged_steps"] == 0
    np.testing.assert_allclose(e["kinetic_end"] - e["kinetic_start"],
                               e["wheel_work"] - e["friction_dissipation"] - e["step_dissipation"], atol=1e-12)
    np.testing.assert_allclose(e["kinetic_end"], 0.5 * 1.0 * 0.3**2, rtol=1e-9)  # riding at the wheel speed
