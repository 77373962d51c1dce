"""Re-ordering a stream: parcels that arrive out of order leave in the order of their sequence numbers, parked in
bays until their turn; one-way aisles keep parcels from meeting head on. Distributed and central control."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from virtual_vehicle.cells.network.programs import check_program
from virtual_vehicle.cells.sorting import Sorter, decode_goal, encode_goal
from virtual_vehicle.cells.sorting.rules import pack, unpack
from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def reorder(central: bool):
    sc, _ = load_scenario("reorder_stream")
    return sc.model_copy(update={"control": sc.control.model_copy(update={"central": central})})


@pytest.mark.parametrize("central", [False, True])
def test_a_scrambled_stream_leaves_in_sequence(central):
    sc = reorder(central)
    arrival = [p.sequence for p in sorted(sc.parcels, key=lambda p: p.t_start)]
    assert arrival != sorted(arrival)  # the stream really arrives out of order
    res = run(sc.build())
    report = sorting_report(res)
    assert report["collisions"] == 0 and report["lost"] == 0 and report["misrouted"] == 0
    assert report["correct"] >= 12 and report["order_inversions"] == 0
    left = sorted((r["entered_at_s"] + r["delivery_time_s"], r["sequence"]) for r in report["parcels"]
                  if r["outcome"] == "delivered")
    assert [q for _, q in left] == list(range(len(left)))  # 0, 1, 2, ... exactly
    # one-way cells: no parcel ever moves west in the entry aisle (y < 0.35 m) or south in the bays
    for pr in res.parcels:
        X = pr.trajectory.states
        aisle = X[:, 1] < 0.35
        bays = (X[:, 1] > 0.45) & (X[:, 1] < 0.75)
        assert np.all(X[aisle, 3] > -2e-3) and np.all(X[bays, 4] > -2e-3), pr.spec.name


def test_goal_words_carry_the_exit_and_the_sequence_number():
    for exit, seq in ((0, None), (2, None), (0, 0), (1, 7), (2, 8000)):
        word = encode_goal(exit, seq)
        assert word < 2**15  # it travels as an I16 word
        e, q = decode_goal(word)
        assert (int(e), int(q)) == (exit, -1 if seq is None else seq)


def test_the_sorter_stays_local_with_parking_and_one_way_cells():
    setup = reorder(False).build()
    cfg = {k: v for k, v in setup.control.config.items() if k != "clearance"}
    assert cfg["park"].sum() == 3 and (cfg["forbid"] >= 0).sum() > 100
    y = np.array([1.6, 0.55, 0.0, 0.0, 0.0, 0.0])  # a parcel in the second bay
    seen = setup.sensors.read([setup.specs[0]], [y], np.random.default_rng(0))
    assert seen.any()
    check_program(Sorter(0.3), setup.control.topology, cfg, ticks=8, sensors=seen)


MAP = """
oo0
oo0
EoP
EoP
"""


def scenario(parcels, program="sort", map_text=MAP, lattice="square"):
    return {"duration": 1.0, "array": {"kind": "map", "pitch": 0.1, "map": map_text, "lattice": lattice},
            "control": {"program": program, **({"targets": [[0.1, 0.1, 0.0]] * len(parcels)} if program == "pose"
                                               else {})},
            "friction": {"law": "viscous"},
            "parcels": [{"name": f"p{k}", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 2.0, "x": 0.05,
                         "y": 0.05, "t_start": float(k), **p} for k, p in enumerate(parcels)]}


@pytest.mark.parametrize("parcels, where, words", [
    ([{"sequence": 0}], r"parcels\[0\].sequence", "destination"),
    ([{"destination": 0, "sequence": 0}, {"destination": 0, "sequence": 2}], r"sequence", r"missing \[1\]"),
    ([{"destination": 0, "sequence": 1}, {"destination": 0, "sequence": 1}], r"sequence", "each once"),
])
def test_sequence_numbers_must_be_deliverable(parcels, where, words):
    with pytest.raises(ScenarioError, match=where) as exc:
        parse_scenario(scenario(parcels)).build()
    assert exc.match(words)


def test_sequence_numbers_need_parking_and_a_sorter():
    with pytest.raises(ScenarioError, match="control.parking"):
        parse_scenario(scenario([{"destination": 0, "sequence": 0}], map_text="oo0\noo0\nEoo\nEoo")).build()
    with pytest.raises(ScenarioError, match=r"parcels\[0\].sequence"):
        parse_scenario(scenario([{"sequence": 0}], program="pose")).build()


def test_parking_leaves_room_for_three_exits_only():
    four = ".o0o.\nooooo\n1oEo2\nooPoo\n.o3o."
    with pytest.raises(ScenarioError, match="control.parking"):
        parse_scenario(scenario([{"destination": 0}], map_text=four)).build()


def test_one_way_arrows_are_for_square_lattices():
    with pytest.raises(ScenarioError, match="square"):
        parse_scenario(scenario([{"destination": 0}], map_text="o>0\no>0\nEoo\nEoo", lattice="hex")).build()


@given(st.lists(st.lists(st.integers(0, 255), min_size=4, max_size=4), min_size=1, max_size=20),
       st.sampled_from([6, 8]))
def test_packed_words_fit_a_signed_32_bit_word_and_unpack_exactly(rows, bits):
    values = np.array(rows) % (1 << bits)
    words = pack(values, bits)
    assert np.all(words >= -(1 << 31)) and np.all(words < 1 << 31)  # travels as an I32 word
    for q in range(4):
        np.testing.assert_array_equal(unpack(words, q, bits), values[:, q])
