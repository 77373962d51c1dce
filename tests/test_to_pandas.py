"""RunResult.to_pandas: every table of a run as a pandas DataFrame in one call, the columns' units kept."""

import sys

import numpy as np
import pytest

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run import tables
from virtual_vehicle.run.sim import run


def _units(table):
    return {f.name: f.metadata[b"unit"].decode() for f in table.schema}


def test_a_networked_recorded_run_gives_every_table_with_units():
    sc, _ = load_scenario("prototype_18_network_ideal")
    sc = sc.model_copy(update={"duration": 0.3, "sensors": sc.sensors.model_copy(update={"record": True})})
    result = run(sc.build())
    frames = result.to_pandas()
    arrow = tables.build(result)
    assert sorted(frames) == sorted(arrow) == ["cell_traffic", "cells", "events", "network", "trajectories"]
    for name, df in frames.items():
        assert list(df.columns) == arrow[name].column_names
        assert len(df) == arrow[name].num_rows
        assert df.attrs["units"] == _units(arrow[name])
    traj = frames["trajectories"]
    assert traj.attrs["units"] == {"parcel": "", "t": "s", "x": "m", "y": "m", "theta": "rad", "vx": "m/s",
                                   "vy": "m/s", "omega": "rad/s"}
    pr = result.parcels[0]
    rows = traj[traj.parcel == pr.spec.name]
    assert np.array_equal(rows.t.to_numpy(), pr.trajectory.times)
    assert np.array_equal(rows[["x", "y", "theta", "vx", "vy", "omega"]].to_numpy(), pr.trajectory.states)
    assert frames["cells"].attrs["units"]["wheel0"] == "m/s" and frames["network"].attrs["units"]["t"] == "s"
    assert frames["cell_traffic"].attrs["units"]["x"] == "m" and len(frames["cell_traffic"]) == result.setup.cells.n


def test_a_constant_field_run_has_its_two_tables():
    sc, _ = load_scenario("prototype_18")
    result = run(sc.model_copy(update={"duration": 0.5}).build())
    frames = result.to_pandas()
    assert sorted(frames) == ["events", "trajectories"]
    first = result.parcels[0].trajectory.events[0]
    assert frames["events"].t.iloc[0] == first.t and list(frames["events"].entered.iloc[0]) == list(first.entered)


def test_without_pandas_the_error_says_what_to_install(monkeypatch):
    result = run(load_scenario("paper_2x2_inward")[0].build())
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas now raises ImportError
    with pytest.raises(ImportError, match="to_pandas needs pandas.*pip install pandas"):
        result.to_pandas()
