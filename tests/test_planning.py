"""The plant's planner: its meet times against a scalar root finder, its windows on a uniform field (the viscous
and stick-slip bounds relative to the wheels' common velocity, so they stop shrinking), the stick-slip bound against
the event engine's motion, and no overlap missed in crowds."""

import numpy as np
import pytest
from scipy.optimize import brentq

from virtual_vehicle.engine.plant import Integration, Plant, meet_times
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import rectangle
from virtual_vehicle.physics.collide import lever_of, point_reach, point_reaches, wheel_frame
from virtual_vehicle.physics.laws import LAWS

G = 9.81
SPEC = rectangle(0.22, 0.22, 1.5, 2.0)


@pytest.mark.parametrize("law", ["viscous", "coulomb", "stick_slip"])
def test_meet_times_is_the_earliest_root_never_later(law):
    """Over many pairs at once, the earliest moment their reach bounds could close their gaps: a scalar root
    finder on each pair's closing function (point_reach, one parcel at a time) agrees to 1e-9 s, and the answer
    never comes after that root (the window must end before any pair can meet)."""
    rng = np.random.default_rng(3)
    n = 40
    Y = np.column_stack([rng.uniform(0, 5, (n, 3)), rng.normal(0, 0.3, (n, 3))])
    mu = rng.uniform(0.2, 2.0, n)
    pairs = rng.integers(0, n, (60, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    gaps = rng.uniform(0.01, 0.4, len(pairs))
    H = 1.0
    radius, lever = np.full(n, SPEC.radius), np.full(n, lever_of(SPEC))

    def reach(i, T):
        return point_reach(SPEC, Y[i], T, law=law, mu_max=mu[i], gravity=G, wheel_speed=0.3)[0]

    def closing_of(gaps):
        def closing(sel, T):
            both = np.concatenate([pairs[sel, 0], pairs[sel, 1]])
            r = point_reaches(radius[both], lever[both], Y[both], np.concatenate([T, T]), law=law,
                              mu_max=mu[both], gravity=G, wheel_speed=0.3)[0]
            return r[:len(sel)] + r[len(sel):] - gaps[sel]
        return closing

    roots = [brentq(lambda T: reach(i, T) + reach(j, T) - g, 0.0, H, xtol=1e-12)
             for (i, j), g in zip(pairs, gaps) if reach(i, H) + reach(j, H) >= g]
    assert roots, "some pair must meet within the window for the test to mean anything"
    W = meet_times(closing_of(gaps), gaps, H)
    assert min(roots) - 1e-9 <= W <= min(roots)
    touching = np.where(np.arange(len(gaps)) == 5, 0.0, gaps)
    assert meet_times(closing_of(touching), touching, H) == 0.0  # already within reach
    far = np.full(len(gaps), 1e4)
    assert meet_times(closing_of(far), far, H) == H  # none can meet within H


def test_the_wheel_frame_is_the_field_on_a_uniform_field_and_rest_otherwise():
    v = np.tile([0.2, -0.1], (7, 1))
    frame, spread = wheel_frame(v)
    assert frame.tolist() == [0.2, -0.1] and spread == 0.0
    mixed = np.array([[0.3, 0.0], [-0.3, 0.0], [0.0, 0.3], [0.0, -0.3]])
    frame, spread = wheel_frame(mixed)  # no frame brings every wheel closer than rest does
    assert frame.tolist() == [0.0, 0.0] and spread == pytest.approx(0.3)
    frame, spread = wheel_frame(np.array([[1.0, 0.0], [1.2, 0.1]]))
    assert np.allclose(frame, [1.1, 0.05]) and spread == pytest.approx(np.hypot(0.1, 0.05))


@pytest.mark.parametrize("law", ["viscous", "stick_slip"])
def test_windows_stop_shrinking_on_a_uniform_field(law):
    """Two parcels riding a uniform field side by side, 6 cm apart: relative to the field neither moves, so
    nothing can close the gap and the whole interval is one window; one drifting toward the other at 5 cm/s, the
    window lasts about as long as that drift takes to close the gap (not the few hundredths of a second a bound
    growing with time from rest would give)."""
    cells = layout.grid(40, 20, 0.1)
    field = np.tile([0.2, 0.0], (cells.n, 1))
    spec = SPEC if law == "viscous" else rectangle(0.22, 0.22, 1.5, 0.5)
    plant = Plant(cells, [spec, spec], LAWS[law], G)
    ys = [np.array([1.0, 0.5, 0.0, 0.2, 0.0, 0.0]), np.array([1.0, 0.78, 0.0, 0.2, 0.0, 0.0])]
    assert plant.plan(ys, [True, True], field, 0.0, 5.0) == (5.0, [])
    ys[1][4] = -0.05  # toward the other
    W, groups = plant.plan(ys, [True, True], field, 0.0, 5.0)
    gap = 0.06 - plant.contact.margin
    assert groups == [] and gap / (2 * np.sqrt(lever_of(spec)) * 0.05) <= W <= plant.contact.window
    assert W > 0.5  # the bound growing from rest alone allows ~0.03 s here
    plant.advance(ys, [True, True], field, 0.0, 5.0, 0.1)
    assert plant.record.undetected_overlaps == 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_stick_slip_reach_bounds_the_event_engine_from_a_moving_frame(seed):
    """Stick-slip parcels from random twists on a field of random wheel velocities about a common one (up to
    0.3 m/s off it), moved by the event engine (exact modes, support changes): at every sample no point of the
    outline has moved further from where the frame carried it, or moves faster relative to the frame, than the
    law's reach bound from the wheels' frame and spread allows (the planner's proof that parcels stay apart rests
    on it)."""
    rng = np.random.default_rng(seed)
    cells = layout.grid(40, 40, 0.1)
    common = rng.uniform(-0.2, 0.2, 2)
    off = rng.uniform(0.0, 0.3, cells.n) * np.exp(1j * rng.uniform(0.0, 2 * np.pi, cells.n))
    field = common + np.column_stack([off.real, off.imag])
    frame, spread = wheel_frame(field)
    specs = [rectangle(0.22, 0.3, 1.5, 0.5, mu_static=0.6), rectangle(0.3, 0.3, 4.0, 0.4)]
    ys = [np.array([1.2 + 1.6 * k, 2.0, rng.uniform(-1, 1), *(frame + rng.normal(0, 0.3, 2)), rng.normal(0, 1.0)])
          for k in range(len(specs))]
    start = [y.copy() for y in ys]
    plant = Plant(cells, specs, LAWS["stick_slip"], G)
    out = plant.advance(ys, [True] * len(ys), field, 0.0, 0.8, 0.02)
    worst = 0.0
    for spec, y0, tr in zip(specs, start, out):
        rel0 = np.array([*y0[:3], *(y0[3:5] - frame), y0[5]])
        dist, speed = zip(*(point_reach(spec, rel0, t, law="stick_slip", mu_max=max(spec.mu, spec.mu_static or 0),
                                        gravity=G, wheel_speed=spread) for t in tr.times))
        corners = [spec.world_polygon(y) for y in tr.states]
        c0 = np.asarray(spec.world_polygon(y0).exterior.coords)[:-1]
        for t, y, poly, d, v in zip(tr.times, tr.states, corners, dist, speed):
            moved = np.max(np.hypot(*(np.asarray(poly.exterior.coords)[:-1] - frame * t - c0).T))
            fastest = np.hypot(*(y[3:5] - frame)) + abs(y[5]) * spec.radius
            assert moved <= d * (1 + 1e-9) + 1e-12 and fastest <= v * (1 + 1e-9) + 1e-12
            worst = max(worst, moved / d if d > 0 else 0.0)
    assert worst > 0.05  # the bound is exercised, not met with room to spare by orders of magnitude


@pytest.mark.parametrize("law", ["viscous", "coulomb", "stick_slip"])
def test_a_crowd_on_a_mixed_field_pushes_but_never_overlaps_unnoticed(law):
    """Twenty parcels on a 3 x 3 m floor whose wheels drive everything toward the middle, from random twists:
    they meet and push (contacts), and at no window end do two parcels integrated apart overlap."""
    rng = np.random.default_rng(5)
    cells = layout.grid(30, 30, 0.1)
    toward = 1.5 - cells.positions
    field = 0.3 * toward / np.maximum(np.hypot(*toward.T), 0.1)[:, None]
    spec = rectangle(0.22, 0.22, 1.5, 2.0 if law == "viscous" else 0.5)
    xs = [(0.35 + 0.55 * i, 0.35 + 0.55 * j) for i in range(5) for j in range(5)][:20]
    ys = [np.array([x, y, rng.uniform(-0.3, 0.3), *rng.normal(0, 0.1, 2), rng.normal(0, 0.5)]) for x, y in xs]
    plant = Plant(cells, [spec] * len(ys), LAWS[law], G, Integration(dt=2e-3))
    active = [True] * len(ys)
    plant.advance(ys, active, field, 0.0, 1.5, 0.1)
    assert plant.record.parcel_contacts > 0
    assert plant.record.undetected_overlaps == 0
