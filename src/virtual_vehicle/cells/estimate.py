"""Parcel pose from the cells' binary presence sensors (paper Sections 1 and 2.2: the array "sees" parcels only as
a pattern of shadowed phototransistors).

Units: SI (m, rad, s).

The footprint of a known parcel is consistent with a reading when every lit sensor is inside it and every dark
sensor outside. The consistent poses form a region whose size is set by the sensor spacing; the estimate is the pose
deepest inside it: it minimises ``sum_lit exp(-m / s) + sum_dark exp(m / s)`` over the sensors near the parcel,
``m`` the sensor's signed margin in the footprint (positive inside,
:func:`~virtual_vehicle.model.parcel.footprint_margins`)
and ``s`` a softness of a quarter of the sensor spacing. Over time a prediction (the last estimate moved by the
commanded motion) seeds the search and a weak pull toward it picks, among poses the pattern cannot tell apart, the
one the motion explains. Lit sensors are grouped into parcels by proximity (connected lit sensors within 1.5 sensor
spacings).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from virtual_vehicle.model.parcel import ParcelSpec, footprint_margins


def sensor_spacing(points: np.ndarray) -> float:
    """Median distance (m) from a sensor to its nearest neighbour at another point (the default layout puts two
    sensors on every shared cell edge)."""
    flat = np.unique(np.round(points.reshape(-1, 2), 12), axis=0)
    if len(flat) < 2:
        return 1.0
    d, _ = cKDTree(flat).query(flat, k=2)
    return float(np.median(d[:, 1]))


def blobs(points: np.ndarray, lit: np.ndarray, spacing: float) -> list[np.ndarray]:
    """Groups of lit sensors (indices into the flattened sensor list), one per parcel seen, largest first."""
    flat = points.reshape(-1, 2)
    idx = np.flatnonzero(lit.reshape(-1))
    if not len(idx):
        return []
    pairs = cKDTree(flat[idx]).query_pairs(1.5 * spacing, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])) if len(pairs) else ([], ([], [])),
                       shape=(len(idx), len(idx)))
    _, labels = connected_components(graph, directed=False)
    groups = [idx[labels == k] for k in range(labels.max() + 1)]
    return sorted(groups, key=len, reverse=True)


def initial_pose(points: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Centroid and principal axis of a group of lit sensors: a first guess (x, y, theta) m, m, rad."""
    p = points.reshape(-1, 2)[group]
    c = p.mean(axis=0)
    if len(p) < 3:
        return np.array([c[0], c[1], 0.0])
    w, v = np.linalg.eigh(np.cov((p - c).T))
    axis = v[:, np.argmax(w)]
    return np.array([c[0], c[1], float(np.arctan2(axis[1], axis[0]))])


def estimate_pose(spec: ParcelSpec, points: np.ndarray, lit: np.ndarray, guess, *, spacing: float | None = None,
                  prior_weight: float = 1e-3, headings=(0.0,)) -> tuple[np.ndarray, float]:
    """The pose (x, y, theta) of ``spec`` most consistent with the readings ``lit`` ((n, S) bool) of sensors at
    ``points`` ((n, S, 2) m), searched from ``guess`` (and from ``guess`` turned by each of ``headings``, rad, for
    shapes whose pattern cannot tell those apart). Returns the pose and the number of sensors it contradicts."""
    flat = points.reshape(-1, 2)
    on = lit.reshape(-1)
    spacing = spacing or sensor_spacing(points)
    s = spacing / 4
    guess = np.asarray(guess, dtype=float)[:3]
    near = np.asarray(cKDTree(flat).query_ball_point(guess[:2], spec.radius + 3 * spacing), dtype=int)
    pts, sign = flat[near], np.where(on[near], -1.0, 1.0)
    scale = np.array([spacing, spacing, spacing / max(spec.radius, 1e-9)])

    def cost(z):
        pose = guess + z * scale
        m = footprint_margins(spec, pose, pts)
        e = np.clip(sign * m / s, -50, 50)
        return float(np.sum(np.exp(e))) + prior_weight * float(z @ z)

    best, best_cost = guess, np.inf
    for turn in headings:
        z0 = np.array([0.0, 0.0, turn / scale[2]])
        res = minimize(cost, z0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-10, "maxiter": 2000})
        if res.fun < best_cost:
            best, best_cost = guess + res.x * scale, res.fun
    m = footprint_margins(spec, best, pts)
    wrong = int(np.sum((m > 0) != on[near]))
    return best, wrong
