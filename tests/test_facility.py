"""The industrial drive profile (wheels to 1.1 m/s, 2.5 m/s^2, about 150 ms response, 100 Hz) as a named
``[wheels] profile``, and the bundled facility scenario that uses it: 40 x 40 cells, 4 entries, 6 exit lanes, a
mixed stream of parcels; it validates and delivers."""

import numpy as np
import pytest
from scipy.ndimage import label

from virtual_vehicle.cells.hardware import PROFILES, WheelDrives
from virtual_vehicle.config.scenario import WheelSpec, load_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def step_response(params, target, load=2.0, ticks=150, period=0.01):
    drives = WheelDrives(1, params)
    return np.array([drives.step(np.array([[target, 0.0]]), np.array([[load, 0.0]]), period)[0, 0]
                     for _ in range(ticks)])


def test_the_industrial_profile_meets_its_specification():
    spec = WheelSpec(profile="industrial")
    assert spec.model == "motor" and spec.kp == PROFILES["industrial"]["kp"]
    params = spec.motor()
    t = np.arange(1, 151) * 0.01
    full = step_response(params, 1.1)
    assert abs(full[-1] - 1.1) < 0.02  # reaches 1.1 m/s and holds it
    assert 2.2 < np.diff(full).max() / 0.01 <= 2.5  # m/s^2: the drive's torque caps the acceleration
    small = step_response(params, 0.1)
    assert 0.1 <= t[np.argmax(small >= 0.632 * 0.1)] <= 0.2  # s: about 150 ms to answer a small step


def test_a_profile_fills_only_what_the_table_leaves_out():
    spec = WheelSpec(profile="industrial", kp=10.0)
    assert spec.kp == 10.0 and spec.ki == PROFILES["industrial"]["ki"]
    assert WheelSpec().model == "ideal"


def test_the_facility_scenario_is_a_hall_of_40_by_40_cells_with_4_entries_and_6_exits():
    sc, _ = load_scenario("facility_40x40")
    setup = sc.build()
    cells, cfg = setup.cells, setup.control.config
    assert cells.n >= 1600 and np.ptp(cells.positions, axis=0).min() >= 3.9
    col = np.rint(cells.positions[:, 0] / cells.pitch).astype(int)
    row = np.rint(cells.positions[:, 1] / cells.pitch).astype(int)

    def groups(mask):
        grid = np.zeros((row.max() + 1, col.max() + 1), bool)
        grid[row[mask], col[mask]] = True
        return label(grid)[1]

    assert groups(np.asarray(cfg["entry"])) == 4
    exits = np.asarray(cfg["exit"])
    assert sum(groups(exits == k) for k in range(exits.max() + 1)) == 6
    assert sc.wheels.model == "motor" and sc.wheels.profile == "industrial" and sc.control.speed == 1.1
    assert sc.control.period == 0.01 and sc.friction.law == "stick_slip"
    lengths = np.array([p.length for p in sc.parcels])
    masses = np.array([p.mass for p in sc.parcels])
    assert lengths.min() >= 0.2 and lengths.max() <= 0.35 and masses.min() >= 0.3 and masses.max() <= 8.0
    assert len({p.destination for p in sc.parcels}) == 4


@pytest.mark.parametrize("program", ["sort", "reserve"])
def test_the_facility_delivers(program):
    from virtual_vehicle.cells.programs import PROGRAMS

    sc, _ = load_scenario("facility_40x40")
    control = PROGRAMS[program].Options(**(sc.control.model_dump() | {"program": program}))
    result = run(sc.model_copy(update={"duration": 8.0, "control": control}).build())
    report = sorting_report(result)
    assert report["collisions"] == 0 and report["misrouted"] == 0 and report["lost"] == 0
    assert report["correct"] >= 1 and report["on_array"] >= 4  # the first out within 8 s, more on their way
