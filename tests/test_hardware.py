"""Presence sensors: placement, coverage against shapely, noise rates, stuck faults, recording in runs."""

import csv
import dataclasses

import numpy as np
import pytest
import shapely

from virtual_vehicle import layout, parcel
from virtual_vehicle.control import Shuttle
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.hardware import Sensors, default_offsets
from virtual_vehicle.io import write_results
from virtual_vehicle.scenario import load_scenario, parse_scenario
from virtual_vehicle.sim import run


def test_default_sensors_sit_at_centre_and_edge_midpoints_in_the_cell_frame():
    cells = layout.grid(2, 1, 0.1, drive_angle=np.pi / 2)  # wheel 0 drives along +y
    s = Sensors(cells, default_offsets(0.1))
    np.testing.assert_allclose(s.points[0], [[0, 0], [0, 0.05], [-0.05, 0], [0, -0.05], [0.05, 0]], atol=1e-15)
    assert s.count == 5


def test_coverage_matches_shapely():
    cells = layout.grid(12, 10, 0.1)
    s = Sensors(cells, default_offsets(0.1))
    specs = [parcel.rectangle(0.35, 0.22, 1.0, 0.5), parcel.rectangle(0.2, 0.2, 1.0, 0.5)]
    rng = np.random.default_rng(2)
    for _ in range(20):
        states = [np.r_[rng.uniform(0.2, 0.9, 2), rng.uniform(-3, 3), 0, 0, 0] for _ in specs]
        got = s.covered(specs, states).ravel()
        pts = s.points.reshape(-1, 2)
        want = np.zeros(len(pts), bool)
        for spec, y in zip(specs, states):
            want |= shapely.contains_xy(spec.world_polygon(y), pts[:, 0], pts[:, 1])
        np.testing.assert_array_equal(got, want)


def test_noise_rates_and_stuck_faults():
    cells = layout.grid(50, 40, 0.1)
    spec = parcel.rectangle(2.0, 2.0, 1.0, 0.5)
    state = [np.array([2.45, 1.95, 0, 0, 0, 0])]
    truth = Sensors(cells, default_offsets(0.1)).covered([spec], state)
    noisy = Sensors(cells, default_offsets(0.1), false_positive=0.02, false_negative=0.1)
    r = noisy.read([spec], state, np.random.default_rng(1))
    fp = (r & ~truth).sum() / (~truth).sum()
    fn = (~r & truth).sum() / truth.sum()
    assert abs(fp - 0.02) < 0.006 and abs(fn - 0.1) < 0.02
    on = np.zeros(truth.shape, bool)
    off = np.zeros(truth.shape, bool)
    on[0, 0] = True  # far from the parcel
    off[np.argwhere(truth)[0][0], np.argwhere(truth)[0][1]] = True
    faulty = Sensors(cells, default_offsets(0.1), stuck_on=on, stuck_off=off)
    r = faulty.read([spec], state, np.random.default_rng(0))
    assert r[0, 0] and not r[tuple(np.argwhere(truth)[0])]
    assert np.array_equal(r & ~on & ~off, truth & ~on & ~off)


def test_same_seed_same_readings_and_validation():
    cells = layout.grid(5, 5, 0.1)
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.5)
    y = [np.array([0.2, 0.2, 0.3, 0, 0, 0])]
    a = Sensors(cells, default_offsets(0.1), 0.3, 0.3).read([spec], y, np.random.default_rng(9))
    b = Sensors(cells, default_offsets(0.1), 0.3, 0.3).read([spec], y, np.random.default_rng(9))
    assert np.array_equal(a, b)
    with pytest.raises(ScenarioError, match="offsets"):
        Sensors(cells, np.zeros((6, 2)))
    with pytest.raises(ScenarioError, match="false_positive"):
        Sensors(cells, default_offsets(0.1), false_positive=1.5)
    sc, _ = load_scenario("prototype_18_network_ideal")
    d = sc.model_dump()
    d["sensors"]["stuck_on"] = [[3, 7]]
    with pytest.raises(ScenarioError, match=r"sensors.stuck_on\[0\]"):
        parse_scenario(d).build()


def test_recorded_readings_match_the_trajectory(tmp_path):
    sc, _ = load_scenario("prototype_18_network_ideal")
    d = sc.model_dump()
    d["sensors"]["record"] = True
    d["duration"] = 1.0
    res = run(parse_scenario(d).build())
    paths = write_results(res, tmp_path)
    rows = list(csv.DictReader(open(paths["sensors"])))
    assert len(rows) == 100 * 18 and list(rows[0])[:3] == ["t", "cell", "s0"]
    tr = res.parcels[0].trajectory
    spec = res.setup.specs[0]
    centres = res.setup.cells.positions
    for row in rows[::37]:
        t, cell = float(row["t"]), int(row["cell"])
        y = tr.states[np.argmin(np.abs(tr.times - t))]
        assert abs(tr.times[np.argmin(np.abs(tr.times - t))] - t) < 1e-9
        covered = parcel.footprint_margins(spec, y, centres[cell:cell + 1])[0] > 0
        assert int(row["s0"]) == int(covered)
        assert float(row["wheel0"]) in (0.2, -0.2)


def test_turning_on_the_edge_sensors_turns_the_box_sooner():
    sc, _ = load_scenario("prototype_18_network_ideal")
    setup = sc.build()
    centre = run(setup).parcels[0].trajectory.states[:, 0]
    all_sensors = dataclasses.replace(setup.control, program=Shuttle(0.2, 16, 20, trigger_sensors=range(5)))
    edges = run(dataclasses.replace(sc.build(), control=all_sensors)).parcels[0].trajectory.states[:, 0]
    assert edges.max() < centre.max() - 0.02 and edges.min() > centre.min() + 0.02


def test_running_a_setup_twice_is_bit_identical():
    """Delivery models and sensor noise start afresh from their seeds in every run."""
    sc, _ = load_scenario("prototype_18_network")
    d = sc.model_dump()
    d["duration"] = 1.0
    d["sensors"].update(false_positive=0.01, false_negative=0.05, seed=4)
    d["control"]["wire"]["bit_error_rate"] = 1e-3
    setup = parse_scenario(d).build()
    a, b = run(setup), run(setup)
    assert np.array_equal(a.parcels[0].trajectory.states, b.parcels[0].trajectory.states)
    assert np.array_equal(a.network.latencies, b.network.latencies)
    c = run(parse_scenario(d).build())
    assert np.array_equal(a.parcels[0].trajectory.states, c.parcels[0].trajectory.states)
