"""A second reading of the compiled per-parcel event loop (issue 32): the cases where it hands back to Python or
meets the array's end. Being the loop's own unit tests (as tests/test_kernel.py), these may name private parts: the
table's drive code (0: the loop makes no pieces itself) and its size bound."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.engine import dynamics
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.physics.laws import affine

SHAPES = {"rectangle": parcel.rectangle(0.4, 0.3, 2.0, 1.0),
          "L": parcel.polygon([[0, 0], [0.4, 0], [0.4, 0.12], [0.12, 0.12], [0.12, 0.4], [0, 0.4]], 2.0, 1.0,
                              com=(0.1, 0.1)),
          "thin": parcel.rectangle(0.6, 0.08, 1.0, 0.7)}
LAYOUTS = {"small": layout.grid(8, 6, 0.1), "row": layout.grid(20, 1, 0.1), "sparse": layout.grid(6, 6, 0.15)}


def _same_run(a, b):
    assert np.array_equal(a.times, b.times) and np.array_equal(a.states, b.states)
    assert a.events == b.events and a.segments == b.segments and a.status == b.status


@settings(max_examples=25, deadline=None)
@given(where=st.sampled_from(sorted(LAYOUTS)), shape=st.sampled_from(sorted(SHAPES)),
       law=st.sampled_from(["coulomb", "viscous"]), seed=st.integers(0, 2 ** 16))
def test_the_loop_at_the_arrays_end_is_the_python_made_run(where, shape, law, seed):
    """Random fields on small arrays, a single row (every support set on one line: the 1-D solve, in Python) and a
    sparse grid: parcels lift cells off, touch down, leave the array and tip. The loop that makes pieces itself,
    the loop that may not (every new support set found in Python) and a loop whose table is emptied every few
    pieces run the same, bit for bit."""
    cells, spec = LAYOUTS[where], SHAPES[shape]
    rng = np.random.default_rng(seed)
    V = rng.uniform(-0.4, 0.4, (cells.n, 2)) + rng.uniform(-0.5, 0.5, 2)
    lo, hi = cells.positions.min(axis=0), cells.positions.max(axis=0)
    y0 = np.array([*rng.uniform(lo, hi), rng.uniform(-3.0, 3.0), 0.0, 0.0, 0.0])

    def ran(drive: bool):
        m = ParcelModel(cells, spec, V, laws.LAWS[law])
        if not drive:
            m._table = dynamics._PieceTable(m, len(affine.ROW_FIELDS))
            m._table.law_args = (0, *m._table.law_args[1:])
        return integrate(m, y0, 0.0, 1.0, sample_dt=0.05)

    made = ran(True)
    _same_run(made, ran(False))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(dynamics._PieceTable, "max_pieces", 3)
        _same_run(made, ran(True))


@given(law=st.sampled_from(["coulomb", "viscous", "stick_slip"]))
@settings(max_examples=3, deadline=None)
def test_a_model_copied_mid_run_goes_on_as_the_original(law):
    """A model copied (deep or shallow) after the loop filled its table, its solutions unpacked only in part, runs on
    as the original does; and the pieces it holds after the run (the loop's, read late) are a fresh model's."""
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    V = fields.Inward((1.5, 1.5), 3.0).velocities(cells)
    m = ParcelModel(cells, spec, V, laws.LAWS[law])
    first = integrate(m, np.array([1.12, 1.47, 0.3, 0.0, 0.0, 0.0]), 0.0, 0.7, sample_dt=0.05)
    assert len(first.events) > 5
    y = first.states[-1]
    deep, shallow = copy.deepcopy(m), copy.copy(m)
    on = integrate(m, y, 0.7, 1.5, sample_dt=0.05)
    _same_run(on, integrate(deep, y, 0.7, 1.5, sample_dt=0.05))
    _same_run(on, integrate(shallow, y, 0.7, 1.5, sample_dt=0.05))
    fresh = ParcelModel(cells, spec, V, laws.LAWS[law])
    for state in np.concatenate([first.states, on.states])[::4]:
        try:
            mine = m.piece_at(state)
        except Exception:  # (tipped)
            continue
        theirs = fresh.piece_at(state)
        assert mine.key == theirs.key and mine.row == theirs.row
        for name in ("points", "in_contact", "basis", "plane_lin", "plane_const", "force_lin", "force_const",
                     "hull_normals", "hull_offsets", "spring_lin"):
            assert np.array_equal(getattr(mine.solution, name), getattr(theirs.solution, name)), name
        assert np.array_equal(mine.normal_forces(state), theirs.normal_forces(state))


def _same_mode_run(a, b):
    """Two stick-slip runs the same bit for bit: samples, events, pieces, and every stat (energy account, the mode
    record with each mode before and after, pieces cached, solves)."""
    _same_run(a, b)
    assert a.t_end == b.t_end and a.rhs_evals == b.rhs_evals
    assert a.stats.keys() == b.stats.keys()
    for key, value in a.stats.items():
        assert value == b.stats[key], key


def _loop_and_python(cells, spec, V, y0, t1, sample_dt=0.05, progress=None):
    """The run of a fresh model with the compiled stick-slip loop (and the log entries it wrote) and with every event
    in Python (``dynamics._MODE_LOOP`` off)."""
    from virtual_vehicle.engine import _modeloop

    logged = []
    run_modes = _modeloop.run_modes

    def counted(*args):
        out = run_modes(*args)
        logged.append(out[9])
        return out

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(_modeloop, "run_modes", counted)
        loop = integrate(ParcelModel(cells, spec, V, laws.LAWS["stick_slip"]), y0, 0.0, t1, sample_dt=sample_dt,
                         progress=progress)
        patch.setattr(dynamics, "_MODE_LOOP", False)
        python = integrate(ParcelModel(cells, spec, V, laws.LAWS["stick_slip"]), y0, 0.0, t1, sample_dt=sample_dt,
                           progress=progress)
    return loop, python, sum(logged)


@pytest.mark.parametrize("theta", [0.0, 0.3])
def test_the_compiled_stick_slip_loop_is_the_python_loop_across_support_and_mode_events(theta):
    """A parcel set down at rest on a uniform field catches up with its wheels (mode events), then crosses support
    sets (new ones, made from solved patterns, and ones met before on other contact sets): the compiled loop takes
    those events itself (it logs them) and the run is the one of the Python loop, bit for bit; also when it hands
    back every few steps for progress."""
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 0.5, mu_static=0.6)
    V = fields.Uniform((0.2, 0.0)).velocities(cells)
    y0 = np.array([0.52, 1.47, theta, 0.0, 0.0, 0.0])
    loop, python, logged = _loop_and_python(cells, spec, V, y0, 2.0)
    _same_mode_run(loop, python)
    assert loop.stats["mode_changes"] >= 1 and sum(e.kind == "support" for e in loop.events) >= 10
    assert logged >= 10  # the compiled loop took events itself
    seen = []
    loop, python, _ = _loop_and_python(cells, spec, V, y0, 2.0, progress=seen.append)
    _same_mode_run(loop, python)
    assert len(seen) > 10


@settings(max_examples=20, deadline=None)
@given(where=st.sampled_from(sorted(LAYOUTS)), shape=st.sampled_from(sorted(SHAPES)), seed=st.integers(0, 2 ** 16))
def test_the_compiled_stick_slip_loop_is_the_python_loop_under_random_fields(where, shape, seed):
    """Random fields on small arrays, a single row and a sparse grid, a static coefficient above the kinetic one:
    wheels grip and break away, cells lift off and touch down, parcels leave the array and tip; the compiled loop
    and the Python loop run the same, bit for bit."""
    cells, spec = LAYOUTS[where], SHAPES[shape]
    spec = dataclasses.replace(spec, mu_static=1.5 * spec.mu)
    rng = np.random.default_rng(seed)
    V = rng.uniform(-0.4, 0.4, (cells.n, 2)) + rng.uniform(-0.5, 0.5, 2)
    lo, hi = cells.positions.min(axis=0), cells.positions.max(axis=0)
    y0 = np.array([*rng.uniform(lo, hi), rng.uniform(-3.0, 3.0), 0.0, 0.0, 0.0])
    loop, python, _ = _loop_and_python(cells, spec, V, y0, 1.0)
    _same_mode_run(loop, python)


def test_copies_started_from_the_cells_told_or_found_run_as_the_python_loop():
    """The plant makes a parcel's model again every tick (other wheels) and may tell the cells under it: such a
    copy's compiled loop finds its first piece itself (from the cells told or those under the footprint), or hands
    the start back where its table cannot give it (a pattern it never met, a parcel off the array). Tick by tick,
    with the parcel going on, set down elsewhere, or off the array, the copies' runs are the Python loop's bit for
    bit, and both ways of starting were taken."""
    from virtual_vehicle.engine import _modeloop

    cells = layout.grid(12, 10, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.3, 0.3, mu_static=0.6)
    field = fields.Inward((0.6, 0.5), 0.2).velocities(cells)
    rng = np.random.default_rng(5)
    starts = []
    run_modes = _modeloop.run_modes

    def counted(*args):
        out = run_modes(*args)
        if args[6] < 0:
            starts.append(out[0] == _modeloop.LOOP_START)
        return out

    bases = [ParcelModel(cells, spec, field, laws.LAWS["stick_slip"]) for _ in range(2)]
    poses = np.column_stack([rng.uniform(0.3, 0.9, (60, 2)), rng.uniform(-3, 3, 60)])
    for base in bases:  # a store of more patterns than a table mirrors: a table meets patterns it cannot solve
        for pose in poses:
            base.piece_at(pose)
    y = np.array([0.42, 0.33, 0.2, 0.0, 0.0, 0.0])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(_modeloop, "run_modes", counted)
        for k in range(80):
            V = field * (1.0 + 0.5 * np.sin(0.7 * k))  # the wheels change every tick
            t0, t1 = k * 0.01, (k + 1) * 0.01
            if k % 10 == 9:  # off the array: it tips at once
                y = np.array([3.0, 3.0, 0.0, 0.0, 0.0, 0.0])
            elif rng.random() < 0.6:  # set down elsewhere, possibly on a pattern the table never met
                y = np.array([*rng.uniform(0.2, 1.0, 2), rng.uniform(-3, 3), *rng.normal(0, 0.1, 3)])
            told = rng.random() < 0.5
            runs = []
            for base, compiled in zip(bases, (True, False)):
                patch.setattr(dynamics, "_MODE_LOOP", compiled)
                model = base.with_velocities(V)
                support = model.support_at(y) if told else None
                runs.append(dynamics.integrate_prechecked(model, y, t0, t1, np.array([t0, t1]), mode="event",
                                                          rtol=1e-10, atol=1e-12, max_step=np.inf, dt=1e-3,
                                                          support=support))
            _same_mode_run(*runs)
            if k % 10 == 9:
                assert runs[0].status == "tipped"
            y = runs[0].states[-1] if runs[0].status == "completed" else np.array([0.5, 0.5, 0.0, 0.0, 0.0, 0.0])
    assert starts.count(False) >= 10 and starts.count(True) >= 1  # found by the loop, and handed back
