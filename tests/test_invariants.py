"""Invariants of the whole simulator: rigid motions of the scene move the result with it, cell numbering does not
matter, runs are bit-reproducible, interrupted writes leave no complete-looking file."""

import json
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle import fields, friction, io, layout, parcel
from virtual_vehicle.dynamics import ParcelModel, integrate
from virtual_vehicle.scenario import bundled_scenarios, load_scenario
from virtual_vehicle.sim import run

LAWS = {"coulomb": friction.CoulombLaw(), "viscous": friction.ViscousLaw(), "stick_slip": friction.StickSlipLaw()}


def rot(a):
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def simulate(cells, spec, velocities, law, y0, T=0.6):
    m = ParcelModel(cells, spec, velocities, law)
    return integrate(m, y0, 0.0, T, dt=1e-3, sample_dt=0.05)


@settings(max_examples=12, deadline=None)
@given(st.sampled_from(sorted(LAWS)), st.floats(-np.pi, np.pi), st.floats(-3, 3), st.floats(-3, 3),
       st.integers(0, 1000))
def test_a_rigidly_moved_scene_gives_the_moved_result(law_name, angle, tx, ty, seed):
    """Rotate and translate the cells (and their wheel directions), the wheel field and the parcel's start by one
    rigid motion: the trajectory is the same rigid motion of the original one (heading shifted by the angle)."""
    rng = np.random.default_rng(seed)
    cells = layout.grid(9, 7, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.2, 0.6 if law_name != "viscous" else 1.0, mu_static=None)
    V = rng.uniform(-0.4, 0.4, size=(cells.n, 2))
    y0 = np.array([0.42, 0.31, rng.uniform(-0.5, 0.5), rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.3])
    law = LAWS[law_name]
    a = simulate(cells, spec, V, law, y0)
    R = rot(angle)
    t = np.array([tx, ty])
    moved_cells = layout.CellArray(cells.positions @ R.T + t, cells.drive_directions @ R.T, cells.pitch)
    z0 = np.r_[R @ y0[:2] + t, y0[2] + angle, R @ y0[3:5], y0[5]]
    b = simulate(moved_cells, spec, V @ R.T, law, z0)
    assert a.status == b.status and len(a.events) == len(b.events)
    np.testing.assert_allclose(b.states[:, :2], a.states[:, :2] @ R.T + t, atol=1e-7)
    np.testing.assert_allclose(b.states[:, 2], a.states[:, 2] + angle, atol=1e-7)
    np.testing.assert_allclose(b.states[:, 3:5], a.states[:, 3:5] @ R.T, atol=1e-7)
    np.testing.assert_allclose(b.states[:, 5], a.states[:, 5], atol=1e-7)


def test_cell_numbering_does_not_matter():
    cells = layout.grid(9, 7, 0.1)
    rng = np.random.default_rng(4)
    V = rng.uniform(-0.4, 0.4, size=(cells.n, 2))
    perm = rng.permutation(cells.n)
    shuffled = layout.CellArray(cells.positions[perm], cells.drive_directions[perm], cells.pitch)
    spec = parcel.rectangle(0.33, 0.27, 1.2, 1.0)
    y0 = [0.42, 0.31, 0.2, 0.05, 0.0, 0.3]
    a = simulate(cells, spec, V, friction.ViscousLaw(), y0)
    b = simulate(shuffled, spec, V[perm], friction.ViscousLaw(), y0)
    np.testing.assert_allclose(a.states, b.states, atol=1e-9)
    # shuffled cell k is original cell perm[k]
    assert [tuple(sorted(perm[list(e.entered)].tolist())) for e in b.events] == [e.entered for e in a.events]


@pytest.mark.parametrize("name", sorted(bundled_scenarios()))
def test_bundled_scenarios_are_bit_reproducible(name):
    sc, _ = load_scenario(name)
    a, b = run(sc.build()), run(sc.build())
    for pa, pb in zip(a.parcels, b.parcels):
        assert np.array_equal(pa.trajectory.states, pb.trajectory.states)
        assert pa.trajectory.events == pb.trajectory.events


def test_an_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    target = tmp_path / "summary.json"
    real_fsync = os.fsync

    def dying_fsync(fd):
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(os, "fsync", dying_fsync)
    with pytest.raises(KeyboardInterrupt):
        io.write_atomic(target, json.dumps({"complete": True}))
    assert not target.exists() and list(tmp_path.iterdir()) == []
    monkeypatch.setattr(os, "fsync", real_fsync)
    target.write_text("old")
    monkeypatch.setattr(os, "fsync", dying_fsync)
    with pytest.raises(KeyboardInterrupt):
        io.write_atomic(target, "new")
    assert target.read_text() == "old"  # the previous complete file survives
