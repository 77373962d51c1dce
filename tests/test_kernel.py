"""The compiled kernels against what they replace and what they must agree with: the event engine
(virtual_vehicle.engine._kernel, its segments and root finder) against the footprint margins of parcel.py (shapely
for non-convex outlines), scipy's DOP853 step by step and scipy's brentq, and itself when a run is handed back to
Python and resumed; parcel.py's compiled margins against its array operations; the support solve's compiled hull
against Qhull. Being the kernels' own unit tests, these may name private functions; every other test goes through
public names."""

import json
import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st
from scipy.integrate import DOP853
from scipy.optimize import brentq
from scipy.spatial import ConvexHull

from virtual_vehicle.engine import _kernel as kernel
from virtual_vehicle.engine import dynamics
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.physics.contact import solve_support
from virtual_vehicle.physics.laws import affine
from virtual_vehicle.run.warm import warm_up

CELLS = layout.grid(30, 30, 0.1)
SHAPES = {
    "rectangle": parcel.rectangle(0.4, 0.3, 2.0, 1.0),
    "convex": parcel.polygon([[0, 0], [0.4, 0], [0.5, 0.2], [0.2, 0.35], [-0.05, 0.2]], 2.0, 1.0),
    "L": parcel.polygon([[0, 0], [0.4, 0], [0.4, 0.12], [0.12, 0.12], [0.12, 0.4], [0, 0.4]], 2.0, 1.0,
                        com=(0.1, 0.1)),
}


@pytest.mark.parametrize("name", SHAPES)
@settings(max_examples=60, deadline=None)
@given(st.floats(1.0, 2.0), st.floats(1.0, 2.0), st.floats(-3.2, 3.2))
@example(1.49609375, 1.25, -0.75)  # the L tips here (found by CI)
def test_compiled_margins_are_the_footprint_margins_of_every_outline(name, segment_at, x, y, th):
    """The engine's event values start with the footprint margins of the candidate cells: the same numbers as
    parcel.footprint_margins (closed form, half-planes, or shapely's signed distance for the L), to rounding, so the
    same cells support the parcel wherever that is not a matter of rounding."""
    spec = SHAPES[name]
    m, piece, seg, y0 = segment_at(CELLS, spec, x, y, th)
    assert seg.arrays.kind == {"rectangle": kernel.RECTANGLE, "convex": kernel.CONVEX, "L": kernel.POLYGON}[name]
    mine = seg.values(y0)[:seg.bounds[1]]
    ref = parcel.footprint_margins(spec, y0, CELLS.positions[seg.ids])
    np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-13)
    clear = np.abs(ref) > 1e-12  # a cell on the outline (to rounding) may fall either way
    assert np.all((mine > 0)[clear] == (ref > 0)[clear])
    # One value alone (as Brent's method asks for the changed ones) is the same number as in the whole vector.
    y1 = y0 + np.array([0.013, -0.007, 0.05, 0.0, 0.0, 0.0])
    every = seg.values(y1)
    assert [kernel.value(seg.arrays, y1, i) for i in range(len(every))] == every.tolist()


def _room(values, gradients):
    """The distance to the zero of affine functions, in numpy (the reference for the compiled support_slack)."""
    norm = np.linalg.norm(gradients, axis=1)
    return np.where(norm > 0, values / np.where(norm > 0, norm, 1.0), np.where(values > 0, np.inf, -np.inf))


@pytest.mark.parametrize("name", SHAPES)
@settings(max_examples=40, deadline=None)
@given(st.floats(1.0, 2.0), st.floats(1.0, 2.0), st.floats(-3.2, 3.2))
def test_anchor_measures_are_the_event_values_and_their_distances_to_zero(name, segment_at, x, y, th):
    """What a quiet-step anchor measures (virtual_vehicle.engine.batch): cell_margins gives the event values' margins to
    the last bit and the smallest |margin|; support_slack gives how far the centre of mass can move before a spring
    force or a hull half-plane reaches zero (each less its noise), as numpy computes it from the solution."""
    m, piece, seg, y0 = segment_at(CELLS, SHAPES[name], x, y, th)
    kind, _, half, normals, offsets, vertices = m.outline
    margins, nearest = kernel.cell_margins(kind, half, normals, offsets, vertices, CELLS.positions[seg.ids], y0)
    assert margins.tolist() == seg.values(y0)[:seg.bounds[1]].tolist()
    assert nearest == np.abs(margins).min()
    assert kernel.cell_margins(kind, half, normals, offsets, vertices, np.zeros((0, 2)), y0)[1] == np.inf
    sol = piece.solution
    xi = y0[:2] - sol.origin
    noise_force, noise_length = 1e-11 * m.weight, 1e-11 * 3.0
    springs = _room(np.abs(sol.spring_values(xi)) - noise_force, sol.basis @ sol.plane_lin)
    hull = _room(sol.hull_slack(xi) - noise_length * np.linalg.norm(sol.hull_normals, axis=1), sol.hull_normals)
    ref = min(springs.min(initial=np.inf), hull.min(initial=np.inf))
    got = kernel.support_slack(sol.basis, sol.plane_lin, sol.plane_const, sol.spring_lin, sol.hull_normals,
                               sol.hull_offsets, xi[0], xi[1], noise_force, noise_length)
    assert got == pytest.approx(ref, rel=1e-12, abs=1e-15)


def test_support_slack_of_constant_functions_is_unbounded_or_none():
    """A spring force that does not depend on the centre of mass (zero gradient) bounds nothing while it is clear of
    its noise, and allows no move at all when it is not; with nothing to bound, the slack is infinite."""
    basis, lin, none2 = np.eye(1), np.zeros((1, 2)), np.zeros((0, 2))
    clear = kernel.support_slack(basis, lin, np.array([5.0]), lin, none2, np.zeros(0), 0.3, 0.1, 1e-9, 1e-11)
    lifted = kernel.support_slack(basis, lin, np.array([1e-12]), lin, none2, np.zeros(0), 0.3, 0.1, 1e-9, 1e-11)
    assert clear == np.inf and lifted == -np.inf
    assert kernel.support_slack(np.zeros((0, 0)), none2, np.zeros(0), none2, none2, np.zeros(0), 0, 0, 0, 0) == np.inf
    # one half-plane x <= 0.5 with the centre of mass at x = 0.2: 0.3 m to go, less the noise
    half = kernel.support_slack(np.zeros((0, 0)), none2, np.zeros(0), none2, np.array([[2.0, 0.0]]), np.array([1.0]),
                                0.2, 7.0, 0.0, 0.01)
    assert half == pytest.approx((1.0 - 0.4 - 0.02) / 2.0)


def test_a_segment_reads_the_supports_off_its_event_values_while_its_candidates_reach():
    """After an event the engine takes the cells under the parcel from the probe's footprint margins, not from a new
    search: the same cells as ``support_at`` wherever the candidate list still covers the footprint, and no answer
    beyond it (nor without values)."""
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    m = ParcelModel(cells, spec, np.zeros((cells.n, 2)), laws.CoulombLaw())
    y0 = np.array([1.12, 1.47, 0.3, 0, 0, 0])
    seg = dynamics._Segment(m, m.piece_at(y0), y0)
    rng = np.random.default_rng(4)
    told = 0
    for _ in range(200):
        y = y0 + np.r_[rng.uniform(-0.15, 0.15, 2), rng.uniform(-1, 1), 0, 0, 0]
        g = seg.values(y)
        found = seg.support(g)
        if np.hypot(*(y[:2] - y0[:2])) < seg.buffer:
            np.testing.assert_array_equal(found, m.support_at(y))
            np.testing.assert_array_equal(kernel._positive(seg.ids, g), found)  # the compiled engine's reading
            told += 1
        else:
            assert found is None
    assert 50 < told < 200 and seg.support(None) is None


def test_a_segment_keeps_its_predecessors_candidates_only_within_half_the_buffer():
    """A segment that starts within half the refresh buffer of where its predecessor gathered its candidates keeps
    them, and their centre, so that its refresh value still counts from there; a segment starting farther gathers
    new ones. Either way it reads the supports off its event values as support_at finds them."""
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    m = ParcelModel(cells, spec, np.zeros((cells.n, 2)), laws.CoulombLaw())
    y0 = np.array([1.12, 1.47, 0.3, 0, 0, 0])
    first = dynamics._Segment(m, m.piece_at(y0), y0)
    near = y0 + np.array([0.03, -0.03, 0.4, 0, 0, 0])  # 0.042 m away: within half of the 0.1 m buffer
    kept = dynamics._Segment(m, m.piece_at(near), near, first)
    assert kept.ids is first.ids and kept.center is first.center
    np.testing.assert_array_equal(kept.support(kept.values(near)), m.support_at(near))
    assert kept.values(near)[-1] == pytest.approx(kept.buffer - np.hypot(0.03, 0.03), abs=1e-15)
    far = y0 + np.array([0.06, 0.0, -0.2, 0, 0, 0])
    fresh = dynamics._Segment(m, m.piece_at(far), far, first)
    assert fresh.ids is not first.ids and fresh.center.tolist() == far[:2].tolist()
    np.testing.assert_array_equal(fresh.support(fresh.values(far)), m.support_at(far))


@settings(max_examples=300, deadline=None)
@given(st.floats(1.0, 2.0), st.floats(1.0, 2.0), st.floats(-3.2, 3.2), st.floats(-0.1, 0.1), st.floats(-0.1, 0.1),
       st.floats(-0.5, 0.5), st.sampled_from([1e-3, 1e-2, 0.1]))
def test_the_event_root_finder_is_scipys_brentq_without_evaluating_the_ends_again(segment_at, x, y, th, dx, dy, dth,
                                                                                 h):
    """Events are located by Brent's method as scipy runs it, on the engine's own event function (the earliest of the
    changed footprint margins along a step's dense output), given the bracket's end values: the same root to the
    last bit, two evaluations fewer."""
    m, piece, seg, y0 = segment_at(layout.grid(30, 30, 0.1), parcel.rectangle(0.4, 0.3, 2.0, 1.0), x, y, th)
    delta = np.array([dx, dy, dth, 0.0, 0.0, 0.0])
    F = np.zeros((7, 6))
    F[0] = delta  # a dense output moving the parcel uniformly by delta over the step [0, h]
    g0, g1 = seg.values(y0), seg.values(y0 + delta)
    changed = np.flatnonzero(((g1 > 0) != (g0 > 0))[:seg.bounds[1]])  # margins only: the hull is not searched
    assume(len(changed))
    sgn = np.where(g0[changed] > 0, 1.0, -1.0)
    calls = np.zeros(1, np.int64)
    ctx = (seg.arrays, F, y0, 0.0, h, changed, sgn, np.empty(6), calls)
    fa, fb = float(np.min(sgn * g0[changed])), float(np.min(sgn * g1[changed]))
    assume(fa > 0 > fb)
    eps = np.finfo(float).eps
    mine, outcome = kernel._brent(ctx, 0.0, h, fa, fb, 1e-13, 4 * eps, 100)
    n_mine = int(calls[0])
    calls[0] = 0
    ref = brentq(lambda t: kernel._phi(t, ctx), 0.0, h, xtol=1e-13, rtol=4 * eps)
    assert outcome == kernel.REACHED and mine == ref and n_mine == calls[0] - 2



_OUTLINES = [parcel.rectangle(0.4, 0.3, 1.0, 0.5), parcel.rectangle(0.2, 0.2, 1.0, 0.5),
             parcel.polygon([[0, 0], [0.4, 0], [0.5, 0.2], [0.2, 0.35], [-0.05, 0.2]], 2.0, 1.0),
             parcel.polygon([[0, 0], [0.4, 0], [0.4, 0.12], [0.12, 0.12], [0.12, 0.4], [0, 0.4]], 2.0, 1.0,
                            com=(0.1, 0.1))]


@settings(max_examples=30, deadline=None)
@given(st.sampled_from([0, 2]), st.floats(-3.2, 3.2), st.integers(0, 2**32 - 1))
def test_the_compiled_margin_of_a_point_is_the_array_margin_to_the_last_bit(which, theta, seed):
    """What the compiled pairs test, point by point: the margin of a rectangle or of a convex outline, the same
    float as _turned_margins makes in array operations (not merely the same sign), near the outline and far."""
    spec = _OUTLINES[which]
    rng = np.random.default_rng(seed)
    dx, dy = rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.4, 0.4, 200)
    c, s = np.cos(np.array([theta])), np.sin(np.array([theta]))
    ref = parcel._turned_margins(spec, c[0], s[0], dx, dy)
    kinds, half, normals, offsets, counts = parcel._outline_table([spec])
    mine = [parcel._turned_margin(kinds[0], half[0], normals[0], offsets[0], counts[0], c[0], s[0], x, y)
            for x, y in zip(dx, dy)]
    assert np.array(mine).tobytes() == ref.tobytes()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from(range(len(_OUTLINES))), min_size=1, max_size=8), st.integers(0, 2**32 - 1),
       st.booleans())
def test_covered_pairs_compiled_keep_what_the_array_margins_keep(kinds, seed, on_lattice):
    """The compiled pairs are those PointGrid.near finds whose margin, computed as _turned_margins computes it in
    array operations, is positive: the same pairs in the same order, to the last rounding step (points on a lattice
    with parcels at rest on it put many exactly on an edge, where the sign is decided by rounding alone)."""
    rng = np.random.default_rng(seed)
    if on_lattice:
        pts = np.stack(np.meshgrid(np.arange(30) * 0.05, np.arange(30) * 0.05), -1).reshape(-1, 2)
        poses = [np.array([0.05 * rng.integers(6, 24), 0.05 * rng.integers(6, 24), 0.5 * np.pi * rng.integers(4)])
                 for _ in kinds]
    else:
        pts = rng.uniform(0.0, 1.5, size=(3000, 2))
        poses = [rng.uniform([0.3, 0.3, -3.2], [1.2, 1.2, 3.2]) for _ in kinds]
    specs = [_OUTLINES[k] for k in kinds]
    states = [np.concatenate([y, rng.normal(size=3)]) for y in poses]
    grid = parcel.PointGrid(pts)
    owner, point = grid.near(np.array(poses)[:, :2], [spec.radius * (1 + 1e-9) + 1e-12 for spec in specs])
    P = np.array(poses)
    cos, sin = np.cos(P[:, 2]), np.sin(P[:, 2])
    keep = np.zeros(len(owner), dtype=bool)
    for k, spec in enumerate(specs):  # as covered_pairs computed them before it was compiled
        sel = owner == k
        at = pts[point[sel]]
        keep[sel] = parcel._turned_margins(spec, cos[k], sin[k], at[:, 0] - P[k, 0], at[:, 1] - P[k, 1]) > 0
    mine = parcel.covered_pairs(specs, states, grid)
    assert mine[0].tolist() == owner[keep].tolist() and mine[1].tolist() == point[keep].tolist()
    assert parcel.covered_pairs(specs, [y[:3] for y in states], grid)[1].tolist() == point[keep].tolist()



def _halfplanes(normals, offsets):
    rows = np.column_stack([normals, offsets])
    return rows[np.lexsort(np.round(rows, 9).T[::-1])]  # ordered as rounded, so that ulps do not reorder ties


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 40), st.booleans())
def test_hull_matches_qhull(seed, m, lattice):
    """The compiled hull's half-planes (physics.contact) are Qhull's (scipy), also on a lattice, where cells lie on
    the hull's edges between its corners and must not make edges of their own."""
    from virtual_vehicle.physics.contact import _hull

    rng = np.random.default_rng(seed)
    if lattice:
        P = 0.1 * rng.integers(0, 6, size=(m, 2)).astype(float)
        assume(np.linalg.matrix_rank(P - P[0]) == 2)
    else:
        P = rng.uniform(-1, 1, size=(m, 2))
    hull = ConvexHull(P)
    ours = _halfplanes(*_hull(P, 1e-12))
    qhull = _halfplanes(hull.equations[:, :2], -hull.equations[:, 2])
    assert ours.shape == qhull.shape
    np.testing.assert_allclose(ours, qhull, atol=1e-12)


def test_compiled_dop853_takes_scipys_steps():
    """From the same state and trial step, the compiled DOP853 lands where scipy's DOP853 lands (the same tableau,
    to rounding: scipy sums stages with BLAS, the kernel in plain loops), accepts or rejects the same trial steps,
    proposes the same next step (to the error estimate's own sensitivity to rounding: it is a small difference of
    large stages) and has the same dense output; here on a viscous piece in steps that grow from 1 ms, up to the
    bound."""
    spec = SHAPES["rectangle"]
    m = ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), 0.2).velocities(CELLS), laws.ViscousLaw())
    y0 = np.array([1.52, 1.47, 0.3, 0.3, -0.2, 1.0])
    piece = m.piece_at(y0)
    ref = DOP853(piece.rhs, 0.0, y0, 1.0, rtol=1e-10, atol=1e-12, first_step=1e-3)
    K, y_new, f_new, work, F, out = np.empty((16, 6)), np.empty(6), np.empty(6), np.empty(6), np.empty((7, 6)), \
        np.empty(6)
    steps = 0
    while ref.status == "running":
        steps += 1
        t, y, f, h_abs = ref.t, ref.y.copy(), ref.f.copy(), ref.h_abs
        ref.step()
        ok, t_new, h_next, _ = kernel._dop853_step(piece.row, t, y, f, 1.0, h_abs, 1e-10, 1e-12, np.inf, K, y_new,
                                                   f_new, work)
        assert ok and t_new == ref.t
        np.testing.assert_allclose(y_new, ref.y, rtol=1e-14, atol=1e-16)
        np.testing.assert_allclose(f_new, ref.f, rtol=1e-13, atol=1e-15)
        assert h_next == pytest.approx(ref.h_abs, rel=1e-6)
        kernel._dense(piece.row, t, y, f, y_new, f_new, t_new - t, K, F, work)
        dense = ref.dense_output()
        for tau in (0.1, 0.5, 0.9):
            kernel.dense_at(F, y, t, t_new - t, t + tau * (t_new - t), out)
            np.testing.assert_allclose(out, dense(t + tau * (t_new - t)), rtol=1e-14, atol=1e-16)
    assert steps > 20 and t_new == 1.0  # the steps grew, and the last one ends at the bound


def test_a_run_handed_back_for_progress_is_the_same_run(monkeypatch):
    """With a progress callback the kernel returns to Python every few steps of a piece (here every 2) and is
    resumed where it stopped: the trajectory is the same to the last bit, and progress moves forward."""
    spec = SHAPES["rectangle"]
    m = ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), 0.2).velocities(CELLS), laws.ViscousLaw())
    y0 = np.array([1.12, 1.47, 0.3, 0.0, 0.0, 0.0])
    seen: list[float] = []
    quiet = integrate(m, y0, 0.0, 20.0, sample_dt=0.5, rtol=1e-12, atol=1e-14)
    monkeypatch.setattr(dynamics, "_PAUSE_STEPS", 2)
    told = integrate(m, y0, 0.0, 20.0, sample_dt=0.5, rtol=1e-12, atol=1e-14, progress=seen.append)
    np.testing.assert_array_equal(told.states, quiet.states)
    np.testing.assert_array_equal(told.times, quiet.times)
    assert [e.t for e in told.events] == [e.t for e in quiet.events]
    assert len(seen) > 3 * told.segments and np.all(np.diff(seen) >= 0) and seen[-1] == 20.0


def test_warming_up_leaves_the_engine_compiled():
    """warm_up() runs a real integration, after which the engine's entry points hold compiled code (loaded from the
    cache or compiled now), so the next integration does not wait."""
    assert warm_up() > 0
    assert kernel.run_events.signatures and kernel.pattern.signatures and kernel.cell_margins.signatures


def test_warming_up_takes_the_loaded_libraries_out_of_the_collectors_passes():
    """In a fresh process warm_up() collects and then freezes what is alive (the libraries and the loaded engine:
    tens of thousands of objects a full collection would pass over); ``settle=False`` leaves the collector alone.
    What is made after it is collected as before."""
    import subprocess
    import sys

    code = """
import gc, sys
from virtual_vehicle.run.warm import warm_up
warm_up(settle=sys.argv[1] == "1")
frozen = gc.get_freeze_count()
class Ring: pass
a, b = Ring(), Ring()
a.other, b.other = b, a
del a, b
print(frozen, gc.collect() >= 2)
"""
    seen = {}
    for settle in ("1", "0"):
        out = subprocess.run([sys.executable, "-c", code, settle], capture_output=True, text=True, check=True)
        frozen, collected = out.stdout.split()
        seen[settle] = int(frozen), collected == "True"
    assert seen["1"][0] > 20_000 and seen["0"][0] == 0
    assert seen["1"][1] and seen["0"][1]  # a cycle made afterwards is still collected


def _kernels_across_a_fresh_run(imports: str, home: str, run: str) -> tuple[dict, dict, dict]:
    """In a fresh process: warm_up(), then the statement ``run`` with the compiled kernels named by ``home`` (a
    statement filling the dict ``home``: kernel name -> module, after ``imports``) counted. Returns each kernel's
    number of signatures before and after the run, and its calls."""
    import subprocess
    import sys
    from pathlib import Path

    code = """
import collections, json, sys
sys.path.insert(0, %r)
%s
from virtual_vehicle.run.warm import warm_up
warm_up()
home = {}
%s
names = tuple(home)
before = {n: len(getattr(home[n], n).signatures) for n in names}
calls = collections.Counter()
def counted(n, f):
    def call(*args):
        calls[n] += 1
        return f(*args)
    return call
kernels = {n: getattr(home[n], n) for n in names}
for n in names:
    setattr(home[n], n, counted(n, kernels[n]))
%s
print(json.dumps([before, {n: len(kernels[n].signatures) for n in names}, calls]))
""" % (str(Path(__file__).resolve().parents[1] / "benchmarks"), imports, home, run)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return tuple(json.loads(out.stdout.strip().splitlines()[-1]))


def test_warming_up_compiles_what_networked_runs_call():
    """In a fresh process, warm_up() leaves the engine's compiled entry points, the quiet step's checks and step and
    the cell query among them, with the very signatures a networked run (25 parcels on 30 x 30, batched quiet
    ticks) then calls them with, so a user's first networked run does not stop to compile: each is called, and none
    gains a signature."""
    before, after, calls = _kernels_across_a_fresh_run(
        """import bench_scale
from virtual_vehicle.engine import _kernel
from virtual_vehicle.physics.laws import affine
from virtual_vehicle.model import parcel
from virtual_vehicle.cells.sorting import policy
from virtual_vehicle.cells.network import delivery
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run_network""",
        """home.update({n: _kernel for n in ("run_events", "pattern", "cell_margins", "support_slack", "edges_clear_many",
                                 "quiet_steps")})
home["_within"] = home["_covered"] = parcel
home["_terms_and_row"] = affine  # the bench_scale hall is viscous
home["step_cells"] = policy
home["_carry"] = delivery""",
        "run_network(parse_scenario(bench_scale.scenario(30, 25, 0.5)).build())")
    assert before == after and min(before.values()) > 0, (before, after)
    assert set(calls) == set(before) and min(calls.values()) > 0, calls


def test_warming_up_compiles_what_stick_slip_runs_call():
    """The same for the default law: after warm_up(), 25 stick-slip parcels in the networked hall (ticked windows:
    parcels catching up with their wheels take the exact mode loop, riding ones the compiled measure of the anchors
    that still stand) call both with signatures warm_up() left (the measure was never reached by it before: its riding
    parcel kept its proof every tick, and the first run loaded it inside its timing). (The pairs benchmark's scene no
    longer reaches the measure: its parcels ride a uniform field in windows of most of a second, across support
    changes, which only the exact loop takes.)"""
    before, after, calls = _kernels_across_a_fresh_run(
        """import bench_scale
from virtual_vehicle.engine import _kernel, _modeloop
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run_network""",
        """home["ride_measure"] = _kernel
home["run_modes"] = _modeloop""",
        "run_network(parse_scenario(bench_scale.scenario(30, 25, 0.5, law='stick_slip')).build())")
    assert before == after and min(before.values()) > 0, (before, after)
    assert set(calls) == set(before) and min(calls.values()) > 0, calls


_TURNTABLE = """name = "turntable"
duration = 1.0
[array]
kind = "grid"
nx = 20
ny = 20
pitch = 0.1
[field]
kind = "rotation"
omega = 0.5
center = [1.0, 1.0]
[friction]
law = "stick_slip"
[[parcels]]
name = "tote"
vertices = [[0, 0], [0.3, 0], [0.3, 0.15], [0.15, 0.15], [0.15, 0.3], [0, 0.3]]
mass = 1.5
mu = 0.6
mu_static = 0.8
x = 1.4
y = 1.0
[[parcels]]
name = "carton"
length = 0.3
width = 0.2
mass = 2.0
mu = 0.6
mu_static = 0.8
x = 0.6
y = 1.0
"""


def test_warming_up_compiles_what_a_non_convex_parcel_calls():
    """The same for an L-shaped tote beside a rectangular carton on a turntable: warm_up() knows only a rectangle,
    whose outline arrays a non-convex parcel's must match in type (writeable), or its first run compiles (or loads)
    the margins and the mode loop again (25 s on a fresh machine, 0.5 s from the cache, when the shared convex
    outlines were read-only)."""
    before, after, calls = _kernels_across_a_fresh_run(
        """from virtual_vehicle.engine import _kernel, _modeloop
from virtual_vehicle.config.scenario import parse_text
from virtual_vehicle.run.sim import run""",
        """home["cell_margins"] = _kernel
home["run_modes"] = _modeloop""",
        "run(parse_text(%r).build())" % _TURNTABLE)
    assert before == after and min(before.values()) > 0, (before, after)
    assert set(calls) == set(before) and min(calls.values()) > 0, calls


def test_max_step_bounds_every_compiled_step():
    """``max_step`` caps the compiled integrator's steps (scipy's rule): a viscous piece that one long step would
    cross takes at least one step per ``max_step``, and ends where the uncapped run ends (to the tolerance)."""
    spec = SHAPES["rectangle"]
    m = ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), 0.2).velocities(CELLS), laws.ViscousLaw())
    y0 = np.array([1.52, 1.47, 0.3, 0.0, 0.0, 0.0])
    free = integrate(m, y0, 0.0, 0.2, sample_dt=0.2)
    capped = integrate(m, y0, 0.0, 0.2, sample_dt=0.2, max_step=1e-3)
    steps_at_least = 200 * (DOP853.n_stages + 3)  # stages and dense output per step
    assert free.rhs_evals < steps_at_least <= capped.rhs_evals
    np.testing.assert_allclose(capped.states[-1], free.states[-1], rtol=0, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 20), st.integers(-50, 50), st.integers(-50, 50))
def test_the_compiled_pattern_is_numpys_and_sees_whole_cell_translations(seed, m, dx, dy):
    """The pattern cache's key (offsets from the first cell in whole resolution units) and origin are numpy's
    round and mean of the cells' positions; a copy of the cells moved by whole pitches has the same key."""
    from virtual_vehicle.engine.dynamics import _PATTERN_RESOLUTION

    pitch = 0.1
    cells = layout.grid(120, 120, pitch)
    rng = np.random.default_rng(seed)
    col, row = rng.integers(50, 70, size=(2, m))
    support = (row * 120 + col).astype(np.int64)
    unit = _PATTERN_RESOLUTION * pitch
    pts, origin, rel = kernel.pattern(cells.positions, support, unit)
    P = cells.positions[support]
    np.testing.assert_array_equal(pts, P)
    np.testing.assert_array_equal(origin, P.mean(axis=0))
    np.testing.assert_array_equal(rel, np.round((P - P[0]) / unit).astype(np.int64))
    moved = (row + dy) * 120 + (col + dx)
    assert kernel.pattern(cells.positions, moved.astype(np.int64), unit)[2].tobytes() == rel.tobytes()


def test_each_row_field_has_its_place_by_name():
    """The row's order is written once, in ROW_FIELDS: each field's ``R_`` place is its index there, one a field."""
    places = {name[2:].lower(): value for name, value in vars(affine).items() if name.startswith("R_")}
    assert places == {name: k for k, name in enumerate(affine.ROW_FIELDS)} and affine.ROW_LENGTH == len(places)


def test_the_compiled_accelerations_read_the_row_as_python_does():
    """The compiled accelerations take the row's places as constants when compiled (numba's cache knows only the
    kernel's file): on a row of distinct values they read what the Python function reads now, so a stale cache
    compiled for another order of ROW_FIELDS fails here. The row writer puts each constant at its place."""
    rng = np.random.default_rng(4)
    row = rng.uniform(0.5, 2.0, affine.ROW_LENGTH)
    for state in rng.normal(0, 0.3, (10, 5)):
        assert kernel.accelerations_compiled(row, *state) == kernel.accelerations(tuple(row.tolist()), *state)
    a, b, c, d, e, moment_lin, moment_const, second_lin = (rng.normal(size=s) for s in
                                                           ((2, 2), 2, (2, 2), 2, 2, (2, 2), 2, 2))
    written = affine.row(a, b, c, d, e, 0.7, 0.3, 9.0, moment_lin, moment_const, second_lin, 0.4, np.array([1.0, 2.0]),
                         0.5, 0.25)
    named = dict(zip(affine.ROW_FIELDS, written.tolist()))
    assert [named[f"a_{ij}"] for ij in ("xx", "xy", "yx", "yy")] == a.ravel().tolist()
    assert [named[f"c_{ij}"] for ij in ("xx", "xy", "yx", "yy")] == c.ravel().tolist()
    assert [named[f"moment_lin_{ij}"] for ij in ("xx", "xy", "yx", "yy")] == moment_lin.ravel().tolist()
    assert [named["de_x"], named["de_y"]] == (d + e).tolist() and [named["b_x"], named["b_y"]] == b.tolist()
    assert [named["moment_const_x"], named["moment_const_y"], named["second_lin_x"], named["second_lin_y"]] == \
        [*moment_const.tolist(), *second_lin.tolist()]
    assert [named[n] for n in ("f", "damping", "weight", "second_const", "origin_x", "origin_y", "inv_mass",
                               "inv_inertia")] == [0.7, 0.3, 9.0, 0.4, 1.0, 2.0, 0.5, 0.25]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(["coulomb", "viscous", "stick_slip"]))
def test_the_accelerations_of_a_laws_row_are_its_wrench_over_mass_and_inertia(seed, law_name):
    """kernel.accelerations of the row a law makes (constants_and_row) at a random state: the direct per-cell
    wrench (eqs. 22, 24) over the mass and the inertia."""
    rng = np.random.default_rng(seed)
    m = int(rng.integers(3, 12))
    P = rng.uniform(-0.5, 0.5, size=(m, 2)) + rng.uniform(-2, 2, size=2)
    angle = rng.uniform(0, np.pi)
    c, s = np.cos(angle), np.sin(angle)
    U = np.broadcast_to(np.array([[c, s], [-s, c]]), (m, 2, 2))
    V = rng.uniform(-1, 1, size=(m, 2))
    W, mu, mass, inertia = 15.0, 0.4, 2.5, 0.3
    law = laws.LAWS[law_name]  # stick-slip: the sliding regime's, Coulomb's
    com = P.mean(axis=0) + 0.3 * (P[0] - P.mean(axis=0))
    sol = solve_support(P, com, W)
    state = np.array([*com, 0.0, *rng.uniform(-1, 1, size=2), rng.uniform(-3, 3)])
    fx, fy, tau = law.wrench(P, sol.forces(com), V, U, mu, state)
    _, row = law.constants_and_row(sol, V, U, mu, mass, inertia)
    np.testing.assert_allclose(kernel.accelerations(row, *com, *state[3:]), [fx / mass, fy / mass, tau / inertia],
                               atol=1e-10 * W / min(mass, inertia))

# The quiet stepper's compiled step and edge checks (virtual_vehicle.engine.batch): parcels on a 12 x 12 array.
BATCH_CELLS = layout.grid(12, 12, 0.1)
BATCH_SPEC = parcel.rectangle(0.33, 0.24, 1.5, 0.8)
BATCH_PENTAGON = parcel.polygon([[0.0, 0.0], [0.3, 0.0], [0.36, 0.16], [0.15, 0.27], [-0.04, 0.14]], 1.2, 0.7)


def _batch_field(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.3, 0.3, (BATCH_CELLS.n, 2))


def _quiet_pieces(law, seed, n=20):
    """n parcels' states and their pieces under a random field, placed at random inside the array."""
    rng = np.random.default_rng(seed)
    model = ParcelModel(BATCH_CELLS, BATCH_SPEC, _batch_field(seed), law)
    ys, rows = [], []
    for _ in range(n):
        y = np.array([*rng.uniform(0.35, 0.75, 2), rng.uniform(-np.pi, np.pi), *rng.normal(0, 0.1, 2),
                      rng.normal(0, 0.5)])
        piece = model.piece_at(y)
        ys.append(y)
        rows.append(dynamics.constants_row(piece.constants, piece.solution.origin, BATCH_SPEC.mass, BATCH_SPEC.inertia))
    return model, np.array(ys), rows


def _quiet_steps(rows, Y, t, t_bound, taus):
    out = np.full((len(Y), len(taus), 6), np.nan)
    accepted, evals = kernel.quiet_steps(np.array(rows), Y, t, t_bound, 1e-10, 1e-12, np.asarray(taus), out)
    return accepted, out, evals


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_quiet_steps_are_scipys_dop853_step(law):
    """Each parcel's step is the one scipy's DOP853 takes from the same state with the whole window as its first
    step (to rounding: scipy sums stages with BLAS), kept exactly when scipy keeps it, and its dense output is
    scipy's; a refused step writes nothing."""
    model, Y, rows = _quiet_pieces(laws.LAWS[law], 3)
    h = 0.05  # long enough that some steps fail the error test
    taus = np.array([0.0, 0.3 * h, 0.77 * h, h])
    accepted, out, evals = _quiet_steps(rows, Y, 0.0, h, taus)
    assert evals == 16  # the first derivative, 11 stages, the end's, and 3 more for the dense output
    for n, y0 in enumerate(Y):
        solver = DOP853(model.piece_at(y0).rhs, 0.0, y0, h, rtol=1e-10, atol=1e-12, first_step=h)
        solver.step()
        assert accepted[n] == (solver.t == h)  # scipy kept the whole step exactly when its error test passed
        if solver.t == h:
            np.testing.assert_allclose(out[n, -1], solver.y, rtol=1e-13, atol=1e-15)
            np.testing.assert_allclose(out[n], solver.dense_output()(taus).T, rtol=1e-13, atol=1e-15)
            assert out[n, 0].tolist() == y0.tolist()
        else:
            assert np.isnan(out[n]).all()
    assert accepted.any() and not accepted.all()


def test_a_step_too_long_for_the_tolerance_or_short_of_the_end_is_refused():
    _, Y, rows = _quiet_pieces(laws.LAWS["viscous"], 4)
    assert not _quiet_steps(rows, Y, 0.0, 2.0, [0.0, 2.0])[0].any()
    t, t_bound = -0.0019132392605720027, 0.0008155261736351271  # t + (t_bound - t) falls short of t_bound by
    assert t + (t_bound - t) < t_bound  # rounding: the engine would take a second, tiny step
    assert not _quiet_steps(rows, Y, t, t_bound, [t, t_bound])[0].any()
    assert _quiet_steps(rows, Y, 0.0, t_bound - t, [0.0, t_bound - t])[0].all()  # the same window from 0


def test_the_edges_of_many_parcels_in_one_call_are_each_parcels_own():
    """edges_clear_many against edges_clear parcel by parcel, with few cells a parcel (padded rows) and two outlines
    (four and five edges, padded)."""
    rng = np.random.default_rng(3)
    # few cells a parcel, over a window of 0.1 s that leaves ~40 % undecided: a cell or an edge dropped or
    # borrowed from a neighbour changes decisions
    points = rng.uniform(-0.2, 0.2, (40, 2))
    outlines = [BATCH_SPEC.halfplanes, BATCH_PENTAGON.halfplanes]
    near = [rng.choice(len(points), rng.integers(1, 4), replace=False) for _ in range(200)]
    shape = rng.integers(0, 2, len(near))
    padded = np.full((len(near), 3), len(points))
    for k, n in enumerate(near):
        padded[k, :len(n)] = n
    normals, offsets = np.zeros((len(near), 5, 2)), np.zeros((len(near), 5))
    for k, o in enumerate(shape):
        normals[k, :len(outlines[o][1])], offsets[k, :len(outlines[o][1])] = outlines[o]
    counts = np.array([len(outlines[o][1]) for o in shape])
    Y = np.column_stack([rng.normal(0, 0.02, (len(near), 2)), rng.uniform(-np.pi, np.pi, len(near)),
                         rng.normal(0, 0.3, (len(near), 2)), rng.normal(0, 0.5, len(near))])
    r, accel = rng.uniform(0, 0.02, len(near)), rng.uniform(0, 0.002, len(near))
    R, lever, noise = np.full(len(near), 0.2), np.full(len(near), 3.0), np.full(len(near), 1e-11)
    together = kernel.edges_clear_many(points, padded, np.array([len(n) for n in near]), normals, offsets, counts,
                                        Y, 0.1, r, accel, R, lever, noise)
    alone = [kernel.edges_clear(points, near[k], *outlines[shape[k]], Y[k], 0.1, r[k], accel[k], R[k], lever[k],
                                 noise[k]) for k in range(len(near))]
    assert together.tolist() == alone and 0.2 < np.mean(alone) < 0.8


def _coulomb_run(model, seconds=1.5):
    y0 = np.array([1.12, 1.47, 0.3, 0.0, 0.0, 0.0])
    return integrate(model, y0, 0.0, seconds, sample_dt=0.05)


def _same_run(a, b):
    assert np.array_equal(a.times, b.times) and np.array_equal(a.states, b.states)
    assert a.events == b.events and a.segments == b.segments and a.status == b.status


def _inward_model(law="coulomb", speed=3.0):
    spec = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    return ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), speed).velocities(CELLS), laws.LAWS[law])


@pytest.mark.parametrize("law, speed", [("coulomb", 3.0), ("viscous", 0.2)])
def test_the_event_loop_makes_pieces_from_patterns_as_the_model_would(law, speed):
    """The compiled event loop makes the pieces of support sets it has never met from solved patterns (the law's
    compiled drive): the same run as one whose loop may not (every new support set found by the model in Python),
    bit for bit, events and all, and the model's cache ends the same."""
    made, found = _inward_model(law, speed), _inward_model(law, speed)
    asked = []  # the support sets the model solved or looked up in Python: the loop solves the rest itself
    made.solution_and_first = lambda support, com: asked.append(1) or ParcelModel.solution_and_first(made, support, com)
    a = _coulomb_run(made)
    found._table = dynamics._PieceTable(found, len(affine.ROW_FIELDS))
    found._table.law_args = (0, *found._table.law_args[1:])  # drive code 0: no pieces made in the loop
    b = _coulomb_run(found)
    _same_run(a, b)
    assert len(a.events) > 10
    # the pieces it made stay table entries until asked for (none was, here), then are the pieces Python made
    unmade = len(made._unmade)
    assert unmade > 10 and made.pieces_cached == found.pieces_cached == made._table.used[kernel.U_PIECES]
    for skey in list(made._unmade):
        made._table.make(made, skey)
    assert not made._unmade and len(made._pieces) == made.pieces_cached
    assert ({k: (p.row, p.constants.terms.tolist()) for k, p in made._pieces.items()}
            == {k: (p.row, p.constants.terms.tolist()) for k, p in found._pieces.items()})
    for k, p in made._pieces.items():
        q = found._pieces[k]
        assert np.array_equal(p.support, q.support) and np.array_equal(p.solution.origin, q.solution.origin)
    # the patterns solved in the loop are in the model's store as Python would have put them: same order, same floats
    assert made.solves == found.solves and len(asked) < made.solves // 2
    mine, python = made.shared_solutions, found.shared_solutions
    assert list(mine) == list(python)
    for key in python:
        assert len(mine[key]) == len(python[key])
        for s, t in zip(mine[key], python[key]):
            for name in ("origin", "points", "in_contact", "basis", "plane_lin", "plane_const", "force_lin",
                         "force_const", "hull_normals", "hull_offsets", "spring_lin", "spring_gradient"):
                assert np.array_equal(getattr(s, name), getattr(t, name)), name
                assert name == "origin" or not getattr(s, name).flags.writeable, name  # (unpacked when read)
            assert s.weight == t.weight and s.one_d == t.one_d and s.contact_collinear == t.contact_collinear


def test_the_event_loop_runs_the_same_from_its_table_and_after_emptying_it(monkeypatch):
    """A second run on the same model (every support set found in the loop's table) and runs whose table is
    emptied every few pieces (bounded memory: the model's piece cache emptied with it) are the first run, bit for
    bit."""
    model = _inward_model()
    first = _coulomb_run(model)
    _same_run(first, _coulomb_run(model))
    monkeypatch.setattr(dynamics._PieceTable, "max_pieces", 7)
    small = _inward_model()
    _same_run(first, _coulomb_run(small))
    assert len(small._table.pieces) <= 7 + small._table.spare and len(small._pieces) < len(model._pieces)


@pytest.mark.parametrize("pause", [4, 64])
def test_the_event_loop_hands_back_for_progress_and_runs_the_same(monkeypatch, pause):
    """With a progress callback the loop hands back every few steps within a piece and every few pieces it begins
    (``_PAUSE_STEPS``; a piece is often one step, and the loop needs Python for little else), so progress is heard
    of at least that often; the run is the same."""
    monkeypatch.setattr(dynamics, "_PAUSE_STEPS", pause)
    times = []
    paused = integrate(_inward_model(), np.array([1.12, 1.47, 0.3, 0.0, 0.0, 0.0]), 0.0, 1.5, sample_dt=0.05,
                       progress=times.append)
    _same_run(_coulomb_run(_inward_model()), paused)
    # each call begins at most `pause` pieces, and Python at most one before it
    assert len(times) >= (paused.segments - 1) / (pause + 1) and times == sorted(times) and times[-1] == 1.5
    assert paused.segments > 100 and len(times) > (10 if pause == 4 else 1)


def test_the_event_loop_hands_back_only_when_its_table_is_full(monkeypatch):
    """The oscillating Coulomb parcel (5 s, ~500 support events, ~370 pieces, ~170 patterns solved) needs Python
    only where the compiled loop has no room for another piece (``_PieceTable.spare`` a call, doubled after a call
    that fills it, so a logarithmic number of times): not for the cells
    under the parcel where the probe's values cannot tell them (it finds them as ``support_at`` does), not for a
    support set met before on other contact sets, not for a solve. Every hand-back is counted (each call's
    outcome), and the run is the one a run whose loop hands back at every piece makes."""
    calls = []
    original = kernel.run_events

    def counted(*args):
        room = args[-2][9].shape[0]  # the pieces this call may make (the law's arguments' born terms)
        out = original(*args)
        calls.append((out[0], out[10], out[11].copy(), out[12].copy(), out[13], room))
        return out

    model = _inward_model()
    monkeypatch.setattr(kernel, "run_events", counted)
    tr = _coulomb_run(model, 5.0)
    misses = [c for c in calls if c[0] == kernel.LOOP_MISS]
    assert len(tr.events) > 400 and model.pieces_cached > 300 and [c[0] for c in calls[-1:]] == [kernel.REACHED]
    assert {c[0] for c in calls} == {kernel.LOOP_MISS, kernel.REACHED}
    for _, born, probe, under, told, room in misses:  # full, with the cells under the probe told as the model finds
        assert born == room and told and under.tolist() == model.support_at(probe).tolist()
    assert [c[5] for c in calls] == sorted(c[5] for c in calls) and calls[-1][5] > calls[0][5]  # it grew
    spare = dynamics._PieceTable.spare  # calls that fill 64, 128, 256, ... pieces: k of them made 64 (2^k - 1)
    assert 1 <= len(misses) <= math.log2(model.pieces_cached / spare + 1)
    monkeypatch.setattr(dynamics, "_PAUSE_STEPS", 1)  # a hand-back at every piece the loop would begin
    _same_run(tr, integrate(_inward_model(), np.array([1.12, 1.47, 0.3, 0.0, 0.0, 0.0]), 0.0, 5.0, sample_dt=0.05,
                            progress=lambda t: None))
    assert len(calls) > tr.segments // 2


_HOLES = np.random.default_rng(3).random(CELLS.n) > 0.2


@pytest.mark.parametrize("name", SHAPES)
@settings(max_examples=40, deadline=None)
@given(st.floats(-0.3, 3.3), st.floats(-0.3, 3.3), st.floats(-3.2, 3.2), st.booleans())
@example(x=1.0, y=1.05, th=0.0, holes=False)  # (the rectangle's edges on rows of cell centres: margins zero)
def test_the_event_loop_finds_the_cells_under_the_parcel_as_the_model_does(name, x, y, th, holes):
    """Where the probe's event values cannot tell the cells under the parcel (a value within rounding noise of zero,
    or the parcel beyond its candidates' reach), the compiled loop finds them itself (``kernel.cells_under``): the
    very cells ``ParcelModel.support_at`` finds, present ones only, off the array's edge too."""
    model = ParcelModel(CELLS, SHAPES[name], np.zeros((CELLS.n, 2)), laws.CoulombLaw())
    if holes:
        model.present = _HOLES
    state = np.array([x, y, th, 0.0, 0.0, 0.0])
    kind, _, half, normals, offsets, vertices = model.outline
    found = kernel.cells_under(dynamics._grid_args(model), model.cells.positions, kind, half, normals, offsets,
                               vertices, state)
    assert found.dtype == np.int64 and found.tolist() == model.support_at(state).tolist()


LEAVES = ("values", "value", "may_hide", "_edge_and_rate", "_changed", "_unchanged", "dense_at", "_phi", "_brent",
          "_rhs", "_stage", "_trial", "_dop853_step", "_dense", "_sign", "accelerations_compiled", "_search",
          "_first_change", "_locate", "_event_in_step", "_linspace", "_copy", "_ids_hash", "table_find", "_free_slot",
          "table_rehash", "table_add_key", "_put_flat", "_put_rows", "record_floats", "table_add_record",
          "table_chain_record", "table_add_piece", "table_add_piece_of", "table_lookup", "_record_holds", "_piece",
          "n_values", "_positive_into", "_holding_at")


def test_the_event_loops_leaves_are_compiled_without_the_runtime_and_it_refuses_a_leaf_that_allocates():
    """The event loop's hot leaves count no references (numba's runtime off: ``kernel.leaf``), the loops that call
    them keep it; and the compiler refuses a leaf that makes an array, so the rule the decorator states is checked,
    not trusted."""
    for name in LEAVES:
        assert getattr(kernel, name).targetoptions.get("_nrt") is False, name
    assert kernel._holds_packed.targetoptions.get("_nrt") is False  # (physics.contact's, asked at every event)
    assert kernel.run_piece.targetoptions.get("_nrt", True) is not False

    def makes_an_array(n):
        return np.zeros(n).sum()

    def copies_a_row_whole(K, f):  # may copy through a temporary: the runtime's
        K[0] = f

    with pytest.raises(Exception, match="Only accept returning of array passed into the function"):
        kernel.leaf(makes_an_array)(3)
    with pytest.raises(Exception, match="NRT required but not enabled"):
        kernel.leaf(copies_a_row_whole)(np.zeros((2, 3)), np.ones(3))


def test_a_leaf_called_from_python_gives_what_the_loops_give():
    """A leaf is also called from Python (the segment's values at a state): the same numbers as its Python source."""
    model = ParcelModel(layout.grid(8, 8, 0.1), parcel.rectangle(0.3, 0.2, 1.0, 1.0),
                        fields.Uniform((0.2, 0.0)).velocities(layout.grid(8, 8, 0.1)), laws.CoulombLaw())
    y = np.array([0.41, 0.37, 0.2, 0.1, 0.0, 0.3])
    piece = model.piece_at(y)
    seg = dynamics._Segment(model, piece, y, None)
    arrays = kernel.Segment(*seg.fields)
    n = arrays.candidates.shape[0] + arrays.basis.shape[0] + arrays.hull_offsets.shape[0] + 1
    compiled, python = np.empty(n), np.empty(n)
    kernel.values(arrays, y, compiled)
    for i in range(n):
        python[i] = kernel.value(arrays, y, i)
    np.testing.assert_allclose(compiled, python, rtol=0, atol=1e-12)
    assert np.array_equal(compiled > 0, python > 0)


def test_a_search_out_of_room_searches_again_and_finds_the_same_bracket():
    """The search for a step's first event works in a scratch made once a loop; a bisection that outgrows its stores
    says so (``SEARCH_FULL``) rather than allocate (it is a leaf), and searched again with grown stores it finds the
    bracket a roomy scratch finds, to the bit. Steps of an oscillating Coulomb parcel from seeded states; a scratch
    with room for two intervals runs out in many of them (checked: else the growth would go untested)."""
    cells = layout.grid(12, 12, 0.1)
    model = ParcelModel(cells, parcel.rectangle(0.3, 0.2, 1.0, 1.0),
                        fields.Inward((0.6, 0.6), 0.2).velocities(cells), laws.CoulombLaw())
    rng = np.random.default_rng(0)
    grown = found = 0
    for _ in range(40):
        y = np.array([*rng.uniform(0.4, 0.8, 2), rng.uniform(-3, 3), *rng.uniform(-0.3, 0.3, 2), rng.uniform(-2, 2)])
        piece = model.piece_at(y)
        seg = kernel.Segment(*dynamics._Segment(model, piece, y, None).fields)
        n = kernel.n_values(seg)
        g0 = np.empty(n)
        kernel.values(seg, y, g0)
        K, F, f, y_new, f_new, work = kernel._workspace()
        row = np.array(piece.row)
        kernel._rhs(row, y, f)
        ok, h, _, _ = kernel._dop853_step(row, 0.0, y, f, 1.0, 0.2, 1e-9, 1e-12, np.inf, K, y_new, f_new, work)
        assert ok
        kernel._dense(row, 0.0, y, f, y_new, f_new, h, K, F, work)
        roomy, tight = kernel.search_scratch(n), kernel._scratch(n, 2)
        args = (seg, F, y, 0.0, h, g0 > 0, 0.0, h, f, f_new)
        want = kernel._first_change(*args, roomy)
        got = kernel._first_change(*args, tight)
        while got[0] == kernel.SEARCH_FULL:
            grown += 1
            tight = kernel._grown_search(tight)
            got = kernel._first_change(*args, tight)
        assert got == want
        if want[0] == kernel.FOUND:
            found += 1
            for name in ("out_changed", "g_a", "g_b"):
                assert np.array_equal(getattr(tight, name)[:n], getattr(roomy, name)[:n]), name
    assert grown >= 10 and found >= 10


def test_a_piece_whose_search_outgrows_the_scratch_is_resumed_and_ends_as_with_room():
    """A piece run in the leaf (``_piece``) hands back when a step's search outgrows the scratch (``SEARCH_OUT``);
    run_piece grows it and resumes from the state it stopped in, taking the same step again: the same event, restart,
    probe and cells under the footprint, to the bit, as with room from the start; the step taken again shows only as
    more evaluations (checked: else the resumption would go untested)."""
    cells = layout.grid(12, 12, 0.1)
    model = ParcelModel(cells, parcel.rectangle(0.3, 0.2, 1.0, 1.0),
                        fields.Inward((0.6, 0.6), 0.2).velocities(cells), laws.CoulombLaw())
    rng = np.random.default_rng(1)
    resumed = 0
    for _ in range(20):
        y = np.array([*rng.uniform(0.4, 0.8, 2), rng.uniform(-3, 3), *rng.uniform(-0.3, 0.3, 2), rng.uniform(-2, 2)])
        piece = model.piece_at(y)
        fields_ = dynamics._Segment(model, piece, y, None).fields
        n = len(fields_[6]) + fields_[8].shape[0] + fields_[12].shape[0] + 1
        runs = []
        for sc in (kernel.search_scratch(n), kernel._scratch(n, 2)):
            samples = np.empty((3, 6))
            runs.append(kernel.run_piece(np.array(piece.row), fields_, y, 0.0, y, 1.0, 0.0, 0.2, 1e-9, 1e-12, np.inf,
                                         10 ** 6, np.array([0.1, 0.5, 1.0]), 0, samples, sc) + (samples,))
        roomy, tight = runs
        assert roomy[0] == kernel.EVENT
        for i in (0, 1, 2, 6, 7, 8, 9, 10):  # outcome, t, state, next sample, probe time and state, cells, told
            assert np.array_equal(roomy[i], tight[i]), i
        np.testing.assert_array_equal(roomy[11][:roomy[6]], tight[11][:tight[6]])  # the samples written
        resumed += tight[5] > roomy[5]
    assert resumed >= 3


def test_the_compiled_linspace_is_numbas():
    """The search's sample times, written into its scratch, are np.linspace's as compiled code computes it."""
    out = np.empty(kernel.SUBSAMPLES + 1)
    for lo, hi in ((0.0, 1.0), (0.123456789, 0.123456789 + 3.7e-3), (5.0, 5.0 + 1e-9)):
        kernel._linspace(lo, hi, out)
        assert np.array_equal(out, np.linspace(lo, hi, kernel.SUBSAMPLES + 1))
