"""The sorter on a hexagonal lattice (six ports a cell, three omni wheels under each; issue 33): the bundled
``hex_sorting_junction`` delivers every parcel it feeds in time to its exit, with no collision, misroute or loss, and
what the sorter does not do on a hexagonal lattice is refused, naming it. (The compiled step against its statement
in array operations on six ports: tests/test_changed_cells.py; a hexagonal run resumed from a checkpoint:
tests/test_checkpoint.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.sorting import Sorter
from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report

HEX_MAP = """
oooooooooo
oooooooo00
EEoooooo00
EEoooooooo
oooooooo11
oooooooo11
oooooooooo
"""


def _hex(control=None, array=None, **extra):
    data = {"name": "t", "duration": 1.0, "friction": {"law": "stick_slip"},
            "array": {"kind": "map", "lattice": "hex", "pitch": 0.1, "map": HEX_MAP, **(array or {})},
            "control": {"program": "sort", **(control or {})},
            "parcels": [{"name": "box", "length": 0.2, "width": 0.2, "mass": 1.0, "mu": 0.6, "x": 0.05, "y": 0.35,
                         "destination": 0}], **extra}
    return parse_scenario(data)


def test_the_hexagonal_junction_delivers_every_parcel_to_its_exit():
    """Every parcel fed in time to ride out (10 s before the end; the longest ride is 9 s) leaves through its own
    exit lane (those of the north-east and south-east lanes turn off the entry's rows by 60-degree steps, those of
    the east lane go straight), and the one fed later is still riding; none collides, is misrouted or lost, and
    none is left stalled."""
    sc, _ = load_scenario("hex_sorting_junction")
    result = run(sc.build())
    so = sorting_report(result)
    due = [p.name for p in sc.parcels if p.t_start + 10.0 <= sc.duration]
    assert so["collisions"] == so["misrouted"] == so["lost"] == 0 and so["stalls"] == []
    assert len(due) == 9 and so["correct"] == len(due) and so["on_array"] == len(sc.parcels) - len(due)
    assert {r["name"] for r in so["parcels"] if r["correct"]} == set(due)
    assert {r["exit"] for r in so["parcels"] if r["correct"]} == {0, 1, 2}


@pytest.mark.parametrize("q", range(6))
def test_hexagonal_cells_drive_a_parcel_out_through_each_port_at_the_vehicle_speed(q):
    """Cells carrying a vehicle heading out through port q command the surface velocity at 60 q degrees in their
    frame at the sorter's speed (their omni wheels make it), exactly (cos 60 degrees = 0.5): a row of three cells
    whose wheel 0 is turned -60 q degrees, so that port q of each faces east, a parcel over the two western ones
    and the eastern one an exit leaving east; the velocity is east in the world."""
    from virtual_vehicle.cells.network.topology import from_layout
    from virtual_vehicle.model import layout

    angle = -np.pi / 3 * q
    cells = layout.hexagonal(3, 1, 0.1, drive_angle=angle)
    topo = from_layout(cells)
    assert topo.neighbor[0, q] == 1 and topo.neighbor[1, q] == 2  # port q faces east
    program = Sorter(0.3, gap=1)
    n, P = cells.n, topo.ports
    config = {"exit": np.array([-1, -1, 0]), "exit_port": np.array([-1, -1, q]),
              "entry": np.array([True, False, False]), "entry_no": np.arange(1, 4)}
    state, inbox = program.init(n, P, config), Mailbox.empty(program.schema, n, P)
    sensors = np.zeros((n, 5), bool)
    sensors[:2] = True  # a parcel over the two western cells
    for k in range(12):
        inputs = CellInputs(k * 0.01, sensors, inbox, topo.connected, config, np.array([0, -1, -1]))
        state, sent, wheels = program.step(state, inputs)
        inbox = Mailbox(program.schema, np.zeros((n, P), bool), {w: np.zeros_like(v) for w, v in sent.values.items()})
        for i in range(n):  # ideal rounds: what cell i said on a port arrives at its neighbour's port back
            for p in range(P):
                j, b = topo.neighbor[i, p], topo.back_port[i, p]
                if j >= 0 and sent.present[i, p]:
                    inbox.present[j, b] = True
                    for w in sent.values:
                        inbox.values[w][j, b] = sent.values[w][i, p]
    unit = [(1.0, 0.0), (0.5, np.sqrt(3) / 2), (-0.5, np.sqrt(3) / 2), (-1.0, 0.0), (-0.5, -np.sqrt(3) / 2),
            (0.5, -np.sqrt(3) / 2)][q]
    assert np.asarray(wheels)[:2].tolist() == [[0.3 * unit[0], 0.3 * unit[1]]] * 2 and not wheels[2].any()
    world = wheels[0] @ cells.drive_directions[0]  # the command's axes are the cell frame's
    np.testing.assert_allclose(world, [0.3, 0.0], atol=1e-12)


@pytest.mark.parametrize("control, array, message", [
    ({"central": True}, None, "central sorter runs on square lattices"),
    ({"reach": 31}, None, "at most 30 hops"),
    # an exit on the zig-zag top edge
    (None, {"map": "oo00oooo\noooooooo\noooooooo\nEEoooooo\nEEoooooo"}, "where the rows end"),
])
def test_what_the_hexagonal_sorter_does_not_do_is_refused_naming_it(control, array, message):
    with pytest.raises(ScenarioError, match=message):
        _hex(control, array).build()


def test_a_sorter_on_square_and_hexagonal_cells_at_once_is_refused():
    data = {"name": "t", "duration": 1.0, "array": {"kind": "mixed", "parts": [
        {"kind": "map", "pitch": 0.1, "map": "Eooo\nEooo"},
        {"kind": "map", "pitch": 0.1, "lattice": "hex", "map": "oo00\noo00", "origin": [0.4, 0.0]}]},
        "control": {"program": "sort"},
        "parcels": [{"name": "box", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 0.6, "x": 0.05, "y": 0.05,
                     "destination": 0}]}
    with pytest.raises(ScenarioError, match="mixes them"):
        parse_scenario(data).build()


def test_the_sorter_refuses_cells_of_other_port_counts_and_a_reach_six_ports_cannot_pack():
    with pytest.raises(ValueError, match="not on cells with 5 ports"):
        Sorter(0.3).init(3, 5, {})
    with pytest.raises(ValueError, match="at most 30 hops"):
        Sorter(0.3, reach=40).init(3, 6, {})
    Sorter(0.3, reach=30).init(3, 6, {})  # the most that packs
    Sorter(0.3, reach=40).init(3, 4, {})  # square cells keep six bits


def test_the_sorter_refuses_a_gap_its_request_word_cannot_carry():
    # a request's depth (up to gap + 1 hops) lies below the LATE (64) and YIELD (128) marks of the same word
    for gap in (0, 63, 100):
        with pytest.raises(ValueError, match="gap must be 1..62"):
            Sorter(0.3, gap=gap)
    Sorter(0.3, gap=62).init(3, 4, {})  # the most that fits below the marks
