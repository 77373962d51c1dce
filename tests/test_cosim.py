"""Co-simulation of cell programs, the network and the parcels."""

import numpy as np
import pytest

from virtual_vehicle.cells.control import Shuttle
from virtual_vehicle.cells.network.programs import check_program
from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import layout
from virtual_vehicle.run.sim import run


def networked(delivery: str, **control):
    sc, _ = load_scenario("prototype_18_network")
    d = sc.model_dump()
    d["control"].update(delivery=delivery, **control)
    return run(parse_scenario(d).build())


def reversals(x):
    v = np.diff(x)
    v = v[np.abs(v) > 1e-9]
    return int(np.count_nonzero(np.sign(v[1:]) != np.sign(v[:-1])))


@pytest.mark.parametrize("delivery", ["ideal", "wire"])
def test_prototype_shuttle_passes_the_box_back_and_forth(delivery):
    res = networked(delivery)
    tr = res.parcels[0].trajectory
    assert tr.status == "completed"
    assert reversals(tr.states[:, 0]) >= 5
    assert tr.states[:, 0].min() > 0.08 and tr.states[:, 0].max() < 0.32  # turned before either end
    rec = res.network
    assert rec.per_tick["received"].sum() == rec.latency.count > 0
    for k in ("sent", "received", "bytes_sent", "bytes_received"):
        assert rec.per_cell[f"cell_{k}"].sum() == rec.per_tick[k].sum()
    if delivery == "ideal":
        np.testing.assert_allclose([rec.latency.min, rec.latency.max, rec.latency.mean], 0.01)
        assert rec.per_tick["dropped"].sum() == 0
    else:
        # latencies emerge from the hardware model: never below one 15-byte sentence at 9600 baud
        assert rec.latency.min >= 15 * 10 / 9600 and rec.latency.max - rec.latency.min > 0.01


def test_slower_network_reverses_later():
    """The box overshoots further when the 'reverse' flood crawls at 1200 baud than on ideal rounds."""
    fast = networked("ideal").parcels[0].trajectory.states[:, 0].max()
    slow = networked("wire", wire={"baud": 1200.0, "cts_timeout": 0.05}).parcels[0].trajectory.states[:, 0].max()
    assert slow > fast + 0.005


def test_shuttle_is_a_local_program():
    topo = from_layout(layout.grid(6, 3, 0.08))
    check_program(Shuttle(0.2, hop_limit=8, heartbeat=3), topo, {}, ticks=8)


def test_control_and_field_are_exclusive():
    sc, _ = load_scenario("prototype_18_network")
    d = sc.model_dump()
    d["field"] = {"kind": "uniform", "velocity": [0.1, 0.0]}
    with pytest.raises(ScenarioError, match="either"):
        parse_scenario(d)
    d.pop("field")
    d.pop("control")
    with pytest.raises(ScenarioError, match="either"):
        parse_scenario(d)
    d = sc.model_dump()
    d["control"]["wire"]["baud"] = -1
    with pytest.raises(ScenarioError, match="control.wire.baud"):
        parse_scenario(d)


def test_dead_links_from_the_scenario_are_cut_and_the_shuttle_still_works():
    sc, _ = load_scenario("prototype_18_network_ideal")
    d = sc.model_dump()
    d["control"]["dead_links"] = [[7, 0], [8, 0], [9, 0]]  # the middle row is cut between columns 1..4
    res = run(parse_scenario(d).build())
    topo = res.setup.control.topology
    assert not topo.connected[7, 0] and not topo.connected[8, 2]
    assert res.network.per_tick["lost"].sum() > 0  # sentences sent into the cut links
    assert reversals(res.parcels[0].trajectory.states[:, 0]) >= 5  # the flood goes round through the other rows
    d["control"]["dead_links"] = [[99, 0]]
    with pytest.raises(ScenarioError, match=r"control.dead_links\[0\]"):
        parse_scenario(d).build()


def test_constant_commands_reproduce_the_open_loop_run():
    """Splitting the integration at control ticks (zero-order hold) must not change the physics: cells that always
    command the uniform field's wheel speeds give the constant-field trajectory."""
    import dataclasses

    from virtual_vehicle.cells.network.delivery import IdealRounds
    from virtual_vehicle.cells.network.messages import Mailbox
    from virtual_vehicle.config.scenario import ControlSetup

    sc, _ = load_scenario("crossing_30x30")
    open_loop = run(sc.build())
    setup = sc.build()

    class Constant:
        schema = Shuttle.schema

        def init(self, n, ports, config):
            return {}

        def step(self, state, inputs):
            n, P = inputs.connected.shape
            wheels = np.tile([0.2, 0.0], (n, 1))
            return state, Mailbox.empty(self.schema, n, P), wheels

    topo = from_layout(setup.cells)
    ctl = ControlSetup(Constant(), topo, lambda: IdealRounds(topo), "ideal", 0.05, {})
    closed = run(dataclasses.replace(setup, control=ctl))
    a, b = open_loop.parcels[0].trajectory, closed.parcels[0].trajectory
    np.testing.assert_allclose(np.interp(1.234, b.times, b.states[:, 0]), np.interp(1.234, a.times, a.states[:, 0]),
                               atol=1e-6)
    np.testing.assert_allclose(b.states[-1], a.states[-1], atol=1e-9)
    assert [e.entered for e in b.events] == [e.entered for e in a.events]


def test_latency_statistics_stream_within_their_bin_width():
    from virtual_vehicle.run.sim import LatencyStats

    rng = np.random.default_rng(4)
    x = rng.lognormal(np.log(0.012), 0.6, size=20000)
    stats = LatencyStats()
    for chunk in np.array_split(x, 37):
        stats.add(chunk)
    assert stats.count == len(x) and stats.min == x.min() and stats.max == x.max()
    assert abs(stats.mean - x.mean()) < 1e-12 * x.sum()
    for q in (50, 95, 99):
        exact = np.percentile(x, q)
        assert exact * (1 - 1e-9) <= stats.percentile(q) <= exact * 1.042
