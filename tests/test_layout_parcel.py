"""Cell arrays and parcels: construction, validation, support detection."""

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import layout, parcel


def test_grid_row_points():
    g = layout.grid(3, 2, 0.25, origin=(1.0, -1.0))
    assert g.n == 6 and g.shape == (2, 3)
    np.testing.assert_allclose(g.positions[4], [1.25, -0.75])
    np.testing.assert_allclose(g.drive_directions[0], np.eye(2))
    assert not g.is_line and layout.row(5, 0.1).is_line
    p = layout.from_points([[0, 0], [0.2, 0], [0, 0.2], [0.2, 0.2]])
    assert p.pitch == pytest.approx(0.2)
    rotated = layout.grid(2, 2, 0.1, drive_angle=np.pi / 6)
    u = rotated.drive_directions[0]
    assert u[0] @ u[1] == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_allclose(u[0], [np.cos(np.pi / 6), np.sin(np.pi / 6)])


def test_layout_validation():
    with pytest.raises(ValueError, match="same position"):
        layout.from_points([[0, 0], [0, 0]])
    with pytest.raises(ValueError, match="pitch"):
        layout.grid(2, 2, -0.1)
    with pytest.raises(ValueError, match="at least one"):
        layout.grid(0, 2, 0.1)
    with pytest.raises(ValueError, match="orthogonal"):
        layout.CellArray(np.zeros((1, 2)), np.array([[[1.0, 0.0], [1.0, 0.0]]]), 0.1)


def test_the_model_raises_plain_errors_and_the_scenario_names_the_field():
    """The model knows nothing of scenario files: a bad argument is a plain ValueError without a TOML path; the
    scenario that made the call names the field, down to the entry of a list."""
    with pytest.raises(ValueError, match="^two cells share the same position$") as exc:
        layout.from_points([[0, 0], [0, 0]])
    assert not isinstance(exc.value, ScenarioError)
    with pytest.raises(ValueError, match="^com, the centre of mass") as exc:
        parcel.polygon([[0, 0], [1, 0], [1, 1], [0, 1]], 1.0, 0.5, com=[2.0, 2.0])
    assert not isinstance(exc.value, ScenarioError)
    box = {"name": "box", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 0.5, "x": 0.05, "y": 0.05}
    field = {"kind": "uniform", "velocity": [0.1, 0.0]}
    doubled = {"kind": "points", "points": [[0.0, 0.0], [0.1, 0.0], [0.1, 0.0]]}
    with pytest.raises(ScenarioError, match=r"^array\.points: two cells share the same position$"):
        parse_scenario({"duration": 1.0, "array": doubled, "field": field, "parcels": [box]}).build()
    odd = dict(box, length=None, width=None, vertices=[[0, 0], [0.1, 0], [0.1, 0.1], [0, 0.1]], com=[0.3, 0.3])
    with pytest.raises(ScenarioError, match=r"^parcels\[0\]: com, the centre of mass \[0.3, 0.3\], must lie inside"):
        parse_scenario({"duration": 1.0, "array": {"kind": "grid", "nx": 3, "ny": 3, "pitch": 0.1}, "field": field,
                        "parcels": [odd]}).build()
    belts = [{"start": [-0.3, 0.1], "end": [-0.1, 0.1], "width": 0.1, "speed": 0.1},
             {"start": [0.0, 0.1], "end": [0.5, 0.1], "width": 0.1, "speed": 0.1}]
    with pytest.raises(ScenarioError, match=r"^array\.belts\[1\]: the belt from \[0.0, 0.1\] to \[0.5, 0.1\] m covers "
                                            r"cell 3 at \[0.0, 0.1\] m"):
        parse_scenario({"duration": 1.0, "array": {"kind": "grid", "nx": 3, "ny": 3, "pitch": 0.1, "belts": belts},
                        "field": field, "parcels": [box]}).build()


def test_rectangle_inertia_and_validation():
    p = parcel.rectangle(0.3, 0.2, 1.5, 0.4)
    assert p.inertia == pytest.approx(1.5 * (0.09 + 0.04) / 12)
    assert p.half_extents == (0.15, 0.1)
    with pytest.raises(ValueError, match="mass"):
        parcel.rectangle(0.3, 0.2, -1.0, 0.4)
    with pytest.raises(ValueError, match="width"):
        parcel.rectangle(0.3, 0.0, 1.0, 0.4)
    notched = parcel.ParcelSpec(np.array([[-1, -1], [1, -1], [0, -0.5], [1, 1], [-1, 1]], float), 1.0, 1.0, 0.5)
    assert not notched.convex  # non-convex outlines are fine
    with pytest.raises(ValueError, match="simple polygon"):
        parcel.ParcelSpec(np.array([[-1, -1], [1, 1], [1, -1], [-1, 1]], float), 1.0, 1.0, 0.5)
    clockwise = parcel.ParcelSpec(np.array([[-1, -1], [-1, 1], [1, 1], [1, -1]], float), 1.0, 1.0, 0.5)
    assert clockwise.polygon.exterior.is_ccw and not shapely.Polygon(clockwise.footprint[::-1]).exterior.is_ccw


@settings(max_examples=100, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-np.pi, np.pi))
def test_margins_agree_with_shapely_and_the_generic_polygon_path(x, y, theta):
    spec = parcel.rectangle(0.4, 0.3, 1.0, 0.5)
    # the same rectangle with a fifth vertex mid-edge: not the closed form's four corners, so the half-plane path
    generic = parcel.ParcelSpec(np.array([[-0.2, -0.15], [0.0, -0.15], [0.2, -0.15], [0.2, 0.15], [-0.2, 0.15]]), 1.0,
                                1.0, 0.5)
    assert generic.half_extents is None and generic.convex
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, size=(50, 2))
    m = parcel.footprint_margins(spec, (x, y, theta), pts)
    np.testing.assert_allclose(m, parcel.footprint_margins(generic, (x, y, theta), pts), atol=1e-12)
    poly = spec.world_polygon((x, y, theta))
    import shapely

    inside = shapely.contains_xy(poly, pts[:, 0], pts[:, 1])
    clear = np.abs(m) > 1e-9
    assert np.array_equal((m > 0)[clear], inside[clear])
    # inside, the margin is the distance to the boundary
    dist = shapely.distance(poly.exterior, shapely.points(pts))
    np.testing.assert_allclose(m[m > 0], dist[m > 0], atol=1e-12)


def test_supporting_cells_tree_matches_brute_force():
    cells = layout.grid(20, 20, 0.1)
    spec = parcel.rectangle(0.45, 0.35, 1.0, 0.5)
    rng = np.random.default_rng(3)
    for pose in rng.uniform([0, 0, -3], [2, 2, 3], size=(50, 3)):
        a = parcel.supporting_cells(spec, pose, cells.positions, cells.tree)
        b = parcel.supporting_cells(spec, pose, cells.positions)
        assert a.tolist() == b.tolist()


LAYOUTS = {
    "grid": lambda rng: layout.grid(20, 20, 0.1).positions,
    "scattered": lambda rng: rng.uniform(-1.0, 3.0, size=(300, 2)),
    "row": lambda rng: layout.row(40, 0.05).positions,
    "thin": lambda rng: np.column_stack([rng.uniform(0, 2, 200), rng.uniform(0, 1e-9, 200)]),
    "clusters": lambda rng: np.concatenate([rng.uniform(0, 0.3, (100, 2)), rng.uniform(50, 50.3, (100, 2))]),
    "one": lambda rng: np.array([[0.4, -0.2]]),
    "none": lambda rng: np.zeros((0, 2)),
}


@pytest.mark.parametrize("kind", LAYOUTS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(0, 30), reach=st.floats(0.0, 0.6))
def test_point_grid_gathers_every_point_within_reach(kind, seed, count, reach):
    """Every point within ``reach`` of a centre (as a KD-tree finds them) is among those the grid gathers for it,
    and each gathered point lies in a bucket that meets the centre's square: a superset, never a miss, once each;
    the bucket count stays linear in the points (thin and clustered layouts too)."""
    rng = np.random.default_rng(seed)
    pts = LAYOUTS[kind](rng)
    grid = parcel.PointGrid(pts)
    assert np.prod(grid.shape) <= 3 * max(len(pts), 1) + 2 * np.sqrt(max(len(pts), 1)) + 1
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(2), np.ones(2))
    centres = rng.uniform(lo - 0.5, hi + 0.5, size=(count, 2))
    radii = rng.uniform(0.0, reach, size=count)
    owner, point = grid.near(centres, radii)
    assert np.all(np.diff(owner) >= 0)  # grouped by centre
    for k in range(count):
        mine = point[owner == k]
        assert len(set(mine.tolist())) == len(mine)
        expected = cKDTree(pts).query_ball_point(centres[k], radii[k]) if len(pts) else []
        assert set(expected) <= set(mine.tolist())
        slack = grid.size * (1 + 1e-9)  # a gathered point's bucket meets the square
        assert np.all(np.abs(pts[mine] - centres[k]) <= radii[k] + slack)


@pytest.mark.parametrize("kind", LAYOUTS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), reach=st.floats(0.0, 0.6), far=st.floats(0.0, 60.0))
def test_point_grid_within_is_a_ball_query(kind, seed, reach, far):
    """``within`` gives exactly the ids a KD-tree's sorted ball query gives, for centres on, near and far off the
    layout (the bucket range clipped on every side), and of those only the ones ``present``."""
    rng = np.random.default_rng(seed)
    pts = LAYOUTS[kind](rng)
    grid = parcel.PointGrid(pts)
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(2), np.ones(2))
    present = rng.random(len(pts)) < 0.7
    for centre in [*rng.uniform(lo - 0.5, hi + 0.5, size=(10, 2)), lo - far, hi + far, [lo[0] - far, hi[1]],
                   [hi[0] + far, lo[1]], *(pts[:3] if len(pts) else [])]:
        r = rng.uniform(0.0, reach)
        expected = np.asarray(cKDTree(pts).query_ball_point(centre, r, return_sorted=True) if len(pts) else [],
                              dtype=int)
        got = grid.within(centre[0], centre[1], r)
        assert got.tolist() == expected.tolist()
        assert grid.within(centre[0], centre[1], r, present).tolist() == expected[present[expected]].tolist()


def test_point_grid_refuses_what_it_cannot_bin():
    with pytest.raises(ValueError, match="finite"):
        parcel.PointGrid([[0.0, 0.0], [np.nan, 1.0]])
    with pytest.raises(ValueError, match="finite"):
        parcel.PointGrid([[0.0, 0.0], [1.0, 1.0]]).near([[0.0, np.inf]], 0.1)
    for x, reach in ((np.nan, 0.1), (0.0, -0.1), (0.0, np.inf)):
        with pytest.raises(ValueError, match="finite"):
            parcel.PointGrid([[0.0, 0.0], [1.0, 1.0]]).within(x, 0.0, reach)


def test_a_point_grid_keeps_its_own_read_only_copy_of_the_points():
    """A PointGrid keeps its own read-only copy of the points (one compiled signature for every grid)."""
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.2, 0.0]])
    grid = parcel.PointGrid(pts)
    assert not grid.points.flags.writeable and pts.flags.writeable and not np.shares_memory(grid.points, pts)
    assert grid.within(0.1, 0.0, 0.15).tolist() == [0, 2]


def test_covered_pairs_are_the_points_strictly_under_each_footprint():
    """Many parcels of several outlines at once: exactly the points whose margin is positive, parcel by parcel."""
    rng = np.random.default_rng(7)
    pts = rng.uniform(0.0, 3.0, size=(4000, 2))
    specs = [parcel.rectangle(0.4, 0.3, 1.0, 0.5), parcel.rectangle(0.2, 0.2, 1.0, 0.5),
             parcel.polygon([[0, 0], [0.4, 0], [0.5, 0.2], [0.2, 0.35], [-0.05, 0.2]], 2.0, 1.0),
             parcel.polygon([[0, 0], [0.4, 0], [0.4, 0.12], [0.12, 0.12], [0.12, 0.4], [0, 0.4]], 2.0, 1.0,
                            com=(0.1, 0.1))] * 3
    states = [np.concatenate([rng.uniform([0.3, 0.3, -3], [2.7, 2.7, 3]), np.zeros(3)]) for _ in specs]
    owner, point = parcel.covered_pairs(specs, states, parcel.PointGrid(pts))
    for k, (spec, y) in enumerate(zip(specs, states)):
        assert sorted(point[owner == k].tolist()) == np.flatnonzero(parcel.footprint_margins(spec, y, pts) > 0).tolist()
    assert [len(a) for a in parcel.covered_pairs([], [], parcel.PointGrid(pts))] == [0, 0]
