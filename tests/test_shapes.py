"""Parcels of any simple outline: inertia against textbook formulas, signed margins against shapely, support
detection in notches, exact event positions, and scenario files."""

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.physics.contact import normal_forces

L_SHAPE = [[0, 0], [0.4, 0], [0.4, 0.15], [0.15, 0.15], [0.15, 0.3], [0, 0.3]]


def rect_inertia_about(m, w, h, cx, cy, px, py):
    return m * (w * w + h * h) / 12 + m * ((cx - px) ** 2 + (cy - py) ** 2)


def test_inertia_matches_textbook_formulas():
    # L-shape = two rectangles (0.4 x 0.15 and 0.15 x 0.15), parallel-axis theorem about the combined centroid
    a1, a2 = 0.4 * 0.15, 0.15 * 0.15
    m = 2.0
    m1, m2 = m * a1 / (a1 + a2), m * a2 / (a1 + a2)
    c1, c2 = (0.2, 0.075), (0.075, 0.225)
    cx = (m1 * c1[0] + m2 * c2[0]) / m
    cy = (m1 * c1[1] + m2 * c2[1]) / m
    expected = rect_inertia_about(m1, 0.4, 0.15, *c1, cx, cy) + rect_inertia_about(m2, 0.15, 0.15, *c2, cx, cy)
    spec = parcel.polygon(L_SHAPE, m, 0.5)
    assert spec.inertia == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(spec.footprint[0], [-cx, -cy], atol=1e-15)  # body origin at the centre of mass
    # triangle with sides a, b, c: I = m (a^2 + b^2 + c^2) / 36 about its centroid
    tri = np.array([[0, 0], [0.5, 0], [0.1, 0.3]])
    sides = np.linalg.norm(tri - np.roll(tri, 1, axis=0), axis=1)
    assert parcel.polygon(tri, 3.0, 0.5).inertia == pytest.approx(3.0 * np.sum(sides**2) / 36, rel=1e-12)
    # a rectangle outline agrees with rectangle(); an off-centre centre of mass adds m d^2
    r = parcel.polygon([[0, 0], [0.3, 0], [0.3, 0.2], [0, 0.2]], 1.5, 0.5)
    assert r.inertia == pytest.approx(parcel.rectangle(0.3, 0.2, 1.5, 0.5).inertia, rel=1e-12)
    off = parcel.polygon([[0, 0], [0.3, 0], [0.3, 0.2], [0, 0.2]], 1.5, 0.5, com=(0.2, 0.1))
    assert off.inertia == pytest.approx(r.inertia + 1.5 * 0.05**2, rel=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-np.pi, np.pi))
def test_nonconvex_margins_are_shapely_signed_distances(x, y, th):
    spec = parcel.polygon(L_SHAPE, 1.0, 0.5)
    assert not spec.convex
    pts = np.random.default_rng(1).uniform(-1.4, 1.4, size=(40, 2))
    m = parcel.footprint_margins(spec, (x, y, th), pts)
    poly = spec.world_polygon((x, y, th))
    d = shapely.distance(poly.exterior, shapely.points(pts))
    inside = shapely.contains_xy(poly, pts[:, 0], pts[:, 1])
    np.testing.assert_allclose(m, np.where(inside, d, -d), atol=1e-12)


def test_cells_in_the_notch_do_not_support():
    spec = parcel.polygon(L_SHAPE, 1.0, 0.5)
    cells = layout.grid(5, 4, 0.1, origin=(-0.05, -0.05))
    centroid = np.array(shapely.Polygon(L_SHAPE).centroid.coords[0])
    ids = parcel.supporting_cells(spec, (*centroid, 0.0), cells.positions)
    inside = shapely.contains_xy(shapely.Polygon(L_SHAPE), cells.positions[:, 0], cells.positions[:, 1])
    assert ids.tolist() == np.flatnonzero(inside).tolist()
    assert not inside[cells.n - 1]  # the far corner cell (0.35, 0.25) is in the notch


def test_events_of_an_l_shape_are_exactly_on_its_outline():
    spec = parcel.polygon(L_SHAPE, 2.0, 1.0)
    cells = layout.grid(20, 12, 0.1)
    m = ParcelModel(cells, spec, fields.Uniform((0.3, 0.1)).velocities(cells), laws.ViscousLaw())
    tr = integrate(m, [0.4, 0.4, 0.2, 0, 0, 0.5], 0, 2.0)
    assert tr.status == "completed" and len(tr.events) > 20
    for e in tr.events:
        ids = list(e.entered) + list(e.left)
        if ids:
            assert np.abs(parcel.footprint_margins(spec, e.state, cells.positions[ids])).max() < 1e-9


def test_off_centre_mass_loads_the_near_cells():
    box = [[0, 0], [0.3, 0], [0.3, 0.3], [0, 0.3]]
    spec = parcel.polygon(box, 2.0, 0.5, com=(0.2, 0.15))
    pts = np.array([[0.05, 0.05], [0.25, 0.05], [0.05, 0.25], [0.25, 0.25]])
    N = normal_forces(pts, np.array([0.2, 0.15]), spec.weight(9.81))
    assert N[1] > N[0] and np.isclose(N @ pts[:, 0], spec.weight(9.81) * 0.2)


def l_scenario(**changes) -> dict:
    """The CLI tests' base scenario with the L-shaped parcel instead of its rectangle."""
    from test_cli import base

    d = base()
    p = d["parcels"][0]
    del p["length"], p["width"]
    p.update({"vertices": L_SHAPE, "x": 0.25, "y": 0.2, **changes})
    return d


def test_scenario_outlines():
    setup = parse_scenario(l_scenario()).build()
    assert not setup.specs[0].convex
    for changes, field in (({"vertices": [[0, 0], [1, 1], [1, 0], [0, 1]]}, "vertices"),
                           ({"com": [5.0, 5.0]}, "com"),
                           ({"length": 0.3}, "either length and width")):
        with pytest.raises(ScenarioError, match=field):
            parse_scenario(l_scenario(**changes)).build()
