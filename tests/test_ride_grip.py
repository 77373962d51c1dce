"""The riding parcel's grip, tested against its zonotope's facets (issue 32 item 6): a pure force is held exactly as
far as the facets say (not only within the zonotope's inradius, which its torque facets set about ten times lower
on 0.1 m cells), and the margins for a moved centre and a turning force keep it held. Turns the inradius refused
now ride, as the exact run moves; a turn just outside a facet is refused and really slips."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from test_ride import CELLS, assert_same, run, turn
from virtual_vehicle.model import parcel
from virtual_vehicle.physics import contact
from virtual_vehicle.physics.stick_modes import wheel_arrays, zonotope_grip, zonotope_inradius

GRAVITY = 9.81  # m/s^2, the plant's default


def holds(G: np.ndarray, wrench: np.ndarray) -> bool:
    """Whether ``wrench`` (N, N, N m) lies in the zonotope ``{G^T lam : |lam_j| <= 1}``: a feasible linear program,
    independent of the facet enumeration under test."""
    res = linprog(np.zeros(len(G)), A_eq=G.T, b_eq=wrench, bounds=[(-1.0, 1.0)] * len(G), method="highs")
    return res.status == 0


def generators(points, dirs, N, mu_s, centre) -> np.ndarray:
    """The rows ``mu_s N_j [u_j, r_j x u_j]`` of wheels at ``points`` (m) driving along ``dirs``, ``r`` from
    ``centre`` (m)."""
    r = points - centre
    return mu_s * N[:, None] * np.column_stack([dirs, r[:, 0] * dirs[:, 1] - r[:, 1] * dirs[:, 0]])


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), m=st.integers(3, 10), lever=st.floats(0.02, 1.0), share=st.floats(0.0, 0.9),
       still=st.booleans())
def test_the_grip_is_the_facet_test_wherever_the_centre_goes(seed, m, lever, share, still):
    """At the anchor the grip's ``g`` is exact: a force along ``d`` of size ``(1 -+ 1e-4) / g`` is held / not held
    (a linear program decides). With the centre moved by ``Delta`` (``|Delta| <= D <= share s``; normal forces
    affine in it, within ``(1 -+ D / s)`` of the anchor's) and the force turned to ``d'``, the ride's test
    ``|F| (g + a |d' - d| + b D) < 1 - D / s`` accepts only forces the moved zonotope holds. ``still``: the normal
    forces do not change, only the levers."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-lever, lever, (m, 2))
    angles = rng.choice([0.0, np.pi / 2], m) if m > 4 else rng.uniform(-np.pi, np.pi, m)  # roller grids: x and y
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    mu_s, N0, slack = rng.uniform(0.05, 1.0), rng.uniform(0.1, 10.0, m), rng.uniform(0.001, 0.5)
    G0 = generators(points, dirs, N0, mu_s, np.zeros(2))
    if np.linalg.matrix_rank(G0) < 3:
        return
    d = rng.normal(size=2)
    d /= np.linalg.norm(d)
    g, a, b = zonotope_grip(G0, d, 0.0)
    assert 0 < g <= a and b >= 0
    assert holds(G0, np.r_[(1 - 1e-4) / g * d, 0.0])
    assert not holds(G0, np.r_[(1 + 1e-4) / g * d, 0.0])
    assert zonotope_inradius(G0) <= 1 / a * (1 + 1e-9)  # the inradius holds every direction: at most the least reach
    grad = rng.normal(size=(m, 2))
    grad *= (N0 * rng.uniform(0.0, 0.0 if still else 1.0, m) / np.linalg.norm(grad, axis=1))[:, None] / slack
    step = rng.normal(size=2)
    step *= share * slack / np.linalg.norm(step)
    D = float(np.linalg.norm(step))
    turned = rng.uniform(0, 0.3)
    d2 = np.array([[np.cos(turned), -np.sin(turned)], [np.sin(turned), np.cos(turned)]]) @ d
    size = 0.999 * (1 - D / slack) / (g + a * np.linalg.norm(d2 - d) + b * D)  # just inside the test
    assert holds(generators(points, dirs, N0 + grad @ step, mu_s, step), np.r_[size * d2, 0.0])


def grip_case(spec, y0, omega: float, centre):
    """The generators (N, N, N m) of the wheels under parcel ``spec`` at state ``y0`` on a turn at ``omega`` (rad/s)
    about ``centre`` (m), from the support's normal forces (eq. 19), and its centripetal force ``m omega x v`` (N)."""
    support = parcel.supporting_cells(spec, y0[:3], CELLS.positions)
    solution = contact.solve_support(CELLS.positions[support], np.asarray(y0[:2]), spec.weight(GRAVITY))
    P, U, _, _, _, FL, FC, origin, mus, _ = wheel_arrays(CELLS, support, solution, turn(omega, centre), spec.mu,
                                                         spec.mu_static)
    N = FL @ (np.asarray(y0[:2]) - origin) + FC
    on = (N > 0) & (mus > 0)
    G = generators(P[on], U[on], N[on], 1.0, np.asarray(y0[:2])) * mus[on, None]
    force = spec.mass * omega * np.array([-y0[4], y0[3]])
    return G, force


def on_turn(x: float, y: float, omega: float, centre) -> list[float]:
    """A parcel at (x, y) m, heading 0, moving with the turn at ``omega`` rad/s about ``centre`` (m)."""
    return [x, y, 0.0, omega * (centre[1] - y), omega * (x - centre[0]), omega]


@settings(max_examples=4, deadline=None)
@given(mu_s=st.floats(0.003, 0.008), angle=st.floats(-np.pi, np.pi))
@example(mu_s=0.005, angle=0.0)  # 0.018 N against an inradius of 0.0098 N and facets 0.049 N away
def test_turns_the_inradius_refused_ride_as_the_exact_run(mu_s, angle):
    """A slow turn (0.2 rad/s, 0.3 m from its centre) with so little static friction that the centripetal force is
    above the zonotope's inradius but inside its facets: the parcel rides most windows, and the run equals the run
    that never rides to 1e-9 m / rad."""
    spec = parcel.rectangle(0.33, 0.24, 1.5, mu_s * 0.8, mu_static=mu_s)
    omega, x, y = 0.2, 1.5, 0.7
    centre = np.array([x + 0.3 * np.cos(angle), y + 0.3 * np.sin(angle)])
    y0 = on_turn(x, y, omega, centre)
    G, force = grip_case(spec, y0, omega, centre)
    assert np.linalg.norm(force) > zonotope_inradius(G)  # the old bound refused it
    assert holds(G, np.r_[1.2 * force, 0.0])  # the facets hold it, with room
    fields = lambda k: turn(omega, centre) if k < 20 else None  # noqa: E731
    a, record = run(fields, [y0], True, [spec])
    b, _ = run(fields, [y0], False, [spec])
    assert record.quiet_steps >= 10
    assert_same(a, b)


def test_a_turn_just_outside_a_facet_is_refused_and_slips():
    """The same turn with the static friction set so the centripetal force is 2 % outside the zonotope along its
    direction: the window is refused and the exact run slips (its velocity leaves the field's at its centre). A
    control 10 % inside (room for the window's margins) rides as the exact run."""
    omega, x, y = 0.2, 1.5, 0.7
    centre = np.array([x + 0.3, y])
    y0 = on_turn(x, y, omega, centre)
    probe = parcel.rectangle(0.33, 0.24, 1.5, 0.004, mu_static=0.005)
    G, force = grip_case(probe, y0, omega, centre)
    reach = 1 / zonotope_grip(G, force / np.linalg.norm(force), 0.0)[0]  # N: the facets' reach along the force
    fields = lambda k: turn(omega, centre) if k < 1 else None  # noqa: E731
    for factor, rides in ((1.02, False), (0.9, True)):
        mu_s = 0.005 * np.linalg.norm(force) / (factor * reach)  # the zonotope scales with mu_s
        spec = parcel.rectangle(0.33, 0.24, 1.5, 0.8 * mu_s, mu_static=mu_s)
        G, force = grip_case(spec, y0, omega, centre)
        assert holds(G, np.r_[force, 0.0]) == rides
        a, record = run(fields, [y0], True, [spec])
        b, _ = run(fields, [y0], False, [spec])
        first = b[0][0]
        end = first.states[-1]
        field = omega * np.array([centre[1] - end[1], end[0] - centre[0]])
        if rides:
            assert record.quiet_steps >= 1
            assert_same(a, b)
            assert np.abs(end[3:5] - field).max() < 1e-9
        else:
            assert record.quiet_steps == 0
            assert np.abs(end[3:5] - field).max() > 1e-6


def test_a_plant_resumed_mid_ride_rides_the_same_windows():
    """The riding parcels' proofs are run state: a plant made afresh and given the state of one mid-ride (through
    the checkpoint's own encoding) goes on as that plant does, to the last bit (the same windows ride, the same
    states), over a turn, an aisle and a field change; three parcels, resumed at several ticks."""
    import copy

    from virtual_vehicle.engine.plant import Plant
    from virtual_vehicle.physics import laws
    from virtual_vehicle.run import checkpoint
    from test_ride import PERIOD, SPEC, aisle

    fields = lambda k: aisle(0.4, 0.05) if k < 20 else turn(0.3, (1.5, 0.7))  # noqa: E731
    y0s = [[0.5, 0.4, 0.1, 0.0, 0.0, 0.0], [1.2, 1.0, 0.0, 0.4, 0.05, 0.0], [2.0, 0.6, -0.3, 0.0, 0.0, 0.0]]

    def going(plant, ys, ticks):
        out = []
        for k in ticks:
            out.append(plant.advance(ys, [True] * 3, fields(k), k * PERIOD, (k + 1) * PERIOD, PERIOD))
        return out

    plant = Plant(CELLS, [SPEC] * 3, laws.StickSlipLaw())
    ys = [np.array(y, dtype=float) for y in y0s]
    states, whole = {}, []
    for k in range(40):
        if k in (12, 27):
            doc, arrays = checkpoint.encode(plant.state())
            back, arrays = checkpoint.unpack(checkpoint.pack({"format_version": checkpoint.FORMAT_VERSION,
                                                              "state": doc}, arrays))
            states[k] = (checkpoint.decode(back["state"], arrays), copy.deepcopy(ys), plant.record.quiet_steps)
        whole.append(going(plant, ys, [k])[0])
    for k, (state, ys_k, rides_k) in states.items():
        fresh = Plant(CELLS, [SPEC] * 3, laws.StickSlipLaw())
        fresh.restore(state)
        tail = going(fresh, ys_k, range(k, 40))
        assert fresh.record.quiet_steps == plant.record.quiet_steps and rides_k < plant.record.quiet_steps
        for ta, tb in zip(whole[k:], tail):
            for ra, rb in zip(ta, tb):
                assert np.array_equal(ra.times, rb.times) and np.array_equal(ra.states, rb.states)
