"""Friction laws (paper eqs. 20-38): the paper's worked example, constants against direct per-cell sums, and
dissipation of the viscous damping terms."""

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.engine.dynamics import constants_row
from virtual_vehicle.physics.contact import solve_support
from virtual_vehicle.physics.laws import LAWS, CoulombLaw, ViscousLaw, coulomb_constants, viscous_constants

D = 0.1
X2x2 = np.array([[-D / 2, -D / 2], [D / 2, -D / 2], [-D / 2, D / 2], [D / 2, D / 2]])  # eq. 20
F2x2 = np.array([[1, 1], [-1, 1], [1, -1], [-1, -1]], float)  # eq. 21 (columns of the paper's F)
XY_WHEELS = np.broadcast_to(np.eye(2), (4, 2, 2))
FIELDS = ("a", "b", "c", "d", "e", "f", "damping", "weight", "moment_lin", "moment_const", "second_lin",
          "second_const")


def test_paper_2x2_inward_field():
    W, mu = 9.81, 0.5
    k = coulomb_constants(X2x2, F2x2, W, mu)
    R = X2x2[:, 0] * F2x2[:, 1] - X2x2[:, 1] * F2x2[:, 0]
    np.testing.assert_allclose(R, 0, atol=1e-15)  # eq. 26
    # eq. 23: a is diagonal (each force depends only on its own coordinate): a stiffness 2 mu W / d toward the centre
    np.testing.assert_allclose(k.a, -2 * mu * W / D * np.eye(2), rtol=1e-12)
    np.testing.assert_allclose(k.b, 0, atol=1e-12)
    # eq. 29: no torque anywhere over this support set
    rng = np.random.default_rng(0)
    for X in rng.uniform(-D / 2, D / 2, size=(20, 2)):
        assert abs(k.torque(X)) < 1e-12
        np.testing.assert_allclose(k.force(X), -2 * mu * W / D * X, rtol=1e-12)


def test_coulomb_law_derives_eq21_from_wheel_velocities():
    V = 0.3 * F2x2  # wheels spinning inward at 0.3 m/s
    np.testing.assert_array_equal(CoulombLaw().drive_vectors(V, XY_WHEELS), F2x2)
    V[0, 1] = 0.0  # a stopped wheel pushes nothing
    assert CoulombLaw().drive_vectors(V, XY_WHEELS)[0].tolist() == [1.0, 0.0]


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(["coulomb", "viscous", "stick_slip"]))
def test_constants_equal_direct_per_cell_sums(seed, law_name):
    """f = a X + b and tau = X^T c X + (d + e) X + f (eqs. 23, 29, 33, 38) against the sums of eqs. 22/24, 30/34."""
    rng = np.random.default_rng(seed)
    m = int(rng.integers(3, 12))
    P = rng.uniform(-0.5, 0.5, size=(m, 2)) + rng.uniform(-2, 2, size=2)
    angle = rng.uniform(0, np.pi)
    c, s = np.cos(angle), np.sin(angle)
    U = np.broadcast_to(np.array([[c, s], [-s, c]]), (m, 2, 2))
    V = rng.uniform(-1, 1, size=(m, 2))
    W, mu = 15.0, 0.4
    law = LAWS[law_name]  # stick-slip: the sliding regime's, Coulomb's
    com = P.mean(axis=0) + 0.3 * (P[0] - P.mean(axis=0))
    sol = solve_support(P, com, W)
    k = law.constants(sol, V, U, mu)
    N = sol.forces(com)
    state = np.array([*com, 0.0, *rng.uniform(-1, 1, size=2), rng.uniform(-3, 3)])
    fx, fy, tau = law.wrench(P, N, V, U, mu, state)
    xi = com - sol.origin
    np.testing.assert_allclose(k.force(xi, state[3:5], state[5]), [fx, fy], atol=1e-10 * W)
    np.testing.assert_allclose(k.torque(xi, state[3:5], state[5]), tau, atol=1e-10 * W)
    # the law's compiled constants and row: the same constants to the last bit, and the row of those constants (its
    # accelerations against the direct sums: test_kernel)
    mass, inertia = 2.5, 0.3
    k2, row = law.constants_and_row(sol, V, U, mu, mass, inertia)
    for name in FIELDS:
        assert np.array_equal(getattr(k2, name), getattr(k, name)), name
    # views of one packed array: a pickled copy, and one pickled before any was read, the same
    k3 = law.constants_and_row(sol, V, U, mu, mass, inertia)[0]
    for copy in (pickle.loads(pickle.dumps(k2)), pickle.loads(pickle.dumps(k3))):
        assert all(np.array_equal(getattr(copy, name), getattr(k, name)) for name in FIELDS)
    assert type(k3.f) is float and type(k3.second_const) is float
    with pytest.raises(AttributeError, match="no attribute 'g'"):
        k3.g
    assert row == constants_row(k, sol.origin, mass, inertia) and all(type(v) is float for v in row)


def test_viscous_translation_is_coulomb_form_plus_damping():
    """Eq. 33: f = mu V N - mu W Xdot_c; the rotation speed does not enter the net force."""
    W, mu = 10.0, 2.0
    V = np.array([[0.2, 0.1], [0.0, -0.3], [0.5, 0.5], [-0.1, 0.2]])
    k = viscous_constants(X2x2, V, W, mu)
    X = np.array([0.01, -0.02])
    N = solve_support(X2x2, X, W).forces(X)
    v = np.array([0.3, -0.1])
    for omega in (0.0, 1.0, -7.0):
        np.testing.assert_allclose(k.force(X, v, omega), mu * V.T @ N - mu * W * v, rtol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000))
def test_viscous_damping_only_dissipates(seed):
    """With the wheels stopped the viscous law can only take energy out: f . v + tau omega <= 0 (eqs. 33, 38)."""
    rng = np.random.default_rng(seed)
    P = rng.uniform(-1, 1, size=(int(rng.integers(3, 10)), 2))
    com = P.mean(axis=0) + 0.5 * (P[1] - P.mean(axis=0))
    sol = solve_support(P, com, 5.0)
    m = len(P)
    k = ViscousLaw().constants(sol, np.zeros((m, 2)), np.broadcast_to(np.eye(2), (m, 2, 2)), 0.7)
    v, omega = rng.uniform(-1, 1, size=2), rng.uniform(-5, 5)
    xi = com - sol.origin
    power = k.force(xi, v, omega) @ v + k.torque(xi, v, omega) * omega
    assert power <= 1e-12
    # and it is exactly the sum of -mu N_i |slip_i|^2 over the cells
    r = P - com
    slip = -(v + omega * np.column_stack([-r[:, 1], r[:, 0]]))
    np.testing.assert_allclose(power, -0.7 * np.sum(sol.forces(com) * np.sum(slip**2, axis=1)), rtol=1e-9, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 30))
def test_compiled_coulomb_drive_vectors_are_eq21(seed, m):
    """The compiled drive vectors are eq. 21 as numpy writes it, on wheels at any angle, with stopped wheels (zero
    velocity component along them) and wheels at right angles to their cell's velocity."""
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-np.pi, np.pi, size=(m, 2))
    U = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (m, 2 wheels, 2)
    V = rng.standard_normal((m, 2)) * rng.integers(0, 2, size=(m, 1))  # some cells stopped
    V[0] = [-U[0, 0, 1], U[0, 0, 0]]  # cell 0's first wheel at right angles to its velocity
    expected = np.einsum("ik,ikj->ij", np.sign(np.einsum("ij,ikj->ik", V, U)), U)
    np.testing.assert_array_equal(CoulombLaw().drive_vectors(V, U), expected)
