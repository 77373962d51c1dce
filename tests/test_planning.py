"""The plant's planner: its meet times against a scalar root finder, its windows on a uniform field (the viscous
and stick-slip bounds relative to the wheels' common velocity, so they stop shrinking) and on a rotation field (both
bounds in the field's turning frame), the stick-slip bounds against the event engine's motion, and no overlap missed
in crowds."""

import numpy as np
import pytest
from scipy.optimize import brentq

from virtual_vehicle.engine.plant import Integration, Plant, meet_times
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import rectangle
from virtual_vehicle.model.fields import Rotation, Twist, Uniform
from virtual_vehicle.physics.collide import lever_of, point_reach, point_reaches, rigid_rotation, wheel_frame
from virtual_vehicle.physics.laws import LAWS, rotating_reach

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


def test_the_rigid_rotation_of_a_rotation_or_a_turning_twist_is_its_own_and_a_translation_has_none():
    """A rotation field's and a turning twist's centre and rate come back to rounding, the wheels 0 off them; a
    uniform field has no rotation; wheels put off a rotation are off it by their largest sum over one cell's
    wheels."""
    cells = layout.grid(12, 9, 0.1)
    for field, centre, omega in ((Rotation((0.4, 0.7), -0.8), (0.4, 0.7), -0.8),
                                 (Twist((0.5, 0.5), (0.2, -0.1, 0.5)), (0.5 + 0.1 / 0.5, 0.5 + 0.2 / 0.5), 0.5)):
        got = rigid_rotation(cells.positions, field.velocities(cells), cells.active_directions)
        assert np.allclose(got[0], centre, atol=1e-12) and got[1] == pytest.approx(omega, rel=1e-12)
        assert got[2] <= 1e-14
    assert rigid_rotation(cells.positions, Uniform((0.3, 0.1)).velocities(cells), cells.active_directions) is None
    off = np.zeros((cells.n, 2))
    off[17] = [0.03, -0.02]  # grid cells' wheels run along x and y
    got = rigid_rotation(cells.positions, Rotation((0.4, 0.7), -0.8).velocities(cells) + off, cells.active_directions)
    assert got[2] == pytest.approx(0.05, rel=0.02)  # (the fit moves a little toward the odd cell)
    # asked for a rotation nearer than ``beyond``: judged on a sample of 64 entries first, then on them all
    big = layout.grid(40, 40, 0.1)
    turning = Rotation((2.0, 1.0), 0.7).velocities(big)
    got = rigid_rotation(big.positions, turning, big.active_directions, beyond=0.1)
    assert got is not None and got[1] == pytest.approx(0.7, rel=1e-12)
    odd = turning.copy()
    odd[5] += [0.3, 0.0]  # not among the sample (every 25th entry): only the whole array's pass sees it
    assert rigid_rotation(big.positions, odd, big.active_directions, beyond=0.2) is None
    assert rigid_rotation(big.positions, odd, big.active_directions, beyond=0.4)[2] == pytest.approx(0.3, rel=0.02)
    sorter = np.random.default_rng(1).uniform(-0.3, 0.3, (big.n, 2))
    assert rigid_rotation(big.positions, sorter, big.active_directions, beyond=0.3) is None


def test_windows_on_a_rotation_field_last_while_the_parcels_ride_it():
    """Two stick-slip parcels riding a turntable 0.5 m apart: in the field's turning frame neither moves but for the
    centrifugal drift a lost grip could give, so the window is the planner's longest, where the translating
    frame (the wheels' speeds spread over the whole array) allowed ~0.1 s; the run then misses no overlap."""
    cells = layout.grid(20, 20, 0.1)
    field = Rotation((1.0, 1.0), 0.5).velocities(cells)
    spec = rectangle(0.3, 0.2, 2.0, 0.6, mu_static=0.8)

    def riding(x):
        return np.array([x, 1.0, 0.0, 0.0, 0.5 * (x - 1.0), 0.5])

    plant = Plant(cells, [spec, spec], LAWS["stick_slip"], G)
    ys = [riding(0.6), riding(1.4)]
    W, groups = plant.plan(ys, [True, True], field, 0.0, 3.0)
    assert groups == [] and W == plant.contact.window
    W_translating, _ = plant.plan(ys, [True, True], field, 0.0, 3.0, rotation=None)
    assert W_translating < 0.2
    plant.advance(ys, [True, True], field, 0.0, 3.0, 0.1)
    assert plant.record.undetected_overlaps == 0 and plant.record.windows <= 4
    for y, x in zip(ys, (0.6, 1.4)):  # still riding, a quarter turn on (x - 1 turned by 1.5 rad)
        assert np.hypot(y[0] - 1.0, y[1] - 1.0) == pytest.approx(abs(x - 1.0), abs=1e-6)
        assert y[2] == pytest.approx(1.5, abs=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_stick_slip_reach_bounds_the_event_engine_in_a_turning_frame(seed):
    """Stick-slip parcels from random twists on a rotation field with random wheels a little off it (up to 4 cm/s
    a wheel), moved by the event engine (exact modes, support changes): at every sample no point of the outline
    has moved further in the field's turning frame, or moves faster relative to it, than
    :func:`rotating_reach` with the law's frame power allows (the planner's proof, on a turntable, rests on it)."""
    rng = np.random.default_rng(seed)
    cells = layout.grid(40, 40, 0.1)
    centre, omega = rng.uniform(1.5, 2.5, 2), rng.uniform(0.3, 1.0) * rng.choice([-1.0, 1.0])
    field = Rotation(tuple(centre), omega).velocities(cells) + rng.uniform(-0.02, 0.02, (cells.n, 2))
    c, w, slack = rigid_rotation(cells.positions, field, cells.active_directions)
    specs = [rectangle(0.22, 0.3, 1.5, 0.5, mu_static=0.6), rectangle(0.3, 0.3, 4.0, 0.4)]
    ys = []
    for k, spec in enumerate(specs):
        p = np.array([1.2 + 1.6 * k, 2.0])
        r = p - c
        ys.append(np.array([*p, rng.uniform(-1, 1), *(w * np.array([-r[1], r[0]]) + rng.normal(0, 0.3, 2)),
                            w + rng.normal(0, 1.0)]))
    start = [y.copy() for y in ys]
    plant = Plant(cells, specs, LAWS["stick_slip"], G)
    out = plant.advance(ys, [True] * len(ys), field, 0.0, 0.8, 0.02)
    worst = 0.0
    for spec, y0, tr in zip(specs, start, out):
        r0 = y0[:2] - c
        rel = y0[3:5] - w * np.array([-r0[1], r0[0]])
        energy = rel @ rel + spec.inertia / spec.mass * (y0[5] - w) ** 2
        power = LAWS["stick_slip"].frame_power(max(spec.mu, spec.mu_static or 0) * spec.mass * G, slack)
        dist, speed = rotating_reach(np.hypot(*r0), energy + 2 * power * tr.times / spec.mass, w, lever_of(spec),
                                     tr.times)
        c0 = np.asarray(spec.world_polygon(y0).exterior.coords)[:-1]
        for t, y, d, v in zip(tr.times, tr.states, dist, speed):
            a = -w * t
            back = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            corners = np.asarray(spec.world_polygon(y).exterior.coords)[:-1]
            moved = np.max(np.hypot(*((corners - c) @ back.T + c - c0).T))
            r = y[:2] - c
            fastest = np.hypot(*(y[3:5] - w * np.array([-r[1], r[0]]))) + abs(y[5] - w) * spec.radius
            assert moved <= d * (1 + 1e-9) + 1e-12 and fastest <= v * (1 + 1e-9) + 1e-12
            worst = max(worst, moved / d if d > 0 else 0.0)
    assert worst > 0.05  # the bound is exercised, not met with room to spare by orders of magnitude


@pytest.mark.parametrize("law", ["viscous", "stick_slip"])
def test_a_crowd_on_a_turntable_pushes_but_never_overlaps_unnoticed(law, monkeypatch):
    """Sixteen parcels on a turntable that also draws them inward (wheels well off the rotation): they meet and
    push, and at no window end do two parcels integrated apart overlap, whichever frame planned the window (the
    turning frame plans some: those without a group)."""
    import virtual_vehicle.engine.plant as plant_module

    turned = []

    def counted(*args):
        turned.append(1)
        return rotating_reach(*args)

    monkeypatch.setattr(plant_module, "rotating_reach", counted)
    rng = np.random.default_rng(8)
    cells = layout.grid(30, 30, 0.1)
    toward = 1.5 - cells.positions
    field = Rotation((1.5, 1.5), 0.8).velocities(cells) + 0.3 * toward / np.maximum(np.hypot(*toward.T), 0.1)[:, None]
    spec = rectangle(0.22, 0.22, 1.5, 2.0 if law == "viscous" else 0.5)
    xs = [(0.65 + 0.5 * i, 0.65 + 0.5 * j) for i in range(4) for j in range(4)]
    ys = [np.array([x, y, rng.uniform(-0.3, 0.3), *rng.normal(0, 0.1, 2), rng.normal(0, 0.5)]) for x, y in xs]
    plant = Plant(cells, [spec] * len(ys), LAWS[law], G, Integration(dt=2e-3))
    plant.advance(ys, [True] * len(ys), field, 0.0, 1.5, 0.1)
    assert plant.record.parcel_contacts > 0
    assert plant.record.undetected_overlaps == 0
    assert turned  # windows without a group planned in the turning frame


def test_a_parcel_flung_off_a_fast_turntable_stays_within_the_turning_frames_bound():
    """A stick-slip parcel put riding a turntable too fast for its grip (omega^2 rho = 7.2 m/s^2 against mu_s g =
    5.9) slides outward, the event engine moving it: the centrifugal drift the turning frame's bound allows for
    (rho0 (cosh(omega T) - 1) from riding) holds it at every sample, within a factor of about six (the rim's lever
    and the energy bound); without that drift the bound would be 0."""
    cells = layout.grid(40, 40, 0.1)
    centre, w = np.array([2.0, 2.0]), 2.0
    field = Rotation(tuple(centre), w).velocities(cells)
    spec = rectangle(0.3, 0.3, 4.0, 0.5, mu_static=0.6)
    r0 = np.array([1.8, 0.0])
    y0 = np.array([*(centre + r0), 0.0, *(w * np.array([-r0[1], r0[0]])), w])
    plant = Plant(cells, [spec], LAWS["stick_slip"], G)
    ys = [y0.copy()]
    tr = plant.advance(ys, [True], field, 0.0, 0.4, 0.02)[0]
    power = LAWS["stick_slip"].frame_power(0.6 * spec.mass * G, 0.0)
    dist, _ = rotating_reach(1.8, 0.0 + 2 * power * tr.times / spec.mass, w, lever_of(spec), tr.times)
    c0 = np.asarray(spec.world_polygon(y0).exterior.coords)[:-1]
    ratios = []
    for t, y, d in zip(tr.times, tr.states, dist):
        a = -w * t
        back = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        corners = np.asarray(spec.world_polygon(y).exterior.coords)[:-1]
        moved = np.max(np.hypot(*((corners - centre) @ back.T + centre - c0).T))
        assert moved <= d * (1 + 1e-9) + 1e-12
        ratios.append(moved / d if d > 0 else 0.0)
    assert np.hypot(*(ys[0][:2] - centre)) > 1.85  # it was flung outward
    assert max(ratios) > 0.1
