"""The cell network: topology from layouts, ideal-round delivery, and the wire-level model's timing, contention,
faults and corruption handling."""

import numpy as np
import pytest

from virtual_vehicle.cells.network.delivery import IdealRounds
from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.sentence import SentenceError, WordType
from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.cells.network.wire import WireLevel, WireParams
from virtual_vehicle.model import layout

SCHEMA = Schema.of(value=(1, WordType.I16), hops=(2, WordType.U8))
EAST, NORTH, WEST, SOUTH = range(4)


def outbox(n, sends):
    """sends: {(cell, port): value}"""
    box = Mailbox.empty(SCHEMA, n, 4)
    for (i, p), v in sends.items():
        box.present[i, p] = True
        box.values["value"][i, p] = v
        box.values["hops"][i, p] = 1
    return box


def test_topology_of_a_grid_is_mutual_and_silent_at_edges():
    t = from_layout(layout.grid(4, 3, 0.1))
    assert t.neighbor.shape == (12, 4)
    # every link is mutual: the neighbour's back port leads back
    for i, p in zip(*np.nonzero(t.neighbor >= 0)):
        j, q = t.neighbor[i, p], t.back_port[i, p]
        assert t.neighbor[j, q] == i and t.back_port[j, q] == p
    assert t.neighbor[0, WEST] == -1 and t.neighbor[0, SOUTH] == -1
    assert (t.neighbor >= 0).sum() == 2 * (3 * 3 + 4 * 2)  # directed links of a 4x3 grid
    rotated = from_layout(layout.grid(4, 3, 0.1, drive_angle=np.pi / 2))  # ports turn with the cell frame
    assert rotated.neighbor[0, EAST] == 4  # "east" of the cell is +y in the world


def lattice_links(cells, ports: int) -> np.ndarray:
    """(n, ports) the cell one pitch away straight out of each port (ports every 360/ports degrees from +x, wheel 0
    along +x), -1 where there is none: the links a lattice means."""
    angles = 2 * np.pi * np.arange(ports) / ports
    want = cells.positions[:, None, :] + cells.pitch * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    gap = np.linalg.norm(want[:, :, None, :] - cells.positions[None, None, :, :], axis=3)  # (n, ports, n)
    return np.where(gap.min(axis=2) < 1e-6, gap.argmin(axis=2), -1)


def far_links(t, cells) -> int:
    """Links (each counted once) between cells more than 1.01 pitch apart: not lattice neighbours."""
    i, p = np.nonzero(t.neighbor >= 0)
    j = t.neighbor[i, p]
    return int(((np.hypot(*(cells.positions[j] - cells.positions[i]).T) > 1.01 * cells.pitch) & (i < j)).sum())


def test_a_hole_in_a_square_grid_leaves_no_link_across_its_corner():
    """A diagonal cell lies on the boundary of two ports' sectors (45 degrees): it belongs to neither, whatever the
    rounding of the 0.1 m positions, so where the straight neighbour is missing the port is silent. Removed one at a
    time, several of these holes used to leave a link diagonally across a corner (e.g. row 3, column 3)."""
    for r in range(6):
        for c in range(8):
            rows = [["o"] * 8 for _ in range(6)]
            rows[r][c] = "."
            cells, _ = layout.from_map("\n".join("".join(row) for row in rows), 0.1)
            t = from_layout(cells)
            assert far_links(t, cells) == 0, (r, c)
            np.testing.assert_array_equal(t.neighbor, lattice_links(cells, 4), err_msg=f"hole at {(r, c)}")


def test_stress_floor_86_links_only_lattice_neighbours():
    """Seed 86's floor (holes, 0.1 m pitch) had two links across a hole's corner; every port now has the cell
    straight out of it or none."""
    from virtual_vehicle.analysis.stress import random_floor

    a = random_floor(86).table["array"]
    cells, _ = layout.from_map(a["map"], a["pitch"])
    t = from_layout(cells)
    assert far_links(t, cells) == 0
    np.testing.assert_array_equal(t.neighbor, lattice_links(cells, 4))


def test_a_hexagonal_lattice_with_holes_links_its_six_neighbours_and_nothing_else():
    """Its sector boundaries (30 degrees off each port) hold no cell within reach: holes change nothing but the
    missing links."""
    cells, _ = layout.from_map("oooooo\noo.ooo\nooo.oo\no.oooo\noooooo", 0.1, lattice="hex")
    t = from_layout(cells)
    assert far_links(t, cells) == 0
    np.testing.assert_array_equal(t.neighbor, lattice_links(cells, 6))


def test_topology_faults_cut_both_directions():
    t = from_layout(layout.grid(3, 3, 0.1)).with_faults(dead_cells=[4], dead_links=[(0, EAST)])
    assert not t.alive[4] and not t.connected[4].any()
    assert not t.connected[1, SOUTH] and not t.connected[3, EAST]  # links into the dead centre
    assert not t.connected[0, EAST] and not t.connected[1, WEST]


def test_ideal_rounds_delivers_to_the_opposite_port():
    t = from_layout(layout.grid(3, 1, 0.1))
    ideal = IdealRounds(t)
    inbox, stats = ideal.exchange(outbox(3, {(0, EAST): 7, (1, WEST): -3, (2, EAST): 9}), 0.0, 0.01)
    assert inbox.present[1, WEST] and inbox.values["value"][1, WEST] == 7
    assert inbox.present[0, EAST] and inbox.values["value"][0, EAST] == -3
    assert inbox.count() == 2 and stats.unaddressed == 1 and stats.sent.sum() == 2  # cell 2 has nobody east
    assert np.all(stats.latencies == 0.01)
    assert stats.bytes_sent.sum() == 2 * SCHEMA.sentence_bytes


def test_ideal_rounds_loss_and_dead_cells():
    t = from_layout(layout.grid(10, 10, 0.1))
    send = np.ones(100, bool)
    box = Mailbox.broadcast(SCHEMA, send, 4, value=np.arange(100), hops=np.zeros(100))
    inbox, stats = IdealRounds(t, loss_rate=0.25, seed=1).exchange(box, 0, 0.01)
    total = (t.neighbor >= 0).sum()
    assert stats.lost + inbox.count() == total
    assert abs(stats.lost / total - 0.25) < 0.06
    dead, dstats = IdealRounds(t.with_faults(dead_cells=[55])).exchange(box, 0, 0.01)
    assert not dead.present[55].any() and not dead.present[54, EAST]
    assert dstats.lost == 4  # the four neighbours' sentences to the dead cell


def byte_time(params, nbytes):
    return nbytes * params.bits_per_byte / params.baud


def test_wire_latency_follows_the_protocol_exactly():
    """Cell 0 sends east at t=0: it raises its handshake line at once; cell 1 polls port 0, 1, 2(west) at
    0, tau, 2 tau, so the transfer starts at 2 tau and lasts select + bytes at 10 bits each."""
    p = WireParams()
    w = WireLevel(from_layout(layout.grid(2, 1, 0.1)), p)
    inbox, stats = w.exchange(outbox(2, {(0, EAST): 123}), 0.0, 0.05)
    assert inbox.present[1, WEST] and inbox.values["value"][1, WEST] == 123
    expected = 2 * p.poll_time + p.select_time + byte_time(p, SCHEMA.sentence_bytes)
    assert stats.latencies.tolist() == pytest.approx([expected], abs=1e-12)
    assert stats.extra["timeouts"] == 0 and stats.dropped == 0


def test_wire_serialises_a_busy_receiver():
    """Four neighbours send to the centre at once: one port, one sentence at a time, so the last arrives after at
    least four transfer times, and the queue drains without loss."""
    p = WireParams(cts_timeout=0.2)
    t = from_layout(layout.grid(3, 3, 0.1))
    w = WireLevel(t, p)
    inbox, stats = w.exchange(outbox(9, {(1, NORTH): 1, (3, EAST): 2, (5, WEST): 3, (7, SOUTH): 4}), 0.0, 0.1)
    assert inbox.present[4].all() and sorted(inbox.values["value"][4].tolist()) == [1, 2, 3, 4]
    transfer = p.select_time + byte_time(p, SCHEMA.sentence_bytes)
    assert max(stats.latencies) >= 4 * transfer
    assert stats.dropped == 0 and stats.corrupted == 0


def test_wire_mutual_sends_resolve_by_polling_while_waiting():
    """Cells 0 and 1 both want to send to each other at t=0. Each raises its line and, waiting, polls on: cell 0's
    sweep is at port 0 (east) at once, sees cell 1's line and receives (its own try not counted). After the transfer
    cell 0 tries again after one sweep (4 polls) and cell 1, polling from port 3 on, reaches port 2 (west) three
    polls later: nobody waits the other out (no timeout, no back-off)."""
    p = WireParams()
    w = WireLevel(from_layout(layout.grid(2, 1, 0.1)), p, seed=3)
    inbox, stats = w.exchange(outbox(2, {(0, EAST): 1, (1, WEST): 2}), 0.0, 0.1)
    assert inbox.present[1, WEST] and inbox.present[0, EAST]
    transfer = p.select_time + byte_time(p, SCHEMA.sentence_bytes)
    assert stats.latencies.tolist() == pytest.approx([transfer, 2 * transfer + 7 * p.poll_time], abs=1e-12)
    assert stats.extra["timeouts"] == 0 and stats.dropped == 0


def test_wire_a_ring_of_waiting_senders_is_served_without_timeouts():
    """Four cells of a 2 x 2 block each send to the next round the block at t=0 (0 east, 1 north, 3 west, 2 south):
    every one waits on a neighbour that waits on another. Polling while they wait, each answers the one waiting on
    it: all four arrive with no handshake timed out, within the four transfers one after another and a few sweeps,
    far inside one timeout (a model whose waiting cells poll nobody has all four time out first)."""
    p = WireParams()
    w = WireLevel(from_layout(layout.grid(2, 2, 0.1)), p, seed=1)
    inbox, stats = w.exchange(outbox(4, {(0, EAST): 1, (1, NORTH): 2, (3, WEST): 3, (2, SOUTH): 4}), 0.0, 0.1)
    assert inbox.present[1, WEST] and inbox.present[3, SOUTH] and inbox.present[2, EAST] and inbox.present[0, NORTH]
    assert [inbox.values["value"][c, q] for c, q in ((1, WEST), (3, SOUTH), (2, EAST), (0, NORTH))] == [1, 2, 3, 4]
    transfer = p.select_time + byte_time(p, SCHEMA.sentence_bytes)
    assert stats.extra["timeouts"] == 0 and stats.dropped == 0
    assert max(stats.latencies) <= 4 * (transfer + 2 * 4 * p.poll_time) < p.cts_timeout


def test_wire_dead_link_times_out_and_drops_after_max_attempts():
    p = WireParams(max_attempts=3, cts_timeout=2e-3)  # three tries of 2 ms (not the line's 67 ms) fit in the tick
    t = from_layout(layout.grid(2, 1, 0.1)).with_faults(dead_links=[(0, EAST)])
    w = WireLevel(t, p)
    inbox, stats = w.exchange(outbox(2, {(0, EAST): 5}), 0.0, 0.1)
    assert inbox.count() == 0 and stats.extra["timeouts"] == 3 and stats.dropped == 1


def test_wire_bit_errors_are_caught_not_misread():
    p = WireParams(bit_error_rate=0.02, cts_timeout=0.05)
    t = from_layout(layout.grid(2, 1, 0.1))
    w = WireLevel(t, p, seed=5)
    delivered = corrupted = 0
    for k in range(300):
        inbox, stats = w.exchange(outbox(2, {(0, EAST): k}), k * 0.02, 0.02)
        corrupted += stats.corrupted
        if inbox.present[1, WEST]:
            delivered += 1
            if stats.undetected == 0:
                assert inbox.values["value"][1, WEST] == k
    # 72 data bits at 2%: P(no error) = 0.98^72 ~ 0.23
    assert corrupted > 150 and 30 < delivered < 120


def test_wire_queue_keeps_the_newest_and_state_persists_between_ticks():
    """At 1200 baud one sentence takes ~75 ms; ticks of 10 ms pile sentences up: with queue_limit 1 the newest
    replaces the waiting one and late arrivals carry latencies longer than a tick."""
    p = WireParams(baud=1200, cts_timeout=1.0)
    t = from_layout(layout.grid(2, 1, 0.1))
    w = WireLevel(t, p)
    got = []
    lat = []
    for k in range(40):
        inbox, stats = w.exchange(outbox(2, {(0, EAST): k}), k * 0.01, 0.01)
        if inbox.present[1, WEST]:
            got.append(int(inbox.values["value"][1, WEST]))
        lat.extend(stats.latencies.tolist())
    assert got == sorted(got) and len(got) >= 4 and got[0] == 0
    assert min(lat) > 0.01 and stats.extra["superseded"] >= 0
    assert all(b - a > 1 for a, b in zip(got, got[1:]))  # older waiting sentences were replaced


def test_wire_parameters_are_validated():
    with pytest.raises(ValueError):
        WireParams(baud=0)
    with pytest.raises(ValueError):
        WireParams(bit_error_rate=2.0)
    # a bad number the default handshake timeout is made from is named, not tripped over
    with pytest.raises(ValueError, match="bits_per_byte"):
        WireParams(bits_per_byte=4)
    with pytest.raises(ValueError, match="select_time"):
        WireParams(select_time=-1.0)
    with pytest.raises(ValueError, match="cts_timeout"):
        WireParams(cts_timeout=0.0)


def test_a_partial_sentence_carries_only_its_words_and_takes_their_time():
    """A mailbox with ``words`` sends only the marked words (labels say which): the receiver's inbox says which
    arrived, and the transfer takes the shorter sentence's bytes."""
    p = WireParams()
    w = WireLevel(from_layout(layout.grid(2, 1, 0.1)), p)
    box = outbox(2, {(0, EAST): 77})
    box.words = np.zeros((2, 4), dtype=np.int64)
    box.words[0, EAST] = 0b01  # "value" only
    inbox, stats = w.exchange(box, 0.0, 0.05)
    assert inbox.present[1, WEST] and inbox.values["value"][1, WEST] == 77
    assert inbox.words is not None and inbox.words[1, WEST] == 0b01
    short = len(SCHEMA.to_bytes({"value": 77, "hops": 1}, 0b01))
    assert short == SCHEMA.sentence_bytes - 3  # the hops word (label, type, one byte) left out
    assert stats.bytes_sent.sum() == short
    assert stats.latencies.tolist() == pytest.approx([2 * p.poll_time + p.select_time + byte_time(p, short)])
    assert SCHEMA.from_bytes(SCHEMA.to_bytes({"value": 77, "hops": 1}, 0b10), partial=True) == {"hops": 1}
    with pytest.raises(SentenceError):  # a sentence short of words is an error where all are expected
        SCHEMA.from_bytes(SCHEMA.to_bytes({"value": 77, "hops": 1}, 0b10))


def test_a_superseded_partial_sentence_hands_its_words_to_the_newer_one():
    """At 1200 baud sentences pile up; a newer partial sentence replacing a waiting one carries the words the
    waiting one carried and it does not, so no word is lost to the queue, each at the port's value when the newer one
    was queued: a word that changed since the older one (back to a value a sentence may leave unsaid) must not reach
    the neighbour as its older value."""
    p = WireParams(baud=1200, cts_timeout=1.0)
    w = WireLevel(from_layout(layout.grid(2, 1, 0.1)), p)
    heard = {}
    for k in range(60):  # 30 ticks of sentences, then 30 of silence to drain the queue
        box = outbox(2, {(0, EAST): 100 + k} if k < 30 else {})
        box.values["hops"][0, EAST] = k if k < 3 else 0  # the port's hops word: 1, 2, then back to 0 (unsaid)
        box.words = np.zeros((2, 4), dtype=np.int64)
        box.words[0, EAST] = 0b10 if k == 1 else 0b01  # tick 1 alone says hops; the others say value
        inbox, stats = w.exchange(box, k * 0.01, 0.01)
        for name, bit in (("value", 0b01), ("hops", 0b10)):
            if inbox.present[1, WEST] and inbox.words[1, WEST] & bit:
                heard[name] = int(inbox.values[name][1, WEST])
    # tick 1's hops went out with a later sentence, at the port's value then (0), and value is the last one
    assert heard["hops"] == 0 and heard["value"] == 129
    assert stats.extra["queued"] == 0
