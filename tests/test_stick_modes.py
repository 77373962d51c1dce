"""Exact event-driven stick-slip of one parcel on one support set (physics.stick_modes), checked against what it did
not write: the pickup's closed form, the fixed-step complementarity law (engine.stickslip) as dt -> 0, an LP for the
zonotope rule, the paper's Coulomb constants, the energy balance, and the symmetries of the plane."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.engine.stickslip import solve_contacts
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import contact, laws
from virtual_vehicle.physics.stick_modes import Wheels, decide_mode, mode_rhs, simulate, wheels_on

G = 9.81
D = 0.1
SQUARE = layout.grid(2, 2, D, origin=(-D / 2, -D / 2))  # four cells a 0.3 m square parcel always covers near (0, 0)
BOX = parcel.rectangle(0.3, 0.3, 1.0, 0.4, mu_static=0.5)


def on(cells, com, spec, V, **kw):
    """Wheels of every cell of ``cells`` under a parcel of ``spec`` at ``com``."""
    sol = contact.solve_support(cells.positions, com, spec.weight(G))
    return wheels_on(cells, np.arange(cells.n), sol, V, spec.mu, spec.mu_static, **kw)


def rot(phi):
    return np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])


def test_pickup_closed_form():
    """stick_slip_pickup: a carton set down at rest on rollers at v accelerates at mu_k g until t = v / (mu_k g),
    then rides at exactly v; one stick event; half the wheels' work is lost to friction."""
    setup = load_scenario("stick_slip_pickup")[0].build()
    spec, y0, cells, V = setup.specs[0], setup.states[0], setup.contact_layer, setup.velocities
    g = setup.scenario.gravity
    model = ParcelModel(cells, spec, V, setup.law, g)
    piece = model.piece_at(y0)
    wheels = wheels_on(cells, piece.support, piece.solution, V, spec.mu, spec.mu_static)
    v, mu = 0.3, spec.mu
    t_star = v / (mu * g)
    run = simulate(wheels, y0, 0.0, 2 * t_star, spec.mass, spec.inertia)
    assert len(run.events) == 1 and run.events[0].kind == "slip"
    np.testing.assert_allclose(run.events[0].time, t_star, rtol=1e-10)
    assert len(run.events[0].after.stick) == wheels.m  # every wheel sticks: the parcel rides
    ts = np.linspace(0, 2 * t_star, 41)
    states = run.state(ts)
    x = y0[0] + np.where(ts < t_star, 0.5 * mu * g * ts**2, v * ts - 0.5 * v * t_star)
    np.testing.assert_allclose(states[:, 0], x, atol=1e-11)
    np.testing.assert_allclose(states[:, 3], np.minimum(mu * g * ts, v), atol=1e-11)
    np.testing.assert_allclose(states[ts > t_star, 3], v, atol=1e-14)  # exactly the wheel speed
    assert np.abs(states[:, [1, 2, 4, 5]] - [y0[1], y0[2], 0, 0]).max() < 1e-14
    np.testing.assert_allclose([run.wheel_work, run.dissipation, run.kinetic_end], [v**2, v**2 / 2, v**2 / 2],
                               rtol=1e-9)


def _twist_scene():
    V = fields.Twist((0.01, 0.0), (0.05, -0.03, 1.0)).velocities(SQUARE)
    y0 = np.array([0.01, -0.005, 0.1, -0.1, 0.05, -0.5])
    return V, y0


def test_fixed_step_law_converges_at_first_order():
    """The per-step box LCP of engine.stickslip, run at dt, dt/2, dt/4, dt/8, approaches the exact solution with
    observed order 1 through three stick events (the wheels under the parcel never change)."""
    V, y0 = _twist_scene()
    model = ParcelModel(SQUARE, BOX, V, laws.StickSlipLaw(), G)
    piece = model.piece_at(y0)
    run = simulate(wheels_on(SQUARE, piece.support, piece.solution, V, BOX.mu, BOX.mu_static), y0, 0, 0.3,
                   BOX.mass, BOX.inertia)
    assert [e.kind for e in run.events] == ["slip"] * 3
    assert len(run.events[-1].after.stick) == 8  # the field is rigid: it ends riding it
    ts = np.linspace(0, 0.3, 31)
    ref = run.state(ts)
    errs = []
    for dt in (4e-4, 2e-4, 1e-4, 5e-5):
        tr = integrate(ParcelModel(SQUARE, BOX, V, laws.StickSlipLaw(), G), y0, 0, 0.3, dt=dt, sample_times=ts,
                       mode="fixed")
        assert len(tr.events) == 0  # the same support set throughout
        errs.append(np.abs(tr.states - ref).max())
    order = np.log2(np.array(errs[:-1]) / errs[1:])
    assert np.all(np.abs(order - 1) < 0.1), (errs, order)


def _kicked_turn(mu_static):
    """Wheels turning the parcel about a point 2 cm off its centre, but one cell's wheels faster along x: that cell
    slips and the other seven wheels ride until the centripetal wrench breaks their grip, twice."""
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.4, mu_static=mu_static)
    V = fields.Twist((0.02, 0.0), (0, 0, 8.0)).velocities(SQUARE) + [[0, 0], [0, 0], [0, 0], [0.3, 0]]
    return spec, V, np.array([0, 0, 0, 0, -8.0 * 0.02, 8.0])


def test_fixed_step_law_converges_through_stick_breaks():
    """With redundant sticking wheels breaking away twice (mu_s = mu_k), the stepped law still approaches the
    exact solution at first order: it breaks where the wrench leaves the zonotope."""
    spec, V, y0 = _kicked_turn(0.4)
    T = 0.41
    run = simulate(on(SQUARE, y0[:2], spec, V), y0, 0, T, spec.mass, spec.inertia)
    assert [e.kind for e in run.events] == ["stick", "stick"] and len(run.events[0].before.stick) == 7
    ts = np.linspace(0, T, 42)
    ref = run.state(ts)
    errs = [np.abs(integrate(ParcelModel(SQUARE, spec, V, laws.StickSlipLaw(), G), y0, 0, T, dt=dt, mode="fixed",
                             sample_times=ts).states - ref).max() for dt in (2e-4, 1e-4, 5e-5)]
    order = np.log2(np.array(errs[:-1]) / errs[1:])
    assert np.all(np.abs(order - 1) < 0.1), (errs, order)


def test_a_lift_off_ends_the_run_where_the_engine_sees_it():
    """The reference holds one support set: it stops where a cell's normal force reaches zero, which is where the
    engine (stepped) lifts that cell off, and a fresh support solve there finds that cell unloaded."""
    spec, V, y0 = _kicked_turn(0.4)
    run = simulate(on(SQUARE, y0[:2], spec, V), y0, 0, 0.6, spec.mass, spec.inertia)
    assert run.status == "support" and run.events[-1].kind == "support"
    lifted = run.events[-1].index // 2  # the wheel's cell (two wheels a cell)
    forces = contact.solve_support(SQUARE.positions, run.y_end[:2], spec.weight(G)).forces(run.y_end[:2])
    assert abs(forces[lifted]) < 1e-9 * spec.weight(G) and (np.delete(forces, lifted) > 0.1).all()
    dt = 1e-4
    first = integrate(ParcelModel(SQUARE, spec, V, laws.StickSlipLaw(), G), y0, 0, 0.6, dt=dt,
                      mode="fixed").events[0]
    assert first.lifted == (lifted,) and abs(first.t - run.t_end) <= dt


def test_energy_account_closes():
    """Wheel work = kinetic energy gained + dissipation, dissipation >= 0, through stick and slip events."""
    V, y0 = _twist_scene()
    run = simulate(on(SQUARE, y0[:2], BOX, V), y0, 0, 0.3, BOX.mass, BOX.inertia)
    assert run.dissipation > 0 and len(run.events) == 3
    gained = run.kinetic_end - run.kinetic_start
    assert abs(run.wheel_work - gained - run.dissipation) <= 1e-8 * abs(run.wheel_work)


def _ramped_rotation():
    """Wheels turning a rigid rotation about a point off the parcel's centre, spinning up at ALPHA rad/s^2: the
    parcel rides until its centripetal and tangential wrench leaves what its wheels can hold."""
    c, w0, alpha = np.array([0.02, 0.0]), 3.0, 10.0
    V = fields.Twist(tuple(c), (0, 0, w0)).velocities(SQUARE)
    A = fields.Twist(tuple(c), (0, 0, alpha)).velocities(SQUARE)
    y0 = np.array([0, 0, 0, 0, -w0 * c[0], w0])
    return c, w0, alpha, on(SQUARE, y0[:2], BOX, V, accelerations=A), y0


def test_stick_breaks_where_an_lp_says_the_wrench_leaves_the_zonotope():
    """The break of a redundant (8-wheel) stick: its time is where no wheel forces within the static bounds supply
    the rigid motion's wrench (an LP on the closed-form rigid motion), and the wheels that break slip."""
    c, w0, alpha, wheels, y0 = _ramped_rotation()
    run = simulate(wheels, y0, 0, 1.1, BOX.mass, BOX.inertia)
    first = run.events[0]
    assert first.kind == "stick" and len(first.before.stick) == 8 and 0 < len(first.after.stick) < 8

    def holds(t):  # the rigid motion's wrench inside the box of static wheel forces?
        phi, om = w0 * t + alpha * t * t / 2, w0 + alpha * t
        r = rot(phi) @ (y0[:2] - c)
        a = alpha * np.array([-r[1], r[0]]) - om**2 * r
        F = [BOX.mass * a[0], BOX.mass * a[1], BOX.inertia * alpha]
        b = wheels.mu_static * wheels.normal(c + r)
        return linprog(np.zeros(8), A_eq=wheels.rows(c + r).T, b_eq=F, bounds=list(zip(-b, b))).status == 0

    lo, hi = 0.0, 1.1
    while hi - lo > 1e-10:
        lo, hi = ((lo + hi) / 2, hi) if holds((lo + hi) / 2) else (lo, (lo + hi) / 2)
    assert abs(first.time - lo) < 1e-7, (first.time, lo)
    gained = run.kinetic_end - run.kinetic_start
    assert abs(run.wheel_work - gained - run.dissipation) <= 1e-8 * abs(run.wheel_work) and run.dissipation > 0


def test_fixed_step_law_obeys_the_zonotope_rule_not_minimum_norm_forces():
    """Redundant sticking wheels hold while the wrench they must supply lies in their zonotope, even where the
    minimum-norm forces would exceed a wheel's bound; the fixed-step law's box LCP (one step) agrees."""
    X = np.array([0.03, 0.02])  # off centre: unequal normal forces, one cell lifted off
    wheels = on(SQUARE, X, BOX, np.zeros((4, 2)))
    J, b = wheels.rows(X), wheels.mu_static * wheels.normal(X)
    M = np.array([BOX.mass, BOX.mass, BOX.inertia])
    h = 1e-4

    def verdicts(z):
        """(exact rule sticks, fixed step sticks) for wheels accelerating rigidly at z (a parcel at rest)."""
        ramp = Wheels(wheels.points, wheels.directions, wheels.speeds, J @ z, 0.0, wheels.force_lin,
                      wheels.force_const, wheels.origin, wheels.mu_static, wheels.mu_kinetic)
        mode = decide_mode(ramp, 0.0, [*X, 0, 0, 0, 0], BOX.mass, BOX.inertia)
        # one fixed step that must give the impulse M h z to stick (the same wrench over h)
        _, nu_p, _, ok = solve_contacts(J, np.zeros(8), b * h, -h * z, 1 / M, np.zeros(8), 100000, 1e-15)
        assert ok
        return len(mode.stick) == int((b > 0).sum()), bool(np.abs(J[b > 0] @ nu_p).max() < 1e-9 * h * np.abs(z).max())

    F = np.array([1.0, 0.0, 0.0])
    c = np.zeros(9)
    c[-1] = -1
    reach = -linprog(c, A_eq=np.hstack([J.T, -F[:, None]]), b_eq=np.zeros(3), bounds=list(zip(-b, b)) + [(0, None)]
                     ).fun  # the largest x-force the wheels can hold
    for scale, sticks in ((0.95, True), (1.05, False)):
        z = scale * reach * F / M
        lam = np.linalg.lstsq(J.T, M * z, rcond=None)[0]
        if sticks:
            assert (np.abs(lam) > b * 1.2).any()  # minimum-norm forces would break it
        assert verdicts(z) == (sticks, sticks)

    @settings(max_examples=40)
    @given(st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1), st.floats(0.3, 3.0))
    def agree(direction, scale):
        F = np.array(direction) * [1, 1, 0.05]
        t = -linprog(c, A_eq=np.hstack([J.T, -F[:, None]]), b_eq=np.zeros(3),
                     bounds=list(zip(-b, b)) + [(0, None)]).fun
        if abs(scale - 1) < 1e-3:
            return
        exact, fixed = verdicts(scale * t * F / M)
        assert exact == fixed == (scale < 1)

    agree()


@pytest.mark.parametrize("kind", ["lumped", "separate", "hex omni"])
def test_every_wheel_slipping_gives_the_papers_coulomb_constants(kind):
    """A parcel at rest on spinning wheels: every wheel slips, and the wrench is the paper's Coulomb constants'
    (eqs. 20-29) for the layer's wheels."""
    base = layout.grid(3, 3, D, origin=(-D, -D))
    cells = {"lumped": base, "separate": layout.separate_wheels(base),
             "hex omni": layout.three_wheels(layout.hexagonal(3, 3, D, origin=(-D, -D)))}[kind]
    V = fields.Inward((0.013, -0.007), 0.4).velocities(cells) + [0.05, 0.02]
    com = np.array([0.01, 0.02]) + (cells.positions.mean(axis=0) if kind == "hex omni" else 0)
    spec = parcel.rectangle(0.32, 0.3, 1.3, 0.45, mu_static=0.6)
    sol = contact.solve_support(cells.positions, com, spec.weight(G))
    wheels = wheels_on(cells, np.arange(cells.n), sol, V, spec.mu, spec.mu_static)
    y = np.array([*com, 0.2, 0, 0, 0])
    mode = decide_mode(wheels, 0.0, y, spec.mass, spec.inertia)
    speeds = wheels.surface(0.0)
    assert len(mode.stick) == 0 and np.array_equal(mode.signs, -np.sign(speeds))
    ydot, lam = mode_rhs(wheels, mode, 0.0, y, spec.mass, spec.inertia)
    k = laws.CoulombLaw().constants(sol, V, cells.active_directions, spec.mu)
    xi = com - sol.origin
    wrench = ydot[3:] * [spec.mass, spec.mass, spec.inertia]
    np.testing.assert_allclose(wrench, [*k.force(xi), k.torque(xi)], rtol=1e-12, atol=1e-12)


def _run(cells, V, y0, T=0.25, **kw):
    return simulate(on(cells, y0[:2], BOX, V, **kw), y0, 0, T, BOX.mass, BOX.inertia)


@settings(max_examples=8)
@given(st.floats(-np.pi, np.pi), st.floats(-5, 5), st.floats(-5, 5))
def test_rotating_and_translating_the_scene_moves_the_motion(phi, dx, dy):
    V, y0 = _twist_scene()
    base = _run(SQUARE, V, y0)
    R, shift = rot(phi), np.array([dx, dy])
    cells = layout.from_points(SQUARE.positions @ R.T + shift, D, drive_angle=phi)
    y1 = np.array([*(R @ y0[:2] + shift), y0[2] + phi, *(R @ y0[3:5]), y0[5]])
    moved = _run(cells, V @ R.T, y1)
    assert [e.kind for e in moved.events] == [e.kind for e in base.events]
    np.testing.assert_allclose([e.time for e in moved.events], [e.time for e in base.events], atol=1e-9)
    y = base.y_end
    np.testing.assert_allclose(moved.y_end, [*(R @ y[:2] + shift), y[2] + phi, *(R @ y[3:5]), y[5]], atol=1e-9)


def test_the_order_of_the_cells_does_not_matter():
    V, y0 = _twist_scene()
    base = _run(SQUARE, V, y0)
    for order in ([3, 1, 0, 2], [2, 3, 1, 0]):
        moved = _run(layout.from_points(SQUARE.positions[order], D), V[order], y0)
        np.testing.assert_allclose([e.time for e in moved.events], [e.time for e in base.events], rtol=1e-12)
        np.testing.assert_allclose(moved.state(np.linspace(0, 0.25, 11)), base.state(np.linspace(0, 0.25, 11)),
                                   atol=1e-12)


def test_stuck_wheels_brake_and_free_wheels_let_go():
    """Wheels that cannot turn stop a parcel sliding along them at mu_k g and then hold it; wheels that cannot push
    leave it coasting."""
    V = fields.Uniform((0.3, 0.0)).velocities(SQUARE)
    v0, mu = 0.2, BOX.mu
    along_x = np.tile([True, False], (4, 1))
    y0 = np.array([0.0, 0.0, 0.0, v0, 0.0, 0.0])
    braked = _run(SQUARE, V, y0, stuck=along_x)  # the x-wheels are held still whatever they are told
    t_stop = v0 / (mu * G)
    assert len(braked.events) == 1 and abs(braked.events[0].time - t_stop) < 1e-10
    np.testing.assert_allclose(braked.y_end, [v0**2 / (2 * mu * G), 0, 0, 0, 0, 0], atol=1e-12)
    coasting = _run(SQUARE, V, y0, free=along_x)
    assert len(coasting.events) == 0
    np.testing.assert_allclose(coasting.y_end, [v0 * 0.25, 0, 0, v0, 0, 0], atol=1e-13)


def test_inconsistent_inputs_are_refused():
    with pytest.raises(ValueError, match="mu_kinetic"):  # static friction below kinetic
        Wheels([[0.0, 0.0]], [[1.0, 0.0]], [0.0], [0.0], 0.0, [[0.0, 0.0]], [1.0], [0.0, 0.0], [0.3], [0.4])
    with pytest.raises(ValueError, match="shape"):
        wheels_on(SQUARE, np.arange(4), contact.solve_support(SQUARE.positions, [0, 0], 9.81), np.zeros((3, 2)), 0.4)
    with pytest.raises(ValueError, match="mass"):
        simulate(on(SQUARE, [0, 0], BOX, np.zeros((4, 2))), np.zeros(6), 0, 1, 0.0, 1.0)


@pytest.mark.parametrize("kind", ["separate", "hex omni"])
def test_set_down_on_a_uniform_field_ends_riding_it(kind):
    """On one-wheel contacts the wheels catch up one by one; the parcel ends riding the field exactly, with the
    energy balance closed (wheel work = kinetic energy gained + dissipation, each > 0)."""
    cells = (layout.separate_wheels(layout.grid(3, 3, D, origin=(-D, -D))) if kind == "separate"
             else layout.three_wheels(layout.hexagonal(3, 3, D, origin=(-D, -D))))
    v = np.array([0.25, -0.1])
    com = cells.positions.mean(axis=0) + [0.01, -0.01]
    y0 = np.array([*com, 0.3, 0, 0, 0])
    run = simulate(on(cells, com, BOX, np.tile(v, (cells.n, 1))), y0, 0, 0.3, BOX.mass, BOX.inertia)
    assert len(run.events) >= 2 and len(run.events[-1].after.stick) == 2 * cells.n - (~cells.wheel_active).sum()
    np.testing.assert_allclose(run.y_end[3:], [*v, 0], atol=1e-12)
    gained = run.kinetic_end - run.kinetic_start
    assert gained > 0 and run.dissipation > 0
    assert abs(run.wheel_work - gained - run.dissipation) <= 1e-8 * run.wheel_work
