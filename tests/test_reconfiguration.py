"""Cells taken out of the array and snapped in while a run goes on (issue 6, modularity / reconfiguration): an absent
cell carries, drives, senses and says nothing; the distributed programs re-converge (the sorter's gradients equal
a central shortest-path computation on the new array) and parcels keep being delivered without collisions."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from virtual_vehicle.cells.sorting import MAX_EXITS, UNREACHABLE
from virtual_vehicle.config.scenario import CellChange, ReconfigurationSpec, load_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.run.sim import NetworkRun, run

WALL = [j * 24 + 12 for j in range(2, 10)]  # sorting_junction: a wall across the middle, rows 2..9 of column 12


def _reconfigured(duration: float, **spec):
    sc, _ = load_scenario("sorting_junction")
    return sc.model_copy(update={"duration": duration, "reconfiguration": ReconfigurationSpec(**spec),
                                 "sensors": sc.sensors.model_copy(update={"record": True})})


def _central_gradients(job: NetworkRun) -> np.ndarray:
    """Shortest paths to every exit on the array as it is now (Dijkstra on the live links, each step into a cell
    costing what the sorter charges for it: 1, or 1 + edge_cost at a side with no neighbour)."""
    topo, cfg = job.topology, job.setup.control.config
    program = job.setup.control.program
    exit_id = np.asarray(cfg["exit"])
    conn = topo.connected
    cost = np.where(conn.all(axis=1) | (exit_id >= 0), 1.0, 1.0 + program.edge_cost)
    a, p = np.nonzero(conn)
    graph = coo_matrix((cost[a], (topo.neighbor[a, p], a)), shape=(topo.n, topo.n)).tocsr()
    out = np.full((topo.n, MAX_EXITS), np.inf)
    for e in range(MAX_EXITS):
        src = np.flatnonzero(exit_id == e)
        if len(src):
            out[:, e] = dijkstra(graph, indices=src, min_only=True)
    return np.where(np.isfinite(out), out, UNREACHABLE)


def _run_until(job: NetworkRun, t: float) -> None:
    while not job.done and job.k * job.period < t - 1e-9:
        job.tick()


def test_the_sorters_gradients_reconverge_to_shortest_paths_after_cells_leave_and_return():
    setup = _reconfigured(12.0, changes=[CellChange(t=2.0, remove=WALL), CellChange(t=6.0, add=WALL)]).build()
    job = NetworkRun(setup)
    _run_until(job, 1.9)
    before = _central_gradients(job)
    np.testing.assert_array_equal(job.state["dist"], before)
    _run_until(job, 5.9)  # the wall has been out for 4 s
    present = job.present
    assert not present[WALL].any() and present.sum() == setup.cells.n - len(WALL)
    during = _central_gradients(job)
    np.testing.assert_array_equal(job.state["dist"][present], during[present])
    assert np.any(during[present] > before[present])  # the detour around the wall is longer
    _run_until(job, 10.0)  # back in for 4 s: the added cells started from scratch and learnt their distances
    np.testing.assert_array_equal(job.state["dist"], _central_gradients(job))
    np.testing.assert_array_equal(job.state["dist"], before)


def test_a_removed_wall_is_detoured_silent_and_dark_and_the_stream_goes_on():
    res = run(_reconfigured(25.0, changes=[CellChange(t=5.0, remove=WALL), CellChange(t=15.0, add=WALL)]).build())
    s = res.summary()
    assert [c["removed"] for c in s["reconfigured"]] == [WALL, []]
    assert [c["added"] for c in s["reconfigured"]] == [[], WALL]
    so = s["sorting"]
    assert so["misrouted"] == 0 and so["collisions"] == 0 and so["lost"] == 0 and so["correct"] >= 3
    log = res.cell_log
    out = (log.t >= 5.0 - 1e-9) & (log.t < 15.0 - 1e-9)
    assert log.sent[out][:, WALL].sum() == 0 and log.received[out][:, WALL].sum() == 0
    assert np.all(log.wheels[out][:, WALL] == 0) and not log.readings[out][:, WALL].any()
    assert log.sent[log.t >= 15.0][:, WALL].sum() > 0  # snapped back in, they talk again
    holes = [shapely.Point(res.setup.cells.positions[c]) for c in WALL]
    for pr in res.parcels:  # no parcel rests where the wall is missing
        for t, y in zip(pr.trajectory.times, pr.trajectory.states):
            if 5.0 < t < 15.0:
                poly = pr.spec.world_polygon(y)
                assert not any(poly.contains(h) for h in holes), (pr.spec.name, t)


def test_cells_absent_at_the_start_are_added_later():
    gap = [5 * 24 + 8, 6 * 24 + 8]
    setup = _reconfigured(6.0, absent=gap, changes=[CellChange(t=2.0, add=gap)]).build()
    assert setup.present[gap].tolist() == [False, False]
    job = NetworkRun(setup)
    _run_until(job, 1.5)
    assert not job.topology.alive[gap].any()
    _run_until(job, 5.0)
    assert job.topology.alive[gap].all()
    np.testing.assert_array_equal(job.state["dist"], _central_gradients(job))


def test_a_cell_taken_out_carries_nothing():
    """A parcel over a hole: the absent cell never supports it, and eq. 33's closed form v = V (1 - exp(-mu g t))
    holds whatever the supports."""
    cells = layout.grid(12, 8, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    model = ParcelModel(cells, spec, fields.Uniform((0.2, 0.0)).velocities(cells), laws.ViscousLaw())
    present = np.ones(cells.n, bool)
    hole = 3 * 12 + 5
    present[hole] = False
    model.present = present
    tr = integrate(model, [0.3, 0.35, 0.0, 0, 0, 0], 0.0, 2.0, sample_dt=0.05)
    assert all(hole not in e.entered and hole not in e.left for e in tr.events)
    assert len(tr.events) >= 4
    assert not any(hole in model.support_at(y) for y in tr.states)
    np.testing.assert_allclose(tr.states[:, 3], 0.2 * (1 - np.exp(-9.81 * tr.times)), atol=1e-10)


@pytest.mark.parametrize("spec, message", [
    ({"changes": [CellChange(t=2.0, add=[5])]}, r"changes\[0\]\.add\[0\].*already in the array"),
    ({"changes": [CellChange(t=2.0, remove=[5]), CellChange(t=3.0, remove=[5])]}, r"changes\[1\]\.remove\[0\]"),
    ({"changes": [CellChange(t=99.0, remove=[5])]}, "not before the end"),
    ({"absent": [9999]}, r"reconfiguration\.absent\[0\]"),
])
def test_bad_reconfigurations_are_named(spec, message):
    with pytest.raises(ScenarioError, match=message):
        _reconfigured(20.0, **spec).build()


def test_reconfiguration_needs_distributed_control():
    sc, _ = load_scenario("crossing_30x30")
    with pytest.raises(ScenarioError, match="distributed program"):
        sc.model_copy(update={"reconfiguration": ReconfigurationSpec(absent=[3])}).build()
    sc, _ = load_scenario("sorting_junction")
    central = sc.model_copy(update={"control": sc.control.model_copy(update={"central": True}),
                                    "reconfiguration": ReconfigurationSpec(absent=[3])})
    with pytest.raises(ScenarioError, match="central = false"):
        central.build()


def test_a_checkpoint_taken_while_cells_are_out_resumes_to_the_same_run(tmp_path):
    from virtual_vehicle.run.sim import resume

    setup = _reconfigured(8.0, changes=[CellChange(t=2.0, remove=WALL), CellChange(t=6.0, add=WALL)]).build()
    whole = run(setup, checkpoint=tmp_path / "c.ckpt", checkpoint_every=4.0)  # the last checkpoint: wall out
    again = resume(tmp_path / "c.ckpt")
    assert again.summary()["reconfigured"] == whole.summary()["reconfigured"]
    for a, b in zip(whole.parcels, again.parcels):
        np.testing.assert_array_equal(a.trajectory.states, b.trajectory.states)


def test_cells_leave_and_return_over_the_wire_model():
    sc, _ = load_scenario("prototype_18_network")
    cell = 9
    sc = sc.model_copy(update={"duration": 3.0, "sensors": sc.sensors.model_copy(update={"record": True}),
                               "reconfiguration": ReconfigurationSpec(changes=[CellChange(t=1.0, remove=[cell]),
                                                                               CellChange(t=2.0, add=[cell])])})
    res = run(sc.build())
    log = res.cell_log
    out = (log.t >= 1.0 - 1e-9) & (log.t < 2.0 - 1e-9)
    back = log.t >= 2.0 - 1e-9
    assert log.sent[out][:, cell].sum() == 0 and log.received[out][:, cell].sum() == 0
    assert log.sent[back][:, cell].sum() > 0 and log.received[back][:, cell].sum() > 0  # polling again
    assert [c["removed"] for c in res.summary()["reconfigured"]] == [[cell], []]
