"""The stick-slip law run event-driven by the engine (integrate's event mode): each wheel sticks or slips between
events, across support changes. Checked against what it did not write: the one-support-set reference
(physics.stick_modes.simulate), the pickup's closed form, the fixed-step complementarity law as dt -> 0, the energy
balance, and the paper's Coulomb law while every wheel slips."""

import dataclasses

import numpy as np
import pytest

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.engine import _kernel
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import contact, laws
from virtual_vehicle.physics.stick_modes import decide_kernel, simulate, wheel_arrays, wheels_on

G = 9.81
D = 0.1
SQUARE = layout.grid(2, 2, D, origin=(-D / 2, -D / 2))  # four cells a 0.3 m square parcel always covers near (0, 0)
BOX = parcel.rectangle(0.3, 0.3, 1.0, 0.4, mu_static=0.5)


def support_events(tr):
    return [e for e in tr.events if e.kind == "support"]


def stick_slip(cells, spec, V, law=None):
    return ParcelModel(cells, spec, V, law or laws.StickSlipLaw(), G)


def reference(cells, spec, V, y0, T, **kw):
    """stick_modes.simulate on the support set of every cell of ``cells`` (the parcel stays over all of them)."""
    sol = contact.solve_support(cells.positions, np.asarray(y0[:2], dtype=float), spec.weight(G))
    wheels = wheels_on(cells, np.arange(cells.n), sol, V, spec.mu, spec.mu_static, **kw)
    return simulate(wheels, y0, 0.0, T, spec.mass, spec.inertia)


@pytest.mark.parametrize("scene", ["slips_catch_up", "stick_breaks"])
def test_engine_agrees_with_the_reference_on_one_support_set(scene):
    """Three wheels catching up (slip events), or seven redundant sticking wheels whose wrench leaves their zonotope
    twice (stick events): the engine's trajectory and mode changes are the reference's to 1e-8 m."""
    if scene == "slips_catch_up":
        spec, T = BOX, 0.3
        V = fields.Twist((0.01, 0.0), (0.05, -0.03, 1.0)).velocities(SQUARE)
        y0 = np.array([0.01, -0.005, 0.1, -0.1, 0.05, -0.5])
    else:
        spec, T = parcel.rectangle(0.3, 0.3, 1.0, 0.4, mu_static=0.4), 0.41
        V = fields.Twist((0.02, 0.0), (0, 0, 8.0)).velocities(SQUARE) + [[0, 0], [0, 0], [0, 0], [0.3, 0]]
        y0 = np.array([0, 0, 0, 0, -8.0 * 0.02, 8.0])
    run = reference(SQUARE, spec, V, y0, T)
    ts = np.linspace(0, T, 41)
    tr = integrate(stick_slip(SQUARE, spec, V), y0, 0, T, sample_times=ts)
    assert tr.status == "completed" and support_events(tr) == []  # one support set throughout
    assert np.abs(tr.states[:, :2] - run.state(ts)[:, :2]).max() <= 1e-8
    assert np.abs(tr.states - run.state(ts)).max() <= 1e-7
    mine = tr.stats["mode_events"]
    assert [k for _, k, _, _ in mine] == [e.kind for e in run.events]
    assert [after for *_, after in mine] == [e.after.state for e in run.events]
    np.testing.assert_allclose([t for t, *_ in mine], [e.time for e in run.events], atol=1e-9)
    assert abs(tr.stats["wheel_work"] - run.wheel_work) <= 1e-8 and abs(tr.stats["friction_dissipation"]
                                                                          - run.dissipation) <= 1e-8


def test_pickup_closed_form_across_support_changes():
    """stick_slip_pickup: the carton accelerates at mu_k g until t* = v / (mu_k g), its one mode change, then rides
    at exactly the wheel speed over the cells it crosses; half the wheels' work is lost to friction."""
    setup = load_scenario("stick_slip_pickup")[0].build()
    spec, y0, cells, V = setup.specs[0], setup.states[0], setup.contact_layer, setup.velocities
    g, v, mu = setup.scenario.gravity, 0.3, setup.specs[0].mu
    T, t_star = setup.scenario.duration, v / (mu * g)
    ts = np.linspace(0, T, 301)
    tr = integrate(ParcelModel(cells, spec, V, setup.law, g), y0, 0, T, sample_times=ts)
    assert tr.status == "completed" and len(support_events(tr)) >= 5  # it crosses cells
    (t_mode, kind, before, after), = tr.stats["mode_events"]
    assert kind == "slip" and abs(t_mode - t_star) <= 1e-12 and set(after) == {0}
    caught, = [e for e in tr.events if e.kind in ("stick", "slip")]  # the run's event: the x wheels grip at t*
    assert caught.kind == "stick" and caught.t == t_mode
    assert len(caught.message.split()) == sum(b in (1, -1) for b in before) > 0
    assert {pair.split(":")[1] for pair in caught.message.split()} == {"0"}  # the wheels driving along x
    x = y0[0] + np.where(ts < t_star, 0.5 * mu * g * ts**2, v * ts - 0.5 * v * t_star)
    np.testing.assert_allclose(tr.states[:, 0], x, atol=1e-11)
    np.testing.assert_allclose(tr.states[:, 3], np.minimum(mu * g * ts, v), atol=1e-11)
    np.testing.assert_allclose(tr.states[ts > t_star, 3], v, atol=1e-13)  # exactly the wheel speed
    assert np.abs(tr.states[:, [1, 2, 4, 5]] - [y0[1], y0[2], 0, 0]).max() < 1e-13
    s = tr.stats
    np.testing.assert_allclose([s["wheel_work"], s["friction_dissipation"], s["kinetic_end"]],
                               [spec.mass * v**2, spec.mass * v**2 / 2, spec.mass * v**2 / 2], rtol=1e-9)


def _crossing():
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 0.5)
    return cells, spec, fields.Uniform((0.2, 0.0)).velocities(cells), [0.52, 1.47, 0.3, 0, 0, 0]


def _turning():
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 0.5)
    return cells, spec, fields.Twist((1.5, 1.5), (0, 0, 0.4)).velocities(cells), [1.5, 1.0, 0.0, 0, 0, 0]


@pytest.mark.parametrize("scene", [_crossing, _turning])
def test_fixed_step_law_converges_to_the_event_driven_one(scene):
    """mu_s = mu_k: the fixed-step complementarity law (fixed mode) approaches the exact event-driven run at first
    order as dt halves, through the catch-up and some twenty support changes."""
    cells, spec, V, y0 = scene()
    T = 1.5
    ts = np.linspace(0, T, 51)
    exact = integrate(stick_slip(cells, spec, V), y0, 0, T, sample_times=ts)
    assert len(support_events(exact)) >= 15 and exact.stats["mode_changes"] >= 1
    errs = [np.abs(integrate(stick_slip(cells, spec, V), y0, 0, T, sample_times=ts, dt=dt, mode="fixed").states[:, :2]
                   - exact.states[:, :2]).max() for dt in (2e-3, 1e-3, 5e-4)]
    order = np.log2(np.array(errs[:-1]) / errs[1:])
    print(f"{scene.__name__}: errors {errs} m, observed order {order}")
    assert np.all(np.abs(order - 1) < 0.1), (errs, order)


def test_energy_account_closes_across_support_changes():
    """With rotation, lift-offs, support changes and mu_s > mu_k: wheel work = kinetic energy gained + friction
    dissipation, the dissipation >= 0 (no step dissipation: there is no step)."""
    cells = layout.grid(10, 8, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.3, 0.45, mu_static=0.6)
    tr = integrate(stick_slip(cells, spec, fields.Inward((0.45, 0.35), 0.4).velocities(cells)),
                   [0.3, 0.25, 0.4, 0.2, -0.1, 1.5], 0, 1.5)
    s = tr.stats
    assert tr.status == "completed" and len(support_events(tr)) > 5 and s["mode_changes"] > 0
    gained = s["kinetic_end"] - s["kinetic_start"]
    assert s["friction_dissipation"] > 0 and s["step_dissipation"] == 0
    assert abs(s["wheel_work"] - gained - s["friction_dissipation"]) <= 1e-8 * abs(s["wheel_work"])


def test_every_wheel_slipping_is_the_papers_coulomb_law():
    """Wheels much faster than the parcel never let it catch up: the event-driven stick-slip run is the paper's
    Coulomb run (eqs. 20-29), with no mode change."""
    cells = layout.grid(2, 2, D, origin=(-D / 2, -D / 2))
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.5)
    V = fields.Inward((0, 0), 2.0).velocities(cells)
    y0 = [0.02, -0.01, 0.1, 0, 0, 0]
    coulomb = integrate(stick_slip(cells, spec, V, laws.CoulombLaw()), y0, 0, 0.5, sample_dt=0.01)
    mine = integrate(stick_slip(cells, spec, V), y0, 0, 0.5, sample_dt=0.01)
    assert mine.stats["mode_changes"] == 0
    assert np.abs(mine.states - coulomb.states).max() < 1e-9


def test_stuck_and_free_wheels_are_the_references_faults():
    """A stuck wheel (held at speed 0, as the run's faults hold it) and a free-spinning one (taken out of the contact
    layer, as a scenario's faults take it) in the engine give stick_modes' wheels_on(stuck=, free=) run."""
    V = fields.Twist((0.01, 0.0), (0.05, -0.03, 1.0)).velocities(SQUARE)
    stuck = np.zeros((4, 2), bool)
    free = np.zeros((4, 2), bool)
    stuck[1, 0] = free[2, 1] = True
    y0 = np.array([0.01, -0.005, 0.1, -0.1, 0.05, -0.5])
    run = reference(SQUARE, BOX, V, y0, 0.3, stuck=stuck, free=free)
    held = V - np.einsum("ik,ikj->ij", np.where(stuck, np.einsum("ij,ikj->ik", V, SQUARE.drive_directions), 0.0),
                         SQUARE.drive_directions)  # zero along each stuck wheel
    cells = dataclasses.replace(SQUARE, wheel_active=SQUARE.wheel_active & ~free)
    ts = np.linspace(0, 0.3, 31)
    tr = integrate(stick_slip(cells, BOX, held), y0, 0, 0.3, sample_times=ts)
    assert len(run.events) > 0 and len(tr.stats["mode_events"]) == len(run.events)
    assert np.abs(tr.states[:, :2] - run.state(ts)[:, :2]).max() <= 1e-8


def test_a_run_split_into_ticks_is_the_same_run():
    """mu_s > mu_k, sticking across control-tick boundaries: integrating tick by tick (as the co-simulation does)
    gives the whole run's trajectory; the mode is decided again from the state at each tick."""
    cells = layout.grid(10, 8, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.3, 0.3, mu_static=0.6)
    V = fields.Inward((0.45, 0.35), 0.2).velocities(cells)
    y0 = np.array([0.42, 0.33, 0.2, 0.0, 0.0, 0.0])
    whole = integrate(stick_slip(cells, spec, V), y0, 0, 0.5, sample_dt=0.01)
    base = stick_slip(cells, spec, V)
    y = y0
    for k in range(50):
        y = integrate(base.with_velocities(V), y, k * 0.01, (k + 1) * 0.01, sample_dt=0.01).states[-1]
    np.testing.assert_allclose(y, whole.states[-1], atol=1e-9)


def test_models_of_new_wheels_each_tick_run_as_fresh_models():
    """A plant makes its parcels' models again every control tick (other wheel velocities): each copy takes over the
    compiled loop's table of the copy before it. Tick by tick under a changing field, the copies' runs equal fresh
    models' (sharing the solved supports as the copies do) bit for bit, and a copy run again after the next one took
    its table runs as a fresh model does then."""
    cells = layout.grid(10, 8, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.3, 0.3, mu_static=0.6)
    field = fields.Inward((0.45, 0.35), 0.2).velocities(cells)
    base = stick_slip(cells, spec, field)
    store: dict = {}
    y_copy = y_fresh = np.array([0.42, 0.33, 0.2, 0.0, 0.0, 0.0])
    before, crossed = None, 0
    for k in range(40):
        V = field * (1.0 + 0.5 * np.sin(0.7 * k))  # the wheels change every tick
        t0, t1 = k * 0.01, (k + 1) * 0.01
        copy = base.with_velocities(V)
        ran = integrate(copy, y_copy, t0, t1, sample_dt=0.005)
        fresh = integrate(ParcelModel(cells, spec, V, laws.StickSlipLaw(), G, store), y_fresh, t0, t1,
                          sample_dt=0.005)
        assert np.array_equal(ran.states, fresh.states) and ran.events == fresh.events
        if before is not None:  # the copy before, whose table this one took, run again: as a fresh model now
            model, V_before, y = before
            again = integrate(model, y, t0 - 0.01, t0, sample_dt=0.005)
            now = integrate(ParcelModel(cells, spec, V_before, laws.StickSlipLaw(), G, store), y, t0 - 0.01, t0,
                            sample_dt=0.005)
            assert np.array_equal(again.states, now.states) and again.events == now.events
        before = copy, V, y_copy
        y_copy, y_fresh = ran.states[-1], fresh.states[-1]
        crossed += len(support_events(ran))
    assert crossed > 0  # the loop met support changes, where the table matters


@pytest.mark.parametrize("mu_static", [0.4, 0.5])
def test_fixed_step_law_converges_through_stick_breaks_and_a_lift_off(mu_static):
    """A kicked turn: one cell's wheel faster than the rest slips, the seven others ride until the centripetal
    wrench leaves their zonotope (twice), a cell lifts off, a wheel catches up. The fixed-step law converges to the
    event-driven run at first order, also with mu_s > mu_k (it keeps the static bound for every wheel whose slip
    after a step is zero: judged by its impulse, a redundant sticking wheel at its bound lost it and the grip broke
    early whatever the step)."""
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.4, mu_static=mu_static)
    V = fields.Twist((0.02, 0.0), (0, 0, 8.0)).velocities(SQUARE) + [[0, 0], [0, 0], [0, 0], [0.3, 0]]
    y0 = np.array([0, 0, 0, 0, -8.0 * 0.02, 8.0])
    T = 0.5
    ts = np.linspace(0, T, 51)
    exact = integrate(stick_slip(SQUARE, spec, V), y0, 0, T, sample_times=ts)
    assert [k for _, k, _, _ in exact.stats["mode_events"]] == ["stick", "stick", "slip"]
    lift, = support_events(exact)
    assert lift.lifted  # the lift-off, between the second break and the slip
    errs = [np.abs(integrate(stick_slip(SQUARE, spec, V), y0, 0, T, sample_times=ts, dt=dt, mode="fixed").states[:, :2]
                   - exact.states[:, :2]).max() for dt in (2e-4, 1e-4, 5e-5)]
    order = np.log2(np.array(errs[:-1]) / errs[1:])
    print(f"mu_static {mu_static}: errors {errs} m, observed order {order}")
    assert np.all(np.abs(order - 1) < 0.15), (errs, order)


def test_a_scenario_run_reports_the_exact_law():
    """stick_slip_pickup through the simulator: event mode, one mode change, the closed-form energy account (no step
    dissipation), support changes where the carton's edges cross cell centres."""
    from virtual_vehicle.run.sim import run

    res = run(load_scenario("stick_slip_pickup")[0].build())
    summary = res.summary()
    carton = summary["parcels"][0]
    assert summary["integrator"] == "event" and carton["stick_slip_mode_changes"] == 1
    energy = carton["energy_J"]
    assert energy["step_dissipation"] == 0 and abs(energy["friction_dissipation"] - 0.3**2 / 2) < 1e-12
    assert carton["support_changes"] == 9


def test_mode_changes_are_the_runs_events():
    """Every mode change of a run is in its events (and so in its event table), in time order with the support
    events: a "stick" event where wheels catch up with the parcel, a "slip" one where they break away, naming the
    wheels as "entry:wheel"; the stick breaks and the catch-up of the kicked turn appear in the order they happen."""
    from virtual_vehicle.run import tables
    from virtual_vehicle.run.sim import run

    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.4, mu_static=0.4)
    V = fields.Twist((0.02, 0.0), (0, 0, 8.0)).velocities(SQUARE) + [[0, 0], [0, 0], [0, 0], [0.3, 0]]
    tr = integrate(stick_slip(SQUARE, spec, V), [0, 0, 0, 0, -8.0 * 0.02, 8.0], 0, 0.5)
    modes = [e for e in tr.events if e.kind in ("stick", "slip")]
    assert [e.t for e in tr.events] == sorted(e.t for e in tr.events)
    changes = tr.stats["mode_events"]
    assert {e.t for e in modes} == {t for t, *_ in changes}
    for t, _, before, after in changes:
        gripped = {j for j, (a, b) in enumerate(zip(before, after)) if a in (1, -1) and b == 0}
        named = [e for e in modes if e.t == t and e.kind == "stick"]
        assert len(named) == (1 if gripped else 0)
        if gripped:
            assert len(named[0].message.split()) == len(gripped)
            assert named[0].entered == () and all(len(pair.split(":")) == 2 for pair in named[0].message.split())
    assert [e.kind for e in modes][:2] == ["slip", "slip"]  # the grip breaks twice before a wheel catches up
    assert modes[-1].kind == "stick"
    res = run(load_scenario("stick_slip_pickup")[0].build())
    kinds = tables.events(res).column("kind").to_pylist()
    assert kinds.count("stick") == 1 and kinds.count("slip") == 0


def test_the_grip_is_handed_to_the_time_stepper():
    """After an event-driven run the model (and the model it was copied from, which a plant keeps) holds which
    wheels grip, so that the fixed-step law taking over (parcels pushing each other are stepped) starts from the
    exact run's grip, not from an earlier episode's: before the pickup the wheels driving along x slip (those along y,
    at rest under a parcel at rest in y, stick), after it every one sticks."""
    setup = load_scenario("stick_slip_pickup")[0].build()
    spec, y0, cells, V = setup.specs[0], setup.states[0], setup.contact_layer, setup.velocities
    base = ParcelModel(cells, spec, V, setup.law, setup.scenario.gravity)
    t_star = 0.3 / (spec.mu * setup.scenario.gravity)
    y = integrate(base.with_velocities(V), y0, 0, 0.5 * t_star).states[-1]
    early = dict(base.contact_memory["stuck"])
    assert early and not any(v for (_, wheel), v in early.items() if wheel == 0)
    assert all(v for (_, wheel), v in early.items() if wheel == 1)
    integrate(base.with_velocities(V), y, 0.5 * t_star, 2 * t_star)
    late = base.contact_memory["stuck"]
    assert late and all(late.values()) and base.contact_memory["lam"].keys() == late.keys()


LATE = parcel.rectangle(0.25, 0.22, 2.0, 0.6, mu_static=0.8)  # the parcel that chattered at 677.5 s of an hour's run


@pytest.mark.parametrize("decide", ["reference", "compiled"])
def test_a_wheel_whose_slip_reached_zero_late_in_a_run_sticks(decide):
    """Late in a long run an event's time is known only to ~16 eps |t| (2.6 ps at 677 s), so a slip that reached
    zero there reads 1e-12 m/s or so either side of it: the wheel is at zero slip and sticks (still wheels, nothing
    else pushing). An hour's junction run chattered here (the x wheels slipping back and forth, a thousand mode
    events in a femtosecond) with a tolerance that did not grow with the time."""
    from virtual_vehicle.physics.stick_modes import decide_compiled, decide_mode

    V = np.zeros((4, 2))
    y = np.array([0.0106, 0.0132, -0.006039, -1.3478541199818395e-12, 0.0, 0.0])  # as at 677.510551 s
    sol = contact.solve_support(SQUARE.positions, y[:2], LATE.weight(G))
    wheels = wheels_on(SQUARE, np.arange(4), sol, V, LATE.mu, LATE.mu_static)
    for t in (677.510551, 3600.0, 36000.0):
        if decide == "reference":
            mode = decide_mode(wheels, t, y, LATE.mass, LATE.inertia)
        else:
            mode, y_out, _ = decide_compiled(wheels, t, y, LATE.mass, LATE.inertia)
            assert np.abs(y_out[3:]).max() <= 1e-20  # the twist projected onto the sticking wheels
        assert set(mode.state) == {0}, (t, mode.state)
    # a slip that is a real one still slips, however late
    y_moving = y.copy()
    y_moving[3] = -1e-6
    slipping = decide_mode(wheels, 36000.0, y_moving, LATE.mass, LATE.inertia)
    assert sorted(set(slipping.state)) == [-1, 0] or sorted(set(slipping.state)) == [0, 1]


@pytest.mark.parametrize("t0", [0.0, 677.51, 3600.0, 36000.0])
def test_a_parcel_stopping_on_still_wheels_stops_the_same_at_any_time(t0):
    """The same parcel sliding onto still wheels at 3.2 mm/s, started at any time up to ten hours into a run:
    it slides to rest at mu g (kinetic), one stick event, and stays there, the same motion to 1e-9 m whatever the
    start (the physics does not know the clock; only the rounding of its times does)."""
    V = np.zeros((4, 2))
    y0 = np.array([0.0106, 0.0132, -0.006039, 0.0032459, 0.0, 0.0])
    tr = integrate(stick_slip(SQUARE, LATE, V), y0, t0, t0 + 0.01, sample_times=t0 + np.array([0.0, 0.01]))
    assert tr.status == "completed"
    assert [e.kind for e in tr.events] == ["stick"]
    a = LATE.mu * G  # eq. 22 with every x wheel slipping the same way: mu W along -x
    stop = y0[3] / a
    assert abs(tr.events[0].t - t0 - stop) <= 1e-9 + 64 * np.finfo(float).eps * t0
    assert np.abs(tr.states[-1, 3:]).max() <= 1e-20  # at rest: the twist projected onto the sticking wheels
    assert abs(tr.states[-1, 0] - (y0[0] + y0[3] ** 2 / (2 * a))) <= 1e-9
    assert np.abs(tr.states[-1, 1:3] - y0[1:3]).max() <= 1e-12


def _one_by_one(md, F, z_old, t_old, h, t_lo, t_hi, v_lo, n_ev):
    """The mode event search as it was before one bisection served all values: each value falling in the first
    sample interval that has any bisected on its own to rounding, the earliest root taken (the first value of
    those that tie): (found, time, value)."""
    y, v, prev, t_a, eps = np.empty(8), np.empty(n_ev), v_lo.copy(), t_lo, np.finfo(float).eps
    for s in range(1, _kernel.SUBSAMPLES + 1):
        t_b = t_lo + (t_hi - t_lo) * s / _kernel.SUBSAMPLES if s < _kernel.SUBSAMPLES else t_hi
        _kernel._dense_all(F, z_old, t_old, h, t_b, y)
        _kernel.mode_values(md, t_b, y, v)
        best, which, at_b = np.inf, -1, v.copy()
        for k in np.flatnonzero((prev > 0) & ~(at_b > 0)):
            lo, hi = t_a, t_b
            while hi - lo > max(4 * eps * abs(hi), 1e-15):
                mid = 0.5 * (lo + hi)
                if mid <= lo or mid >= hi:
                    break
                _kernel._dense_all(F, z_old, t_old, h, mid, y)
                _kernel.mode_values(md, mid, y, v)
                lo, hi = (mid, hi) if v[k] > 0 else (lo, mid)
            if hi < best:
                best, which = hi, int(k)
        if which >= 0:
            return True, best, which, int(((prev > 0) & ~(at_b > 0)).sum())
        prev, t_a = at_b, t_b
    return False, t_hi, -1, 0


@pytest.mark.parametrize("speed, heading", [(0.5, 0.0), (0.37, 0.3), (0.2, 1.1)])
def test_wheels_catching_up_together_meet_at_one_bisected_root(speed, heading):
    """A carton at rest on 36 cells of a uniform field: every wheel driving along the field catches up with it at
    the same instant (t* = v / (mu g) for a field along x). The mode event search bisects the earliest root of all
    the values falling together once, on their minimum; it finds the time (to the bit) and the value that bisecting
    each value alone finds."""
    cells = layout.grid(6, 6, 0.1, origin=(-0.25, -0.25))
    spec = parcel.rectangle(0.55, 0.55, 2.0, 0.5)
    V = np.tile([speed * np.cos(heading), speed * np.sin(heading)], (cells.n, 1))
    y0 = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    support = np.arange(cells.n)
    sol = contact.solve_support(cells.positions, y0[:2], spec.weight(G))
    wheels = wheel_arrays(cells, support, sol, V, spec.mu, spec.mu_static)
    minv = np.array([1 / spec.mass, 1 / spec.mass, 1 / spec.inertia])
    none = np.zeros(0, np.int64)
    ok, state, y, rows, stick, rank, anchor, index = decide_kernel(*wheels, minv, 0.0, y0, none, none)
    assert ok and (np.abs(state) == 1).sum() >= 12  # the wheels along the field slip
    md = (*wheels, state, stick[rows], stick, rank, anchor, index, minv)
    n_ev = int((np.abs(state) == 1).sum()) + (len(index) if len(stick) else 0)
    z = np.concatenate([y, [0.0, 0.0]])
    f, z_new, f_new, work = np.empty(8), np.empty(8), np.empty(8), np.empty(8)
    _kernel._mode_rhs(md, 0.0, z, f)
    K = np.empty((_kernel._N_EXTENDED, 8))
    F = np.empty((_kernel._D.shape[0] + 3, 8))
    step_ok, t_new, _, _ = _kernel._mode_step(md, 0.0, z, f, 1.0, 0.4, 1e-10, 1e-12, np.inf, K, z_new, f_new, work)
    assert step_ok
    _kernel._mode_dense(md, 0.0, z, f, z_new, f_new, t_new, K, F, work)
    v_lo = np.empty(n_ev)
    _kernel.mode_values(md, 0.0, z, v_lo)
    found, t_event, which = _kernel._mode_crossing(md, F, z, 0.0, t_new, 0.0, t_new, v_lo, n_ev)
    ref_found, ref_t, ref_which, together = _one_by_one(md, F, z, 0.0, t_new, 0.0, t_new, v_lo, n_ev)
    assert found and ref_found and together >= 6  # (several values fall in one sample interval)
    assert t_event == ref_t and which == ref_which
    if heading == 0.0:
        assert abs(t_event - speed / (spec.mu * G)) <= 1e-12


@pytest.mark.parametrize("vx, vy", [(0.3, 0.0), (0.21, -0.13)])
def test_a_parcel_riding_a_uniform_field_moves_in_closed_form(vx, vy):
    """A carton already at the wheels' speed rides them: no DOP853 step is taken (the mode's motion is the twist's
    straight line) and every support event falls where a cell's centre crosses one of its edges, x_c = x0 +- L/2 +
    v t (and the same in y), to 1e-12 s; it ends where the line does, at the wheels' speed to the bit."""
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.34, 0.26, 1.5, 0.5)
    V = fields.Uniform((vx, vy)).velocities(cells)
    y0 = np.array([0.731, 1.212, 0.0, vx, vy, 0.0])
    T = 1.5
    tr = integrate(stick_slip(cells, spec, V), y0, 0, T)
    assert tr.status == "completed" and tr.stats["mode_changes"] == 0
    assert tr.rhs_evals <= 2 * tr.segments  # one evaluation a mode to find it rides (DOP853: 16 a step)
    expected = set()
    for c, (x0, v, half) in enumerate([(y0[0], vx, 0.17), (y0[1], vy, 0.13)]):
        lines = cells.positions[:, c]
        for edge in (x0 - half, x0 + half):
            for xc in np.unique(lines):
                t = (xc - edge) / v if v else -1.0
                if 0 < t < T:
                    expected.add(round(t, 9))
    got = [e.t for e in support_events(tr)]
    assert len(got) == len(expected) >= 9
    np.testing.assert_allclose(sorted(got), sorted(expected), atol=1e-9)
    for e in support_events(tr):  # the state at each event on the straight line, to rounding
        xc = [(e.state[0] - y0[0] - vx * e.t), (e.state[1] - y0[1] - vy * e.t)]
        assert max(map(abs, xc)) <= 1e-12
    np.testing.assert_allclose(tr.states[-1], [y0[0] + vx * T, y0[1] + vy * T, 0, vx, vy, 0], atol=1e-12)
    assert (tr.states[-1][3], tr.states[-1][4]) == (vx, vy)
