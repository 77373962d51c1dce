"""The support solve in closed form (the 3x3 moment system by cofactors, paper eqs. 8-19 reduced) against the
LAPACK solve it replaced: the contact set of the compiled active-set iteration (``contact_set``, LAPACK least
squares) and the spring plane from the pseudo-inverse of that set's moment matrix, on random support sets of square
and hexagonal lattices of any pitch, the centre of mass anywhere inside them (lift-off included)."""

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from virtual_vehicle.physics.contact import contact_set, solve_support


def lattice_cells(rng, hexagonal: bool, pitch: float, keep: float) -> np.ndarray:
    """A random subset (each cell kept with probability ``keep``) of a 5 x 5 lattice of ``pitch`` (m), shifted and
    turned at random, as the cells under a footprint are."""
    i, j = np.meshgrid(np.arange(5.0), np.arange(5.0))
    x = i + (0.5 * (j % 2) if hexagonal else 0.0)
    y = j * (np.sqrt(3) / 2 if hexagonal else 1.0)
    pts = pitch * np.column_stack([x.ravel(), y.ravel()])
    angle = rng.uniform(-np.pi, np.pi)
    turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return pts[rng.random(len(pts)) < keep] @ turn.T + rng.uniform(-10, 10, 2)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 100_000), st.booleans(), st.floats(0.01, 0.5), st.floats(0.3, 1.0), st.floats(0.0, 0.999),
       st.floats(0.1, 500.0))
def test_closed_form_solve_equals_the_lapack_solve(seed, hexagonal, pitch, keep, reach, weight):
    rng = np.random.default_rng(seed)
    pts = lattice_cells(rng, hexagonal, pitch, keep)
    assume(len(pts) >= 3)
    centred = pts - pts.mean(axis=0)
    assume(np.linalg.svd(centred, compute_uv=False)[-1] > 1e-3 * pitch)  # not on one line (the 1-D model's case)
    # the centre of mass between the centroid and a random cell: inside the hull, near its edge as reach -> 1
    com = pts.mean(axis=0) + reach * (pts[rng.integers(len(pts))] - pts.mean(axis=0))
    sol = solve_support(pts, com, weight)
    xi = com - sol.origin
    basis = np.column_stack([np.ones(len(pts)), sol.points])
    rhs = weight * np.array([1.0, xi[0], xi[1]])
    reference_set = contact_set(basis, rhs)
    on = basis[reference_set]
    assume(np.linalg.cond(on.T @ on) < 1e8)  # contacts not near one line: the closed form hands those to LAPACK
    assert np.array_equal(sol.in_contact, reference_set)
    minv = np.linalg.pinv(on.T @ on)
    plane_lin, plane_const = weight * minv[:, 1:], weight * minv[:, 0]
    scale = np.abs(np.column_stack([plane_lin, plane_const])).max()
    np.testing.assert_allclose(sol.plane_lin, plane_lin, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(sol.plane_const, plane_const, rtol=0, atol=1e-12 * scale)
    forces = basis @ (plane_lin @ xi + plane_const)
    np.testing.assert_allclose(sol.forces(com), np.where(reference_set, forces, 0.0), rtol=0, atol=1e-12 * weight)


def test_contacts_near_one_line_still_solve():
    # two rows of cells with the centre of mass on the line of one of them: that row carries the parcel, the other
    # lifts off (a contact set on one line, whose moment matrix is singular: the LAPACK path's case)
    pts = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.0, 0.1], [0.1, 0.1], [0.2, 0.1]])
    sol = solve_support(pts, [0.1, 0.0], 10.0)
    np.testing.assert_allclose(sol.forces([0.1, 0.0]), [10 / 3, 10 / 3, 10 / 3, 0, 0, 0], atol=1e-9)
