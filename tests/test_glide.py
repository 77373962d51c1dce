"""Stick-slip parcels translating over a uniform field, written in closed form (engine/glide.py), against the
event-driven engine that would have run them, and against the closed forms of the physics."""

import numpy as np
import pytest

from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.engine import glide
from virtual_vehicle.engine.plant import sample_grid


def scene(field, parcels, duration=0.6, side=0.22, **extra):
    """A 30 x 30 array (pitch 0.1 m) under a uniform ``field`` (m/s), stick-slip, parcels ``side`` x ``side`` m of
    1.5 kg."""
    return {"name": "glide", "duration": duration, "output_dt": 0.05,
            "array": {"kind": "grid", "nx": 30, "ny": 30, "pitch": 0.1},
            "field": {"kind": "uniform", "velocity": list(field)}, "friction": {"law": "stick_slip"},
            "parcels": [{"name": f"p{k}", "length": side, "width": side, "mass": 1.5, "mu": 0.5, **p}
                        for k, p in enumerate(parcels)], **extra}


def advance(sc, glides: bool, every: float | None = None, change=None):
    """Each parcel's trajectory over the scenario, the plant advanced ``every`` s at a time (once: None), with the
    closed form on or off, the cells' velocities (m/s) as ``change(positions, velocities)`` returns them (None: the
    scenario's); and the plant."""
    setup = parse_scenario(sc).build()
    plant = setup.plant()
    assert plant._glide is not None
    if not glides:
        plant._glide = None
    ys = [y.copy() for y in setup.states]
    active = [True] * len(ys)
    T = sc["duration"]
    grid = sample_grid(0.0, T, sc["output_dt"])
    cuts = [0.0] + ([] if every is None else np.arange(every, T - 1e-9, every).tolist()) + [T]
    parts = [[] for _ in ys]
    V = np.array(setup.contact_velocities, dtype=float)
    if change is not None:
        V = change(plant.cells.positions, V)
    for t0, t1 in zip(cuts[:-1], cuts[1:]):
        inside = grid[(grid > t0 + 1e-12) & (grid < t1 - 1e-12)]
        out = plant.advance(ys, active, V, t0, t1, 0.0, None,
                            sample_times=np.concatenate([[t0], inside, [t1]]))
        for p, tr in zip(parts, out):
            p.append(tr)
    return parts, plant


def same_runs(sc, every=None, change=None):
    """Run ``sc`` with and without the closed form; require the same trajectories (samples, events and their cells,
    stick messages, energy account, mode changes) to 1e-9; return how many windows the closed form wrote."""
    a, plant = advance(sc, True, every, change)
    b, _ = advance(sc, False, every, change)
    for A, B in zip(a, b):
        for ta, tb in zip(A, B):
            np.testing.assert_allclose(ta.times, tb.times, rtol=0, atol=1e-12)
            np.testing.assert_allclose(ta.states, tb.states, rtol=0, atol=1e-9)
            assert [e.kind for e in ta.events] == [e.kind for e in tb.events]
            for x, z in zip(ta.events, tb.events):
                assert abs(x.t - z.t) <= 1e-9
                np.testing.assert_allclose(x.state, z.state, rtol=0, atol=1e-9)
                if x.kind == "support":
                    assert (x.entered, x.left, x.lifted, x.touched) == (z.entered, z.left, z.lifted, z.touched)
                else:
                    assert x.message == z.message
            for key in ("wheel_work", "friction_dissipation", "kinetic_start", "kinetic_end"):
                assert ta.stats[key] == pytest.approx(tb.stats[key], abs=1e-9)
            assert ta.stats["mode_changes"] == tb.stats["mode_changes"]
            assert ta.status == tb.status  # (one parcel runs off the array's edge: the engine tips it)
    return int(plant._glide.reasons[0]), plant._glide.reasons


def test_parcels_catching_up_and_riding_across_cells_are_the_engines_to_rounding():
    # at rest under 0.5 m/s along x: each catches up after u / (mu g) and rides, crossing a column every 0.2 s
    parcels = [{"x": 0.5 + 0.6 * i, "y": 0.5 + 0.6 * j} for i in range(2) for j in range(2)]
    written, reasons = same_runs(scene([0.5, 0.0], parcels))
    assert written >= len(parcels) and reasons[1:].sum() == 0


def test_both_axes_slipping_turned_footprints_and_parcels_against_the_wheels():
    # a diagonal field: each axis catches up at its own time; parcels turned, some moving against the wheels (their
    # slip reverses the motion before the catch-up); the plant advanced at once, then a tenth of a second at a time.
    # Parcels of 0.45 m keep every supporting cell well loaded (a small one moving diagonally lifts corner cells
    # off: those pieces go to the engine)
    parcels = [{"x": 0.6 + 0.7 * k, "y": 1.5, "theta": 0.3 * k, "vx": -0.2 + 0.1 * k, "vy": 0.1} for k in range(4)]
    for every, least in ((None, 8), (0.1, 25)):
        written, reasons = same_runs(scene([0.4, -0.3], parcels, side=0.45), every)
        assert written >= least


def test_cells_beside_the_footprint_may_move_otherwise():
    # the cells of the rows beside a parcel's way stand still (as a sorter leaves cells no vehicle is on): they push
    # nothing, so the parcel still takes the closed form, and agrees with the engine; a cell on its way that stands
    # still hands its window back
    def beside(positions, V):
        V[(np.abs(positions[:, 1] - 1.0) > 0.15) & (np.abs(positions[:, 1] - 2.0) > 0.15)] = 0.0
        V[np.hypot(positions[:, 0] - 1.2, positions[:, 1] - 2.0) < 0.01] = 0.0  # on the second parcel's way
        return V

    sc = scene([0.5, 0.0], [{"x": 1.0, "y": 1.0}, {"x": 1.0, "y": 2.0}], duration=0.5)
    written, reasons = same_runs(sc, change=beside)
    assert reasons[0] >= 1 and reasons[glide.REASONS.index("cells under it moving otherwise")] >= 1


def test_a_pickup_meets_its_closed_form_and_its_energy_account():
    # a parcel at rest picked up by wheels at u: it slips until t = u / (mu g), then rides; the wheels do m u^2 of
    # work and friction dissipates half of it (the classic result: the kinetic energy is the other half)
    u, mu, g, m = 0.5, 0.5, 9.81, 1.5
    sc = scene([u, 0.0], [{"x": 1.0, "y": 1.0}], duration=0.3)
    (parts,), plant = advance(sc, True)
    (tr,) = parts
    assert plant._glide.reasons[0] == 1
    (stick,) = [e for e in tr.events if e.kind == "stick"]
    assert stick.t == pytest.approx(u / (mu * g), abs=1e-15)
    assert tr.states[-1][3] == u and tr.states[-1][4] == 0.0
    t_end = 0.3
    x_end = 1.0 + u * u / (2 * mu * g) + u * (t_end - u / (mu * g))
    assert tr.states[-1][0] == pytest.approx(x_end, abs=1e-14)
    assert tr.stats["wheel_work"] == pytest.approx(m * u * u, rel=1e-13)
    assert tr.stats["friction_dissipation"] == pytest.approx(0.5 * m * u * u, rel=1e-13)
    assert tr.stats["kinetic_end"] - tr.stats["kinetic_start"] == pytest.approx(
        tr.stats["wheel_work"] - tr.stats["friction_dissipation"], abs=1e-13)


def test_what_the_closed_form_does_not_cover_goes_to_the_engine():
    # a turning parcel, and one whose cells ahead move otherwise (a second field region): handed back, with reasons
    sc = scene([0.5, 0.0], [{"x": 1.0, "y": 1.0, "omega": 0.5}, {"x": 2.0, "y": 2.0}], duration=0.2)
    (turning, other), plant = advance(sc, True)
    reasons = dict(zip(glide.REASONS, plant._glide.reasons.tolist()))
    assert reasons["turns"] >= 1
    setup = parse_scenario(scene([0.5, 0.0], [{"x": 1.0, "y": 1.0}], duration=0.3)).build()
    plant = setup.plant()
    V = np.array(setup.contact_velocities, dtype=float)
    ahead = np.flatnonzero(np.hypot(*(plant.cells.positions - [1.2, 1.0]).T) < 0.06)
    V[ahead] = [0.3, 0.0]  # one cell ahead of the parcel runs slower
    ys = [y.copy() for y in setup.states]
    (tr,) = plant.advance(ys, [True], V, 0.0, 0.3, 0.05)  # (its front edge reaches that cell's centre at 0.27 s)
    assert plant._glide.reasons[glide.REASONS.index("cells under it moving otherwise")] == 1
    assert plant._glide.reasons[0] == 0 and tr.status == "completed"


def test_a_layer_without_two_uniform_wheels_per_cell_is_not_served():
    setup = parse_scenario(scene([0.5, 0.0], [{"x": 1.0, "y": 1.0}])).build()
    cells = setup.plant().cells
    assert glide.GlideStepper.serves(cells)
    from dataclasses import replace
    active = np.ones((cells.n, 2), bool)
    active[7, 1] = False
    assert not glide.GlideStepper.serves(replace(cells, wheel_active=active))


def test_a_cell_on_an_edge_at_the_start_is_the_engines_to_call():
    # a 0.2 m parcel riding at the wheels' speed, centred on a cell: its front and back edges lie on the next cells'
    # centres at the start (to rounding), which the engine counts as a crossing a rounding step later; the closed
    # form hands it back
    sc = scene([0.5, 0.0], [{"x": 1.0, "y": 1.05, "vx": 0.5}], duration=0.3, side=0.2)
    written, reasons = same_runs(sc)
    assert reasons[glide.REASONS.index("events too close together")] >= 1
