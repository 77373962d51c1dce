"""Controllers. Distributed cell programs follow the contract of :mod:`virtual_vehicle.network.programs`.

:class:`Shuttle` passes a parcel back and forth along the array, as on the authors' prototype, with no central
computer: every cell drives its wheel 0 at ``speed`` (m/s) in the current direction; a cell at an end of the array
(it has no neighbour on that side: local knowledge) that senses the parcel starts a hop-limited flood "direction
reversed", with a sequence number one above the newest it knows, and every cell adopts the newest direction it hears.
Cells repeat what they know every ``heartbeat`` ticks, so a cell that missed a sentence (loss, corruption, a busy
link) catches up. Sequence numbers are 16-bit words; a run with more than 65535 reversals would wrap them, which this
program does not handle.
"""

from __future__ import annotations

import numpy as np

from .network.messages import Mailbox, Schema
from .network.programs import CellInputs, flood_update
from .network.sentence import WordType

EAST, NORTH, WEST, SOUTH = range(4)


class Shuttle:
    """Distributed back-and-forth transport along the cells' wheel-0 axis (east/west ports). An end cell turns the
    parcel when one of its ``trigger_sensors`` (default: sensor 0, the centre of the default layout) sees it."""

    schema = Schema.of(seq=(1, WordType.U16), direction=(2, WordType.I16), hops=(3, WordType.U8))

    def __init__(self, speed: float, hop_limit: int = 32, heartbeat: int = 10, trigger_sensors=(0,)):
        if not speed > 0:
            raise ValueError("speed must be positive (m/s)")
        self.speed = float(speed)
        self.hop_limit = int(hop_limit)
        self.heartbeat = max(1, int(heartbeat))
        self.trigger_sensors = tuple(int(k) for k in trigger_sensors)

    def init(self, n, ports, config):
        return {"seq": np.zeros(n, dtype=np.int64), "direction": np.ones(n, dtype=np.int64),
                "hops": np.zeros(n, dtype=np.int64), "tick": np.zeros(n, dtype=np.int64)}

    def step(self, state, inputs: CellInputs):
        inbox = inputs.inbox
        n, P = inbox.present.shape
        seq, direction, hops, adopted = flood_update(
            state["seq"], state["direction"], state["hops"], inbox.values["seq"], inbox.values["direction"],
            inbox.values["hops"], inbox.present, self.hop_limit)
        sensed = inputs.sensors[:, list(self.trigger_sensors)].any(axis=1)
        east_end = ~inputs.connected[:, EAST]
        west_end = ~inputs.connected[:, WEST]
        turn = sensed & ((east_end & (direction > 0)) | (west_end & (direction < 0)))
        seq = np.where(turn, seq + 1, seq) % 65536
        direction = np.where(turn, -direction, direction)
        hops = np.where(turn, 0, hops)
        tick = state["tick"] + 1
        send = (adopted | turn | (tick % self.heartbeat == 0)) & (hops < self.hop_limit)
        out = Mailbox.broadcast(self.schema, send, P, seq=seq, direction=direction, hops=hops)
        wheels = np.zeros((n, 2))
        wheels[:, 0] = self.speed * direction
        return {"seq": seq, "direction": direction, "hops": hops, "tick": tick}, out, wheels


class FollowField:
    """Each cell commands its own constant wheel speeds (given at installation, m/s) and sends nothing: a constant
    field expressed as a cell program, so that motor-driven wheels can be stepped like any controller's."""

    schema = Schema(())

    def __init__(self, wheel_speeds: np.ndarray):
        self.wheel_speeds = np.asarray(wheel_speeds, dtype=float)

    def init(self, n, ports, config):
        return {}

    def step(self, state, inputs: CellInputs):
        n, P = inputs.connected.shape
        return state, Mailbox.empty(self.schema, n, P), self.wheel_speeds.copy()
