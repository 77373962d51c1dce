"""The closed loop from the cells' own sensors: a parcel's pose from a binary sensor pattern, and a central
controller that drives parcels to target poses with it."""

import numpy as np
import pytest

from virtual_vehicle.cells.estimate import blobs, estimate_pose, initial_pose, sensor_spacing
from virtual_vehicle.cells.hardware import Sensors, default_offsets
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import layout, parcel
from virtual_vehicle.run.sim import run


def test_pose_from_a_single_sensor_pattern_is_within_a_fraction_of_the_sensor_spacing():
    cells = layout.grid(20, 20, 0.05)
    sensors = Sensors(cells, default_offsets(0.05))
    spacing = sensor_spacing(sensors.points)
    assert abs(spacing - 0.025) < 1e-12  # centre and edge midpoints: half a pitch apart
    rng = np.random.default_rng(1)
    pos, ang = [], []
    for shape in (parcel.rectangle(0.2, 0.15, 1.0, 0.5),
                  parcel.polygon([[0, 0], [0.25, 0], [0.25, 0.1], [0.1, 0.1], [0.1, 0.2], [0, 0.2]], 1.0, 0.5)):
        for _ in range(20):
            y = np.array([rng.uniform(0.35, 0.6), rng.uniform(0.35, 0.6), rng.uniform(-np.pi, np.pi)])
            lit = sensors.covered([shape], [y])
            group = blobs(sensors.points, lit, spacing)
            assert len(group) == 1
            guess = initial_pose(sensors.points, group[0])
            guess[2] = y[2] + rng.uniform(-0.3, 0.3)  # heading roughly known (the L has no axis of symmetry)
            est, wrong = estimate_pose(shape, sensors.points, lit, guess, spacing=spacing)
            pos.append(np.hypot(*(est[:2] - y[:2])))
            ang.append(abs((est[2] - y[2] + np.pi) % (2 * np.pi) - np.pi))
    pos, ang = np.array(pos), np.degrees(ang)
    assert pos.mean() < 0.25 * spacing and pos.max() < spacing
    assert ang.mean() < 3.0 and ang.max() < 10.0


def pose_scenario(law="viscous", targets=((0.62, 0.55, -0.3),), **control):
    return parse_scenario({
        "name": "pose", "duration": 4.0, "output_dt": 0.01,
        "array": {"kind": "grid", "nx": 20, "ny": 20, "pitch": 0.05},
        "control": {"program": "pose", "central": True, "period": 0.02, "speed": 0.2, "gain": 3.0,
                    "targets": [list(t) for t in targets],
                    **control},
        "friction": {"law": law},
        "parcels": [{"name": "box", "length": 0.2, "width": 0.15, "mass": 1.0, "mu": 0.8, "x": 0.3, "y": 0.3,
                     "theta": 0.2}]})


@pytest.mark.parametrize("law", ["viscous", "stick_slip"])
def test_closed_loop_from_sensors_reaches_the_target(law):
    s = run(pose_scenario(law).build()).summary()
    p = s["parcels"][0]
    assert p["final_error_mm"] < 5.0 and p["final_error_deg"] < 3.0
    assert p["settled_within_5mm_2deg_at_s"] is not None and p["settled_within_5mm_2deg_at_s"] < 3.5


def test_pose_program_needs_one_target_per_parcel():
    with pytest.raises(ScenarioError, match="targets"):
        parse_scenario({"duration": 1, "array": {"kind": "row", "n": 3, "pitch": 0.1},
                        "control": {"program": "pose"},
                        "parcels": [{"name": "a", "length": 0.1, "width": 0.1, "mass": 1, "mu": 0.5, "x": 0.1, "y": 0}]})
    with pytest.raises(ScenarioError, match="one target per parcel"):
        pose_scenario(targets=((0.5, 0.5, 0.0), (0.6, 0.6, 0.0))).build()


def test_rotate_in_place_to_an_angle():
    s = run(pose_scenario(targets=((0.3, 0.3, 0.8),)).build()).summary()
    p = s["parcels"][0]
    assert p["final_error_mm"] < 5.0 and p["final_error_deg"] < 3.0


def test_transport_along_a_path():
    """An L-shaped path through a waypoint: the parcel passes it, ends at the target, and stays near the path."""
    sc = pose_scenario(targets=((0.65, 0.65, 0.0),), waypoints=[[[0.65, 0.3, 0.0]]], pass_radius=0.01)
    p = run(sc.model_copy(update={"duration": 6.0}).build()).summary()["parcels"][0]
    assert p["final_error_mm"] < 5.0 and p["final_error_deg"] < 3.0
    assert p["max_path_deviation_mm"] < 30.0
