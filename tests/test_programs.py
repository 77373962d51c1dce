"""Multi-hop primitives and the cell-program contract, against breadth-first search on the layout's graph, under
both delivery models."""

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import shortest_path

from virtual_vehicle.cells.network.delivery import IdealRounds
from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import UNREACHABLE, CellInputs, Flood, Routing, check_program
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.cells.network.wire import WireLevel
from virtual_vehicle.model import layout


def bfs(topo, sources):
    """Hop distances to the nearest source over live links (scipy's csgraph), UNREACHABLE where cut off."""
    i, p = np.nonzero(topo.connected)
    g = csr_matrix((np.ones(len(i)), (i, topo.neighbor[i, p])), shape=(topo.n, topo.n))
    d = shortest_path(g, unweighted=True, indices=np.flatnonzero(sources)).min(axis=0)
    return np.where(np.isfinite(d), d, UNREACHABLE).astype(int)


def run(program, topo, config, ticks, delivery=None, period=0.01):
    delivery = delivery or IdealRounds(topo)
    n, P = topo.n, topo.ports
    state = program.init(n, P, config)
    inbox = Mailbox.empty(program.schema, n, P)
    for k in range(ticks):
        state, out, _ = program.step(state, CellInputs(k * period, np.zeros((n, 1), bool), inbox, topo.connected, config))
        inbox, _ = delivery.exchange(out, k * period, period)
    return state


@pytest.mark.parametrize("max_age", [0, 3])
def test_gradient_equals_bfs_and_reconverges_when_cells_die(max_age):
    topo = from_layout(layout.grid(12, 8, 0.1))
    exits = np.zeros(topo.n, bool)
    exits[[11, 95]] = True
    prog = Routing(max_age)
    state = run(prog, topo, {"exit": exits}, 25)
    np.testing.assert_array_equal(state["dist"], bfs(topo, exits))
    # a wall of dead cells with one gap: the field re-converges to the detour distances
    dead = [j * 12 + 6 for j in range(1, 8)]
    broken = topo.with_faults(dead_cells=dead)
    st = prog.init(topo.n, 4, {"exit": exits})
    st.update(dist=state["dist"], heard=state["heard"], age=state["age"])
    delivery = IdealRounds(broken)
    inbox = Mailbox.empty(prog.schema, topo.n, 4)
    for k in range(UNREACHABLE + 30):
        st, out, _ = prog.step(st, CellInputs(k, np.zeros((topo.n, 1), bool), inbox, broken.connected, {"exit": exits}))
        inbox, _ = delivery.exchange(out, k, 1.0)
    alive = broken.alive
    np.testing.assert_array_equal(st["dist"][alive], bfs(broken, exits)[alive])


def test_gradient_under_wire_level_converges_to_the_same_field():
    topo = from_layout(layout.grid(6, 4, 0.1))
    exits = np.zeros(topo.n, bool)
    exits[0] = True
    # at 9600 baud a cell cannot get four 14-byte sentences out every 50 ms: trusting only the last tick fails
    flicker = run(Routing(max_age=0), topo, {"exit": exits}, 60, delivery=WireLevel(topo), period=0.05)
    assert np.any(flicker["dist"] == UNREACHABLE)
    # remembering each neighbour for a few ticks gives the exact field
    state = run(Routing(max_age=4), topo, {"exit": exits}, 60, delivery=WireLevel(topo), period=0.05)
    np.testing.assert_array_equal(state["dist"], bfs(topo, exits))


def test_flood_reaches_exactly_the_cells_within_its_hop_limit():
    topo = from_layout(layout.grid(15, 15, 0.1))
    origin = np.zeros(topo.n, bool)
    origin[7 * 15 + 7] = True
    for limit in (0, 1, 3, 6):
        state = run(Flood(limit), topo, {"origin": origin, "value": np.full(topo.n, 42)}, limit + 3)
        within = bfs(topo, origin) <= limit
        np.testing.assert_array_equal(state["seq"] == 1, within)
        np.testing.assert_array_equal(state["value"][within], 42)
        np.testing.assert_array_equal(state["hops"][within], bfs(topo, origin)[within])


def test_packets_are_forwarded_down_the_gradient_in_shortest_hops():
    topo = from_layout(layout.grid(10, 6, 0.1)).with_faults(dead_cells=[4 + 10 * j for j in range(0, 5)])
    exits = np.zeros(topo.n, bool)
    exits[9] = True
    packets = np.full(topo.n, -1)
    packets[[0, 50, 33]] = [100, 200, 300]
    state = run(Routing(), topo, {"exit": exits, "packet": packets}, 60)
    got = dict(state["delivered"][9])
    d = bfs(topo, exits)
    assert got == {100: d[0], 200: d[50], 300: d[33]}  # each took a shortest path around the wall
    assert d[0] > 9  # and that path is a detour


def test_contract_checker_accepts_local_programs_and_catches_id_leaks():
    topo = from_layout(layout.grid(5, 4, 0.1))
    exits = np.zeros(topo.n, bool)
    exits[3] = True
    check_program(Routing(), topo, {"exit": exits, "packet": np.where(np.arange(20) == 12, 1, -1)}, ticks=8)
    origin = np.zeros(topo.n, bool)
    origin[0] = True
    check_program(Flood(3), topo, {"origin": origin, "value": np.full(20, 5)}, ticks=6)

    class Cheater:
        """Uses its cell id (np.arange): not allowed."""

        schema = Schema.of(x=(1, WordType.I16))

        def init(self, n, ports, config):
            return {}

        def step(self, state, inputs):
            n, P = inputs.connected.shape
            out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, x=np.arange(n))
            return state, out, np.zeros((n, 2))

    with pytest.raises(AssertionError, match="not local"):
        check_program(Cheater(), topo, {}, ticks=2)
