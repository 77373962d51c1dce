"""What the distributed sorter (:class:`~virtual_vehicle.cells.sorting.Sorter`) and its central counterpart
(:class:`~virtual_vehicle.cells.sorting.CentralSorter`) both apply, written once: the goal a label encodes, when a
sequenced parcel is due, a new vehicle's id, what a hop costs in the exit gradients, the wheel command that moves a
parcel through a port, and how long a parcel backs off. The small rules are ``register_jitable``: plain Python when
the central sorter calls them, compiled into the cells' step when it does. Units: SI."""

from __future__ import annotations

import numpy as np
from numba.extending import register_jitable

from virtual_vehicle.cells.network.sentence import WordType, wire_size

MAX_EXITS = 4
PARK = MAX_EXITS - 1
"""In a sequenced run (parcels with sequence numbers), gradient PARK leads to a free parking cell, not to exit 3."""
NONE = -1
BIG = 1 << 20  # above any direction key
HUGE = 1 << 40  # above any vehicle id
ENTRY = -2  # the "ex" word of an entry cell


def decode_goal(goal):
    """(exit, sequence number) of goal words: ``exit + 4 (sequence + 1)``; sequence -1 for an unsequenced parcel."""
    return split_goal(np.asarray(goal, dtype=np.int64))


def encode_goal(exit: int, sequence: int | None) -> int:
    """The label a reader at the entry sees: the exit, and the sequence number when the parcel has one."""
    return int(exit) + (0 if sequence is None else 4 * (int(sequence) + 1))


@register_jitable
def split_goal(goal):
    """(exit, sequence number) of a non-negative goal word (or an array of them): see :func:`decode_goal`."""
    return goal % 4, goal // 4 - 1


@register_jitable
def due(seq, nxt):
    """Whether a parcel with sequence number ``seq`` (-1: none) may head for its exit when ``nxt`` is due next:
    else it waits on a parking cell."""
    return seq < 0 or seq <= nxt


ID_TICK = 1024
"""A vehicle id's tick unit: ``id // ID_TICK`` is the tick it was made (:func:`vehicle_id`)."""


@register_jitable
def vehicle_id(tick, number):
    """A new vehicle's id: the tick it was made (so smaller ids are older vehicles, which go first at a merge),
    times :data:`ID_TICK`, plus the number of the cell that made it modulo :data:`ID_TICK` (so two entries'
    vehicles differ)."""
    return tick * ID_TICK + number % ID_TICK


@register_jitable
def heartbeat_due(tick, number, heartbeat):
    """Whether the cell with installation number ``number`` sends everything at ``tick`` (its heartbeat, every
    ``heartbeat`` ticks, staggered by the number so that the cells do not all send at once). Scalars or arrays."""
    return (tick + number) % heartbeat == 0


def tick_of(t: float, period: float) -> int:
    """The control tick at time ``t`` (s) of a program with control period ``period`` (s; 0: always tick 0)."""
    return int(round(t / period)) if period else 0


@register_jitable
def hop_cost(linked, exit_id, edge_cost):
    """Hops a step into a cell counts in the exit gradients: 1, and ``edge_cost`` more on the array's edge (a cell
    not ``linked`` on every side) unless it is an exit cell (``exit_id`` >= 0), so parcels travel inside the array
    and meet the edge only at their exit. Scalars or arrays alike."""
    return 1 + edge_cost * (1 - (linked | (exit_id >= 0)))


@register_jitable
def opposite(port, P):
    """The port straight across from ``port`` on a cell with ``P`` ports (4: square, 6: hexagonal): behind a vehicle
    heading out through ``port``, and the port a neighbour on ``port`` hears this cell through."""
    return (port + P // 2) % P


@register_jitable
def left_of(port, P):
    """The next port counter-clockwise from ``port`` (90 degrees on a square cell, 60 on a hexagonal one)."""
    return (port + 1) % P


@register_jitable
def right_of(port, P):
    """The next port clockwise from ``port``."""
    return (port + P - 1) % P


@register_jitable
def into_lane(side, out, P):
    """The port that moves a vehicle away from ``side`` into an exit lane whose way out is port ``out``: ``side``
    mirrored across the way out (on a square cell the port across from ``side``, straight sideways; on a hexagonal
    one, whose sides beside the way out lie 60 degrees off it, the port 60 degrees off it on the other side, so the
    vehicle moves sideways while it goes on toward the edge)."""
    return (2 * out + P - side) % P


@register_jitable
def hop_bits(P):
    """Bits of a hop count in the words that pack one per port (``blk``) or a hop count and a port (``stop``): 6 on
    a square cell (four 6-bit fields in 24 bits; a port in the stop byte's top two bits), 5 on a hexagonal one
    (six fields in 30 bits of a 32-bit word; a port in the top three bits), so ``reach`` is at most 30 there.
    The field's largest value, ``2**bits - 1``, means none."""
    return 6 if P <= 4 else 5


@register_jitable
def ack_bits(P):
    """The ``ack`` word's layout (a 16-bit word) on a cell with ``P`` ports: (bits of the run of held cells ahead,
    bits of the port the hold was asked through plus one); the bits above them name the cell's ports that lead to a
    dead neighbour, one a port: 8 + 4 + 4 on a square cell, 7 + 3 + 6 on a hexagonal one (a run is at most
    ``gap + 1 + lead`` cells, below 64, so 127 leaves room)."""
    return (8, 4) if P <= 4 else (7, 3)


@register_jitable
def heading(port, P):
    """The unit velocity (x, y in the cell frame: along wheel 0's drive direction and across it) that moves a
    parcel out through ``port`` of a cell with ``P`` ports: on a square cell one wheel (:func:`drive`), on a
    hexagonal one port q at ``60 q`` degrees (its omni wheels make any planar surface velocity)."""
    if P == 4:
        axis, sign = drive(port)
        return (sign, 0.0) if axis == 0 else (0.0, sign)
    return _HEX_HEADING[port]


_HEX_HEADING = ((1.0, 0.0), (0.5, 0.8660254037844386), (-0.5, 0.8660254037844386), (-1.0, 0.0),
                (-0.5, -0.8660254037844386), (0.5, -0.8660254037844386))
"""(cos, sin) of 0, 60, ..., 300 degrees: a hexagonal cell's ports (cos 60 degrees exactly 0.5, sin sqrt(3)/2)."""


@register_jitable
def drive(port):
    """The wheel command that moves a parcel out through ``port`` (0: +x, 1: +y, 2: -x, 3: -y): the drive axis (0:
    x, 1: y) and the sign of the wheel surface speed along it."""
    return port % 2, 1.0 if port < 2 else -1.0


def back_off_ticks(distance: float, speed: float, period: float) -> int:
    """Ticks a parcel backs off for when it meets an older one head on: long enough to travel ``distance`` (m; the
    gap and one more cell) at ``speed`` (m/s), ticking every ``period`` (s)."""
    return int(np.ceil(distance / (speed * period)))


def lead_cells(speed: float, pitch: float, gap: int, period: float, ports: int, seconds_per_byte: float) -> int:
    """Cells a vehicle asks beyond ``gap + 1`` so that it rides on while each step's run of held cells is told back
    (:class:`~virtual_vehicle.cells.sorting.Sorter`'s ``lead``), on links that carry a byte in ``seconds_per_byte``
    (s; 0 for ideal rounds, where a word travels a hop a tick): a change crosses a hop in :func:`hop_seconds`
    (``ports`` the cell's ports, ``period`` the control period, s); a step's run is told back after ``2 (gap + 1)``
    hops, while the vehicle travels at ``speed`` (m/s); the first cell of that travel is the slack ``gap + 1``
    already leaves (a vehicle moves on a run of ``gap``). Units: m, s."""
    travelled = speed * 2 * (gap + 1) * hop_seconds(period, ports, seconds_per_byte) / pitch
    return max(0, int(np.ceil(travelled - 1e-9)) - 1) if seconds_per_byte > 0 else 0


def hop_seconds(period: float, ports: int, seconds_per_byte: float) -> float:
    """The time a change takes to cross a hop (s) on links that carry a byte in ``seconds_per_byte`` (s): the cell
    says its changes on each of its ``ports`` and hears theirs on the one serial port they share (2 ``ports``
    sentences of one 32-bit word, 10 bytes each: :func:`~virtual_vehicle.cells.network.sentence.wire_size`) and
    the neighbour ticks (``period``, s)."""
    return 2 * ports * wire_size([WordType.I32]) * seconds_per_byte + period


def lane_hold_ticks(reach: int, period: float, ports: int, seconds_per_byte: float) -> int:
    """Ticks a vehicle stands at its exit lane's far side (:class:`~virtual_vehicle.cells.sorting.Sorter`'s
    ``lane_hold``) on links that carry a byte in ``seconds_per_byte`` (s; 0 for ideal rounds: none): a withdrawn
    proposal to move into the lane is forgotten once it has run ``reach`` hops (one hop an exchange,
    :func:`hop_seconds`), and then the cells agree on the turn out; half as long again, as a margin (at the
    junction at 9600 baud a lone parcel's turn came 0.74 s after the stop, against 0.75 s for ``reach`` hops: held
    for that long it was let go just before its turn, and came out 0.2-0.7 s later than held as long as it takes);
    ``period`` the control period (s)."""
    if seconds_per_byte <= 0:
        return 0
    return int(np.ceil(1.5 * reach * hop_seconds(period, ports, seconds_per_byte) / period - 1e-9))


HEARTBEAT_SHARE = 0.1
"""The most of a cell's line its heartbeats take, by default, on a link slow enough that one second's heartbeats
would take more (:func:`heartbeat_seconds`)."""


def heartbeat_seconds(ports: int, sentence_bytes: int, seconds_per_byte: float, floor: float = 1.0) -> float:
    """The sorter's default heartbeat (s): ``floor``, or longer where a cell's heartbeats (a whole sentence of
    ``sentence_bytes`` said and one heard on each of its ``ports``, all on the one serial port it shares between
    them) would take more than :data:`HEARTBEAT_SHARE` of its line at ``seconds_per_byte`` (s; 0 on ideal rounds,
    which have no line). A heartbeat repairs a word lost on the way; on a slow line it also delays every change
    queued behind it, and a line that is nine tenths busy makes each sentence wait several times its own length.
    At 9600 baud, 4 ports and the sorter's 63-byte sentence: 5.25 s; at 115 200 baud: 1 s. Units: s."""
    return max(floor, 2 * ports * sentence_bytes * seconds_per_byte / HEARTBEAT_SHARE)


def pack(values, bits: int = 8) -> np.ndarray:
    """Small non-negative integers (n, k), each below 2**bits, packed into one signed 32-bit word per row."""
    v = np.asarray(values, dtype=np.int64)
    word = sum(v[:, q] << (bits * q) for q in range(v.shape[1]))
    return np.where(word >= 1 << 31, word - (1 << 32), word)


@register_jitable
def unpack(words, q, bits=8):
    """Field q of words packed by :func:`pack` (one word or an array of them)."""
    return ((words & 0xFFFFFFFF) >> (bits * q)) & ((1 << bits) - 1)


@register_jitable
def direction_key(dist, same, port, hops):
    """Direction proposals ordered by distance to the goal, then keeping the current direction (``same`` 1), then
    port; ``hops`` (below 64) from the cell that proposed it."""
    return ((dist * 2 + (1 - same)) * 8 + port) * 64 + hops
