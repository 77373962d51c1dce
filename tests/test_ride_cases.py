"""A second reading of the ride's proof (issue 32): the cases tests/test_ride.py leaves out. Each run that may ride
equals the run that never rides, to 1e-9 m / rad, where the proof is tightest or the wheels are least uniform: a turn
near the grip's limit (low static friction, fast turns), wheels that give no traction (free wheels) or are held
still (stuck wheels, dead cells) under a rigid field, a parcel overhanging the array's edge, a parcel whose centre
of mass is off its outline's centroid, and parcels riding side by side in touch."""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from test_ride import CELLS, PERIOD, SPEC, aisle, assert_same, run, turn
from virtual_vehicle.engine.plant import Integration, Plant
from virtual_vehicle.model import parcel
from virtual_vehicle.physics import laws


def run_on(cells, fields, y0s, batch: bool, specs):
    """As test_ride.run, on contact layer ``cells`` (m/s fields over its entries)."""
    plant = Plant(cells, specs, laws.StickSlipLaw(), integration=Integration(batch=batch))
    ys, active = [np.array(y, dtype=float) for y in y0s], [True] * len(y0s)
    ticks, k = [], 0
    while (V := fields(k)) is not None:
        ticks.append(plant.advance(ys, active, V, k * PERIOD, (k + 1) * PERIOD, PERIOD))
        k += 1
    return ticks, plant.record


def held(V: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Field ``V`` (m/s) on CELLS with the wheels ``mask`` ((n, 2) bool) held still: their surface speed along their
    drive direction is zero, the cell's other wheel keeps its own."""
    speeds = np.einsum("nkd,nd->nk", CELLS.drive_directions, V)
    speeds[mask] = 0.0
    return np.einsum("nk,nkd->nd", speeds, CELLS.drive_directions)


def at_twist(x: float, y: float, theta: float, omega: float, centre) -> list[float]:
    """The state of a parcel at (``x``, ``y``) m, heading ``theta`` rad, moving with a rigid turn at ``omega`` rad/s
    about ``centre`` (m): its velocity is omega x (position - centre)."""
    return [x, y, theta, omega * (centre[1] - y), omega * (x - centre[0]), omega]


def rides_as_exact(fields, y0: list[float], specs=None) -> None:
    """The run that may ride equals the run that never rides (one parcel at ``y0``)."""
    a, _ = run(fields, [y0], True, specs)
    b, _ = run(fields, [y0], False, specs)
    assert_same(a, b)


@settings(max_examples=10, deadline=None)
@given(mu_s=st.floats(0.001, 0.05), omega=st.floats(0.1, 0.4), radius=st.floats(0.15, 0.5),
       sign=st.sampled_from([-1, 1]), angle=st.floats(-np.pi, np.pi), theta=st.floats(-np.pi, np.pi))
@example(mu_s=0.005, omega=0.3, radius=0.5, sign=1, angle=0.0, theta=0.0)  # m omega^2 r 0.068 N, mu_s W 0.074 N
@example(mu_s=0.001, omega=0.2, radius=0.3, sign=1, angle=0.0, theta=0.0)  # 0.018 N over 0.015 N: it slips
@example(mu_s=0.02, omega=0.2, radius=0.3, sign=1, angle=1.0, theta=0.0)  # 0.018 N: rides
def test_a_turn_near_the_grip_limit(mu_s, omega, radius, sign, angle, theta):
    """A parcel carried at the field's twist by a slow rigid turn (few support changes) with so little static friction
    that its centripetal force m omega^2 r is near what its sticking wheels hold (tests/test_ride_grip.py: the
    zonotope's facets, not its inradius): the rides the proof takes are the exact run's, and a parcel whose grip
    fails (at ``mu_s`` 0.001) slips as there."""
    spec = parcel.rectangle(0.33, 0.24, 1.5, mu_s * 0.8, mu_static=mu_s)
    x, y = 1.5, 0.7
    omega *= sign
    centre = np.array([x + radius * np.cos(angle), y + radius * np.sin(angle)])
    V = turn(omega, centre)
    fields = lambda k: V if k < 25 else None  # noqa: E731
    rides_as_exact(fields, at_twist(x, y, theta, omega, centre), [spec])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2 ** 16), share=st.floats(0.05, 0.5), kind=st.sampled_from(["aisle", "turn"]),
       fault=st.sampled_from(["free", "stuck", "dead"]), start=st.sampled_from([0.0, 1.0]))
def test_rigid_fields_over_faulty_wheels(seed, share, kind, fault, start):
    """A rigid field whose cells differ in their wheels' faults: free wheels (the contact layer loses that drive
    direction), stuck wheels and dead cells (their surface speed held at zero, which keeps an x aisle rigid over a
    stuck y wheel but not over a stuck x wheel). The run that rides is the exact one."""
    rng = np.random.default_rng(seed)
    mask = rng.random((CELLS.n, 2)) < share
    if fault == "dead":
        mask = np.repeat(mask[:, :1], 2, axis=1)
    cells = CELLS
    if kind == "aisle":
        V, v, omega = aisle(0.3, 0.0), np.array([0.3, 0.0]), 0.0
    else:
        omega, centre = 0.4, np.array([1.5, 0.2])
        V = turn(omega, centre)
        v = omega * np.array([centre[1] - 0.7, 1.4 - centre[0]])
    if fault == "free":
        cells = dataclasses.replace(CELLS, wheel_active=~mask)
    else:
        V = held(V, mask)
    y0 = [1.4, 0.7, 0.3, *(start * v), start * omega]
    fields = lambda k: V if k < 30 else None  # noqa: E731
    a, _ = run_on(cells, fields, [y0], True, [SPEC])
    b, rec_b = run_on(cells, fields, [y0], False, [SPEC])
    assert rec_b.quiet_steps == 0
    assert_same(a, b)


@settings(max_examples=8, deadline=None)
@given(y=st.floats(-0.1, 0.05), theta=st.floats(-0.3, 0.3), speed=st.floats(0.1, 0.5),
       omega=st.sampled_from([0.0, 0.3]))
def test_riding_along_the_edge(y, theta, speed, omega):
    """A parcel overhanging the array's lower edge rides an aisle along it, or a slow turn about a point above it
    (its support polygon near the centre of mass: little slack), some tipping off at once: as the exact run."""
    if omega:
        centre = (0.8, y + speed / omega)
        V = turn(omega, centre)  # (speed, 0) at the parcel's centre
        y0 = [0.8, y, theta, speed, 0.0, omega]
    else:
        V = aisle(speed, 0.0)
        y0 = [0.8, y, theta, speed, 0.0, 0.0]
    fields = lambda k: V if k < 30 else None  # noqa: E731
    rides_as_exact(fields, y0)


@settings(max_examples=8, deadline=None)
@given(cx=st.floats(-0.1, 0.1), cy=st.floats(-0.05, 0.05), omega=st.floats(-0.8, 0.8), theta=st.floats(-np.pi, np.pi))
def test_an_off_centre_mass_in_a_turn(cx, cy, omega, theta):
    """An L-shaped parcel whose centre of mass is off its centroid, carried by a rigid turn at the field's twist."""
    spec = parcel.polygon([(0, 0), (0.4, 0), (0.4, 0.15), (0.15, 0.15), (0.15, 0.35), (0, 0.35)], 2.0, 0.5,
                          com=(0.12 + cx * 0.5, 0.1 + cy), mu_static=0.6)
    centre = np.array([1.5, 0.1])
    V = turn(omega, centre)
    x, y = 1.5, 0.7
    fields = lambda k: V if k < 30 else None  # noqa: E731
    rides_as_exact(fields, at_twist(x, y, theta, omega, centre), [spec])


@settings(max_examples=6, deadline=None)
@given(gap=st.floats(0.0, 0.02), speed=st.floats(0.1, 0.4), start=st.sampled_from([0.0, 1.0]))
def test_parcels_side_by_side(gap, speed, start):
    """Two parcels touching (or nearly) side by side, and a third nose to tail, in one aisle: stepped together or
    riding, the run is the exact one."""
    y0s = [[1.0, 0.5, 0.0, start * speed, 0.0, 0.0], [1.0, 0.74 + gap, 0.0, start * speed, 0.0, 0.0],
           [1.33 + gap, 0.5, 0.0, start * speed, 0.0, 0.0]]
    fields = lambda k: aisle(speed, 0.0) if k < 30 else None  # noqa: E731
    a, rec_a = run(fields, y0s, True)
    b, rec_b = run(fields, y0s, False)
    assert rec_a.parcel_contacts == rec_b.parcel_contacts
    assert_same(a, b)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), m=st.integers(3, 12), share=st.floats(0.0, 1.0), lever=st.floats(0.01, 1.0),
       still=st.booleans())
def test_the_grip_bound_holds_wherever_the_centre_goes(seed, m, share, lever, still):
    """The ride's grip bound (engine/ride.py, module docstring): with the sticking wheels' normal forces affine in
    the centre and positive within ``s`` of it (every ``|grad N_j| <= N_j / s``), a centre moved by ``D <= s`` leaves
    a zonotope whose inradius is at least ``(1 - D / s) rho - D (1 + D / s) sum mu_s N_j``, ``rho`` the anchor's:
    checked against the inradius there (wheels up to ``lever`` m from the centre, forces in N, torques in N m). With
    the forces ``still`` (constant) only the levers move: the zonotope is sheared, and the bound's second term is
    what holds it."""
    from virtual_vehicle.physics.stick_modes import zonotope_inradius

    rng = np.random.default_rng(seed)
    points = rng.uniform(-lever, lever, (m, 2))
    angles = rng.uniform(-np.pi, np.pi, m)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    mu_s, N0, slack = rng.uniform(0.05, 1.0), rng.uniform(0.1, 10.0, m), rng.uniform(0.001, 0.5)
    grad = rng.normal(size=(m, 2))
    grad *= (N0 * rng.uniform(0.0, 0.0 if still else 1.0, m) / np.linalg.norm(grad, axis=1))[:, None] / slack
    step = rng.normal(size=2)
    step *= share * slack / np.linalg.norm(step)
    D = float(np.linalg.norm(step))

    def generators(centre, N):
        r = points - centre
        return mu_s * N[:, None] * np.column_stack([dirs, r[:, 0] * dirs[:, 1] - r[:, 1] * dirs[:, 0]])

    rho = zonotope_inradius(generators(np.zeros(2), N0))
    bound = (1 - D / slack) * rho - D * (1 + D / slack) * mu_s * N0.sum()
    assert zonotope_inradius(generators(step, N0 + grad @ step)) >= bound - 1e-12 * (1 + rho)


@settings(max_examples=8, deadline=None)
@given(layer=st.sampled_from(["separate", "three"]), kind=st.sampled_from(["aisle", "turn"]),
       theta=st.floats(-np.pi, np.pi), start=st.sampled_from([0.0, 1.0]))
def test_rigid_fields_over_one_wheel_contacts(layer, kind, theta, start):
    """Contact layers of one wheel per contact (a square grid's wheels apart; a hexagonal grid's three-wheel cells,
    drive directions 120 degrees apart): each contact is one row of the ride's rank test, and a rigid field over
    them rides as the exact run."""
    from virtual_vehicle.model import layout

    cells = layout.separate_wheels(layout.grid(30, 14, 0.1)) if layer == "separate" else \
        layout.three_wheels(layout.hexagonal(30, 14, 0.1))
    if kind == "aisle":
        V, v, omega = np.tile([0.25, 0.1], (cells.n, 1)), np.array([0.25, 0.1]), 0.0
    else:
        omega, centre = 0.4, np.array([1.5, 0.2])
        p = cells.positions - centre
        V = np.column_stack([-omega * p[:, 1], omega * p[:, 0]])
        v = omega * np.array([centre[1] - 0.7, 1.4 - centre[0]])
    y0 = [1.4, 0.7, theta, *(start * v), start * omega]
    fields = lambda k: V if k < 30 else None  # noqa: E731
    a, rec_a = run_on(cells, fields, [y0], True, [SPEC])
    b, _ = run_on(cells, fields, [y0], False, [SPEC])
    assert_same(a, b)
    assert rec_a.quiet_steps > 0 or kind == "turn"  # (an aisle rides once the parcel is at its speed)


@settings(max_examples=6, deadline=None)
@given(omega=st.floats(-3.0, 3.0), offset=st.floats(0.0, 0.05), theta=st.floats(-np.pi, np.pi))
def test_spinning_about_a_point_under_the_parcel(omega, offset, theta):
    """A rigid turn about a point under the parcel (its centre of mass at most 5 cm off it): the centre hardly
    moves (``|v| T`` near 0) while every corner sweeps ``|omega| R T``, so cells cross the outline in most windows
    and the clearance must count the turning, not the centre's travel."""
    centre = np.array([1.5 + offset, 0.75])
    V = turn(omega, centre)
    fields = lambda k: V if k < 40 else None  # noqa: E731
    rides_as_exact(fields, at_twist(1.5, 0.75, theta, omega, centre))
