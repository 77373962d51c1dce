"""The compiled event engine (virtual_vehicle.engine._kernel) against what it replaces and what it must agree with: the
footprint margins of parcel.py (shapely for non-convex outlines), scipy's DOP853 step by step, and itself when a
run is handed back to Python and resumed."""

import json

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.integrate import DOP853

from virtual_vehicle.engine import _kernel as kernel
from virtual_vehicle.engine import dynamics
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import friction
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


def test_compiled_dop853_takes_scipys_steps():
    """From the same state and trial step, the compiled DOP853 lands where scipy's DOP853 lands (the same tableau,
    to rounding: scipy sums stages with BLAS, the kernel in plain loops), accepts or rejects the same trial steps,
    proposes the same next step (to the error estimate's own sensitivity to rounding: it is a small difference of
    large stages) and has the same dense output; here on a viscous piece in steps that grow from 1 ms, up to the
    bound."""
    spec = SHAPES["rectangle"]
    m = ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), 0.2).velocities(CELLS), friction.ViscousLaw())
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
    m = ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), 0.2).velocities(CELLS), friction.ViscousLaw())
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
    assert kernel.run_piece.signatures and kernel.pattern.signatures and kernel.cell_margins.signatures


def test_warming_up_compiles_what_networked_runs_call():
    """In a fresh process, warm_up() leaves the engine's compiled entry points, the quiet step's checks and step and
    the cell query among them, with the very signatures a networked run (25 parcels on 30 x 30, batched quiet
    ticks) then calls them with, so a user's first networked run does not stop to compile: each is called, and none
    gains a signature."""
    import subprocess
    import sys
    from pathlib import Path

    code = """
import collections, json, sys
sys.path.insert(0, %r)
import bench_scale
from virtual_vehicle.engine import _kernel
from virtual_vehicle.physics import friction
from virtual_vehicle.model import parcel
from virtual_vehicle.cells.sorting import policy
from virtual_vehicle.cells.network import delivery
from virtual_vehicle.run.warm import warm_up
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run_network
warm_up()
home = {n: _kernel for n in ("run_piece", "pattern", "cell_margins", "support_slack", "edges_clear_many",
                                      "quiet_steps")}
home["_within"] = home["_covered"] = parcel
home["_terms_and_row"] = friction  # the bench_scale hall is viscous
home["step_cells"] = policy
home["_carry"] = delivery
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
run_network(parse_scenario(bench_scale.scenario(30, 25, 0.5)).build())
print(json.dumps([before, {n: len(kernels[n].signatures) for n in names}, calls]))
""" % str(Path(__file__).resolve().parents[1] / "benchmarks")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, after, calls = json.loads(out.stdout.strip().splitlines()[-1])
    assert before == after and min(before.values()) > 0, (before, after)
    assert set(calls) == set(before) and min(calls.values()) > 0, calls


def test_max_step_bounds_every_compiled_step():
    """``max_step`` caps the compiled integrator's steps (scipy's rule): a viscous piece that one long step would
    cross takes at least one step per ``max_step``, and ends where the uncapped run ends (to the tolerance)."""
    spec = SHAPES["rectangle"]
    m = ParcelModel(CELLS, spec, fields.Inward((1.5, 1.5), 0.2).velocities(CELLS), friction.ViscousLaw())
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
