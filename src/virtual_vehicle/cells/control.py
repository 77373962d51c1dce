"""Controllers. Distributed cell programs follow the contract of :mod:`virtual_vehicle.cells.network.programs`.

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

from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import CellInputs, flood_update
from virtual_vehicle.cells.network.sentence import WordType

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
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        return {"seq": np.zeros(n, dtype=np.int64), "direction": np.ones(n, dtype=np.int64),
                "hops": np.zeros(n, dtype=np.int64), "tick": np.zeros(n, dtype=np.int64)}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
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
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        return {}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
        n, P = inputs.connected.shape
        return state, Mailbox.empty(self.schema, n, P), self.wheel_speeds.copy()


class PoseControl:
    """Central closed loop from the cells' own sensors: drive each parcel to a target pose (issue: the virtual
    vehicle, closed loop).

    Every tick the controller reads all presence sensors, estimates each parcel's pose from the pattern
    (:mod:`virtual_vehicle.cells.estimate`, seeded by the last estimate moved by the last command), asks for the twist
    ``gain * error`` (position error in m, heading error in rad, wrapped to the parcel's symmetry), limited to
    ``max_speed`` (m/s at any supporting wheel), and gives the cells under the estimated footprint the wheel speeds
    of that twist (:func:`~virtual_vehicle.cells.design.twist_design`: the steady state of the viscous and stick-slip
    laws). Within ``tolerance`` (m, rad) of its target a parcel's wheels stop. With ``waypoints`` (per parcel, a list
    of poses) a parcel is transported along a path: it heads for each waypoint in turn and passes it once its
    estimate is within ``pass_radius`` (m) of it. It knows each parcel's outline and where it was placed
    (``starts``: the poses a loader put them at), nothing of its motion since. ``retargets``: (t, parcel index,
    pose) changes of target, each from the first tick at or after t (s) on.

    A central controller in the cell-program shape: it sends no sentences and reads every cell's sensors.
    """

    schema = Schema(())

    def __init__(self, cells, sensor_points, specs, starts, targets, *, gain: float = 2.0, max_speed: float = 0.2,
                 tolerance=(5e-4, np.radians(0.2)), period: float = 0.01, symmetry: list[int] | None = None,
                 waypoints=None, pass_radius: float = 0.01, retargets=()):
        from virtual_vehicle.cells.estimate import sensor_spacing

        self.cells = cells
        self.points = np.asarray(sensor_points, dtype=float)
        self.specs = list(specs)
        self.starts = [np.asarray(s, dtype=float)[:3] for s in starts]
        self.targets = [np.asarray(t, dtype=float)[:3] for t in targets]
        if len(self.targets) != len(self.specs):
            raise ValueError("one target pose per parcel")
        self.gain = float(gain)
        self.max_speed = float(max_speed)
        self.tolerance = tuple(float(v) for v in tolerance)
        self.period = float(period)
        self.spacing = sensor_spacing(self.points)
        self.symmetry = symmetry or [rotational_symmetry(s) for s in self.specs]
        self.waypoints = [np.asarray(w, dtype=float).reshape(-1, 3) for w in (waypoints or [[]] * len(self.specs))]
        if len(self.waypoints) != len(self.specs):
            raise ValueError("one list of waypoints per parcel")
        self.pass_radius = float(pass_radius)
        self.retargets = sorted(retargets, key=lambda r: r[0])

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        return {"estimates": [s.copy() for s in self.starts], "twists": [np.zeros(3) for _ in self.specs],
                "wrong": [0] * len(self.specs), "leg": [0] * len(self.specs)}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
        from virtual_vehicle.cells.design import twist_design
        from virtual_vehicle.cells.estimate import estimate_pose

        n, P = inputs.connected.shape
        lit = np.asarray(inputs.sensors, dtype=bool)
        wheels = np.zeros((n, 2))
        estimates, twists, wrong, legs = [], [], [], []
        targets = list(targets_at(self.targets, self.retargets, inputs.t)) if self.retargets else self.targets
        for spec, est, tw, target, sym, way, leg in zip(self.specs, state["estimates"], state["twists"], targets,
                                                        self.symmetry, self.waypoints, state["leg"]):
            guess = est + self.period * tw  # prediction from the last command
            pose, bad = estimate_pose(spec, self.points, lit, guess, spacing=self.spacing)
            while leg < len(way) and np.hypot(*(way[leg, :2] - pose[:2])) < self.pass_radius:
                leg += 1  # waypoint passed
            if leg < len(way):
                target = way[leg]
            err = target - pose
            period_sym = 2 * np.pi / sym
            err[2] = (err[2] + period_sym / 2) % period_sym - period_sym / 2
            if np.hypot(err[0], err[1]) < self.tolerance[0] and abs(err[2]) < self.tolerance[1]:
                twist = np.zeros(3)
            else:
                twist = self.gain * err
            state_now = np.array([*pose, 0.0, 0.0, 0.0])
            design = twist_design(self.cells, spec, state_now, twist, vmax=self.max_speed)
            wheels[design.support] = design.wheel_speeds[design.support]
            estimates.append(pose)
            twists.append(design.achieved)
            wrong.append(bad)
            legs.append(leg)
        return ({"estimates": estimates, "twists": twists, "wrong": wrong, "leg": legs},
                Mailbox.empty(self.schema, n, P), wheels)


def targets_at(targets, retargets, t: float) -> np.ndarray:
    """(P, 3) the target poses (m, m, rad) in force at time ``t`` (s): ``targets`` as changed by each
    (t_r, parcel index, pose) of ``retargets`` with t_r <= t, in their order (a tick at t_r sees its change)."""
    out = np.array(targets, dtype=float).reshape(-1, 3)
    for t_r, j, pose in retargets:
        if t_r <= t + 1e-9:  # within rounding of the tick's k * period
            out[j] = np.asarray(pose, dtype=float)[:3]
    return out


def rotational_symmetry(spec) -> int:
    """How many times a turn maps the outline onto itself about its centre of mass (1, 2 or 4 checked)."""
    for k in (4, 2):
        c, s = np.cos(2 * np.pi / k), np.sin(2 * np.pi / k)
        turned = spec.footprint @ np.array([[c, s], [-s, c]])
        if all(np.min(np.hypot(*(spec.footprint - p).T)) < 1e-9 * max(spec.radius, 1e-12) for p in turned):
            return k
    return 1


def pose_error(spec, pose, target) -> tuple[float, float]:
    """Distance (m) and heading error (rad, wrapped to the outline's rotational symmetry) from ``pose`` to
    ``target``."""
    sym = rotational_symmetry(spec)
    period = 2 * np.pi / sym
    dth = (float(target[2]) - float(pose[2]) + period / 2) % period - period / 2
    return float(np.hypot(target[0] - pose[0], target[1] - pose[1])), abs(dth)


def path_deviation(states, path) -> float:
    """Largest distance (m) of the centre of mass from the polyline ``path`` ((k, 2) or (k, 3), m)."""
    P = np.asarray(path, dtype=float)[:, :2]
    X = np.asarray(states, dtype=float)[:, :2]
    a, b = P[:-1], P[1:]
    e = b - a
    L2 = np.maximum(np.einsum("ij,ij->i", e, e), 1e-300)
    t = np.clip(np.einsum("pkj,kj->pk", X[:, None, :] - a[None], e) / L2, 0.0, 1.0)
    d = np.hypot(*(X[:, None, :] - (a[None] + t[..., None] * e[None])).transpose(2, 0, 1))
    return float(d.min(axis=1).max())


def settled_at(spec, times, states, target, position_tol: float = 5e-3, heading_tol: float = np.radians(2.0)):
    """First sample time (s) from which the parcel stays within ``position_tol`` (m) and ``heading_tol`` (rad) of
    ``target``; None if it never does."""
    ok = np.array([all(np.less_equal(pose_error(spec, y, target), (position_tol, heading_tol))) for y in states])
    if not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return float(times[bad[-1] + 1]) if len(bad) else float(times[0])


class Diffusion:
    """The diffusion law of the authors' earlier work: each cell's wheel speeds relax toward its neighbours', the
    discrete heat equation on the cell network,

        v_i <- v_i + alpha * sum_{j in N(i)} (v_j - v_i),

    with ``alpha`` (per tick; stable for alpha <= 1 / (number of ports)) and the neighbours' speeds as last heard
    (trusted for ``max_age`` ticks, so a slow or lossy link leaves that neighbour out rather than freezing its
    value). Cells with config ``fixed`` hold config ``speed`` ((n, 2) m/s): sources and sinks (Dirichlet);
    a missing neighbour adds nothing (no flux, Neumann). Initial speeds: config ``speed``. Speeds travel as F32
    words, so the scheme is exact to single precision in transit.
    """

    schema = Schema.of(v0=(1, WordType.F32), v1=(2, WordType.F32))

    def __init__(self, alpha: float, max_age: int = 0):
        if not 0 < alpha:
            raise ValueError("alpha must be positive")
        self.alpha = float(alpha)
        self.max_age = int(max_age)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        v = np.asarray(config.get("speed", np.zeros((n, 2))), dtype=float).reshape(n, 2).copy()
        return {"v": v, "heard": np.zeros((n, ports, 2)),
                "age": np.full((n, ports), np.iinfo(np.int32).max, dtype=np.int64), "sent": False}

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        got = np.stack([inbox.values["v0"], inbox.values["v1"]], axis=-1).astype(float)
        heard = np.where(inbox.present[..., None], got, state["heard"])
        age = np.where(inbox.present, 0, np.minimum(state["age"] + 1, np.iinfo(np.int32).max))
        trusted = (age <= self.max_age) & inputs.connected
        v = state["v"]
        if state["sent"]:  # from the second tick on, neighbours' speeds are known
            flux = np.where(trusted[..., None], heard - v[:, None, :], 0.0).sum(axis=1)
            v = v + self.alpha * flux
        fixed = np.asarray(inputs.config.get("fixed", np.zeros(n, bool)), dtype=bool)
        if fixed.any():
            v = np.where(fixed[:, None], np.asarray(inputs.config["speed"], dtype=float).reshape(n, 2), v)
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, v0=v[:, 0], v1=v[:, 1])
        return {"v": v, "heard": heard, "age": age, "sent": True}, out, v.copy()
