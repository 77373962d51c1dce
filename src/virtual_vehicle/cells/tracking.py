"""Distributed closed loop: the cells under each parcel track its pose together and drive it to a target pose, or
along waypoints (paper Section 1: every parcel rides its own virtual vehicle, made of whichever cells are under it).

Units: SI (m, rad, s; wheel speeds in m/s).

Every rule reads only the cell's own row (:mod:`virtual_vehicle.cells.network.programs` contract): its sensors, its
state, its configuration, set when it was installed (``position``: where its centre is; ``sensor_points``: where its
sensors are; ``directions``: its wheels' drive directions), and what its neighbours said last tick. Like the central
controller (:class:`~virtual_vehicle.cells.control.PoseControl`), every cell holds the job list: for parcel k, its
outline, the pose the loader puts it down at, its target and its waypoints. No cell knows where a parcel is now.

- *Record*: a cell that sees a parcel (any sensor lit) holds a record: the job k, its estimate of the parcel's pose
  and the waypoint leg. A cell that starts seeing a parcel adopts the record of the neighbour whose estimated
  footprint covers its lit sensors best; when no neighbour's does (within a sensor spacing), the parcel has just
  been put down and the cell takes the job whose loading pose covers its lit sensors. A dark cell next to a cell
  that sees the parcel holds the same record as a watcher: its dark sensors also tell where the parcel is not, but
  it does not drive. Any other cell that sees nothing drops its record. So the record travels with the parcel,
  handed from cell to cell.
- *Estimate*: every tick each cell (1) moves its estimate by the twist it commanded last tick, (2) averages it
  with the estimates of its neighbours that hold the same job (consensus), (3) takes one gradient step on its own
  share of the central estimator's cost (:mod:`virtual_vehicle.cells.estimate`): each of its own lit sensors pulls the
  estimated footprint over it, each dark one pushes it away (a softplus of the sensor's signed margin over a
  softness of a quarter of the sensor spacing, so a sensor deep inside or far outside says nothing). Together this
  is distributed gradient descent on the sum of the cells' shares, the cost the central estimator minimises, so the
  cells agree on one estimate that follows the parcel.
- *Control*: twist = ``gain`` times (target - estimate) (heading error wrapped to the outline's rotational symmetry;
  zero within ``tolerance``), scaled so that ``|v| + |omega| R <= max_speed`` (R the outline's radius: a bound on
  the speed of every point of the parcel that each cell computes alone, where the central controller scales by the
  fastest wheel under the parcel). Each cell drives the rigid-body velocity of that twist at its own centre,
  projected on its wheels: the twist design of :func:`~virtual_vehicle.cells.design.twist_design`, cell by cell.
  With waypoints, a cell passes a leg once its estimate is within ``pass_radius`` of the waypoint and adopts the
  furthest leg a neighbour of the same job has passed.
"""

from __future__ import annotations

import numpy as np

from virtual_vehicle.cells.control import rotational_symmetry, targets_at
from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.model.parcel import pose_margins

_NONE = -1
_FD = 1e-6  # finite-difference step of the margins' gradient, in units of the pose scale (m, and m at radius R)


def _wrap(a, period=2 * np.pi):
    return (a + period / 2) % period - period / 2


class DistributedPose:
    """Distributed pose control (see the module notes).

    Args:
        specs: each job's parcel outline (:class:`~virtual_vehicle.model.parcel.ParcelSpec`).
        starts: each job's loading pose (x, y, theta), m, m, rad.
        targets: each job's target pose.
        gain: 1/s. max_speed: m/s. tolerance: (m, rad) within which a cell stops driving.
        period: the control period, s.
        waypoints: per job, poses to pass on the way (optional). pass_radius: m.
        spacing: the sensor spacing, m (sets the estimator's softness).
        step: the estimator's gradient step per tick, in sensor softnesses (a fraction of a quarter of the spacing).
        max_age: ticks a neighbour's record is trusted after it was last heard (0 on ideal rounds).
        retargets: (t, job, pose) changes of target, each from the first tick at or after t (s) on.
    """

    schema = Schema.of(job=(1, WordType.I16), x=(2, WordType.F32), y=(3, WordType.F32), th=(4, WordType.F32),
                       leg=(5, WordType.U8), sees=(6, WordType.BOOL))

    def __init__(self, specs, starts, targets, *, spacing: float, gain: float = 2.0, max_speed: float = 0.2,
                 tolerance=(5e-4, np.radians(0.2)), period: float = 0.01, waypoints=None, pass_radius: float = 0.01,
                 step: float = 0.5, max_age: int = 0, retargets=()):
        self.specs = list(specs)
        self.starts = np.array([np.asarray(s, dtype=float)[:3] for s in starts]).reshape(-1, 3)
        self.targets = np.array([np.asarray(t, dtype=float)[:3] for t in targets]).reshape(-1, 3)
        if not len(self.specs) == len(self.starts) == len(self.targets):
            raise ValueError("one loading pose and one target pose per parcel")
        if len(self.specs) > 32767:
            raise ValueError("at most 32767 jobs (the job travels as an I16 word)")
        if not spacing > 0:
            raise ValueError("spacing must be positive (m)")
        self.gain, self.max_speed, self.period = float(gain), float(max_speed), float(period)
        self.tolerance = tuple(float(v) for v in tolerance)
        self.waypoints = [np.asarray(w, dtype=float).reshape(-1, 3) for w in (waypoints or [[]] * len(self.specs))]
        if len(self.waypoints) != len(self.specs):
            raise ValueError("one list of waypoints per parcel")
        if any(len(w) > 254 for w in self.waypoints):
            raise ValueError("at most 254 waypoints a parcel (the leg travels as a U8 word)")
        self.pass_radius = float(pass_radius)
        self.softness = spacing / 4
        self.gradient_step = float(step)
        self.max_age = int(max_age)
        self.radius = np.array([max(s.radius, 1e-9) for s in self.specs])
        self.symmetry = np.array([rotational_symmetry(s) for s in self.specs])
        self.retargets = sorted(retargets, key=lambda r: r[0])

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each (see
        :class:`~virtual_vehicle.cells.network.programs.CellProgram`)."""
        return {"job": np.full(n, _NONE, dtype=np.int64), "est": np.zeros((n, 3)), "twist": np.zeros((n, 3)),
                "leg": np.zeros(n, dtype=np.int64),
                "heard": {f.name: np.zeros((n, ports)) for f in self.schema.fields},
                "age": np.full((n, ports), np.iinfo(np.int32).max, dtype=np.int64)}

    # ------------------------------------------------------------------ the rules, each over every cell at once

    def step(self, state, inputs: CellInputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds (m/s
        along each drive direction); see :class:`~virtual_vehicle.cells.network.programs.CellProgram`."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        cfg = inputs.config
        points = np.asarray(cfg["sensor_points"], dtype=float).reshape(n, -1, 2)
        lit = np.asarray(inputs.sensors, dtype=bool).reshape(n, -1)
        targets = targets_at(self.targets, self.retargets, inputs.t) if self.retargets else self.targets
        heard = {k: np.where(inbox.present, inbox.values[k].astype(float), v) for k, v in state["heard"].items()}
        age = np.where(inbox.present, 0, np.minimum(state["age"] + 1, np.iinfo(np.int32).max))
        trusted = (age <= self.max_age) & inputs.connected
        njob = np.where(trusted, heard["job"], _NONE).astype(np.int64)
        nleg = heard["leg"].astype(np.int64)
        npose = np.stack([heard["x"], heard["y"], heard["th"]], axis=-1)  # (n, P, 3) as they were sent
        for j in np.unique(njob[njob >= 0]):  # moved since, by the twist each neighbour drove (from its record)
            at = njob == j
            npose[at] += ((age[at] + 1) * self.period)[:, None] * self._twist(j, npose[at], nleg[at].copy(),
                                                                                        targets)
        sees = lit.any(axis=1)
        centroid = np.where(lit[..., None], points, 0.0).sum(axis=1) / np.maximum(lit.sum(axis=1), 1)[:, None]

        # -- record: keep, adopt a neighbour's, or start from the job list; drop when nothing is seen
        job, est, leg = state["job"].copy(), state["est"].copy(), state["leg"].copy()
        est += self.period * state["twist"]  # predicted: moved by the twist driven since the last tick
        by_seer = (njob >= 0) & (heard["sees"] > 0)
        watched = (by_seer & (njob == job[:, None])).any(axis=1)  # a neighbour under the same parcel
        job[~sees & ~watched] = _NONE
        new = job == _NONE
        if new.any():  # seeing cells take a neighbour's record or a job; a dark cell watches a seeing neighbour's
            self._adopt(new & sees, job, est, leg, njob, npose, nleg, centroid, fresh=True)
            self._adopt(new & ~sees, job, est, leg, np.where(by_seer, njob, _NONE), npose, nleg,
                        np.asarray(cfg["position"], dtype=float), fresh=False)
        held = job >= 0

        # -- estimate: agree, correct
        same = (njob == job[:, None]) & held[:, None] & (age == 0)  # agree with what arrived this tick
        if same.any():
            k = same.sum(axis=1)
            d = np.where(same[..., None], npose - est[:, None, :], 0.0)
            d[..., 2] = np.where(same, _wrap(d[..., 2]), 0.0)
            est += d.sum(axis=1) / (1 + k)[:, None]  # the mean of its own and its neighbours' estimates
            leg = np.maximum(leg, np.where(same, nleg, 0).max(axis=1))
        for j in np.unique(job[held]):
            rows = np.flatnonzero(job == j)
            est[rows] -= self._descent(j, est[rows], points[rows], lit[rows])
        est[held, 2] = _wrap(est[held, 2])

        # -- control: the twist toward the target (or the next waypoint), driven at the cell's own centre
        wheels = np.zeros((n, 2))
        twist = np.zeros((n, 3))
        for j in np.unique(job[held]):
            rows = np.flatnonzero(job == j)
            lg = leg[rows]
            twist[rows] = self._twist(j, est[rows], lg, targets)
            leg[rows] = lg
            r = np.asarray(cfg["position"], dtype=float)[rows] - est[rows, :2]
            v = twist[rows, :2] + twist[rows, 2:3] * np.column_stack([-r[:, 1], r[:, 0]])  # rigid-body velocity here
            wheels[rows] = np.einsum("ij,ikj->ik", v, np.asarray(cfg["directions"], dtype=float)[rows])
        wheels[~sees] = 0.0  # a watching cell is not under the parcel
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, job=job, x=est[:, 0], y=est[:, 1], th=est[:, 2],
                                leg=np.minimum(leg, 255), sees=sees)
        return ({"job": job, "est": est, "twist": twist, "leg": leg, "heard": heard, "age": age}, out, wheels)

    def _twist(self, j: int, est: np.ndarray, legs: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(m, 3) the twist (m/s, m/s, rad/s) cells holding job ``j`` with estimates ``est`` ((m, 3)) drive toward
        ``targets[j]``, passing waypoints on the way (``legs`` is advanced in place)."""
        while True:  # legs passed by this estimate
            goal = self._goals(j, legs, targets)
            passed = (legs < len(self.waypoints[j])) & (np.hypot(*(goal[:, :2] - est[:, :2]).T) < self.pass_radius)
            if not passed.any():
                break
            legs[passed] += 1
        err = goal - est
        err[:, 2] = _wrap(err[:, 2], 2 * np.pi / self.symmetry[j])
        done = (np.hypot(err[:, 0], err[:, 1]) < self.tolerance[0]) & (np.abs(err[:, 2]) < self.tolerance[1])
        tw = np.where(done[:, None], 0.0, self.gain * err)
        peak = np.hypot(tw[:, 0], tw[:, 1]) + np.abs(tw[:, 2]) * self.radius[j]
        return tw * np.minimum(1.0, self.max_speed / np.maximum(peak, 1e-300))[:, None]

    def _goals(self, j: int, legs: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(m, 3) where job ``j`` heads for, for cells on waypoint legs ``legs``: the waypoint, or the target."""
        way = self.waypoints[j]
        if not len(way):
            return np.tile(targets[j], (len(legs), 1))
        return np.where((legs < len(way))[:, None], way[np.minimum(legs, len(way) - 1)], targets[j])

    def _adopt(self, new, job, est, leg, njob, npose, nleg, centroid, fresh: bool) -> None:
        """Records (in place) for the cells ``new`` that hold none: the neighbour's record whose footprint covers
        ``centroid`` best, else (with ``fresh``) the job whose loading pose covers it."""
        rows = np.flatnonzero(new)
        best = np.full(len(rows), -np.inf)
        for j in np.unique(njob[rows][njob[rows] >= 0]):  # the neighbour whose estimate covers it best
            m = np.where(njob[rows] == j, pose_margins(self.specs[j], npose[rows], centroid[rows, None, :]), -np.inf)
            port = np.argmax(m, axis=1)
            better = m[np.arange(len(rows)), port] > best
            best = np.where(better, m[np.arange(len(rows)), port], best)
            sel = rows[better]
            job[sel] = j
            est[sel] = npose[sel, port[better]]
            leg[sel] = nleg[sel, port[better]]
        put_down = best < -4 * self.softness  # no neighbour's parcel covers it: a parcel just put down
        if fresh and put_down.any():
            r = rows[put_down]
            m = np.stack([pose_margins(s, p, centroid[r]) for s, p in zip(self.specs, self.starts)], axis=1)
            k = np.argmax(m, axis=1)
            ok = m[np.arange(len(r)), k] > -4 * self.softness
            job[r] = np.where(ok, k, _NONE)
            est[r] = self.starts[k]
            leg[r] = 0

    def _descent(self, j: int, est: np.ndarray, points: np.ndarray, lit: np.ndarray) -> np.ndarray:
        """One gradient step (m, m, rad) of each cell's own share of the estimator's cost at its estimate ``est``
        ((m, 3)), from its sensors at ``points`` ((m, S, 2)) reading ``lit`` ((m, S))."""
        spec, s, R = self.specs[j], self.softness, self.radius[j]
        scale = np.array([1.0, 1.0, 1.0 / R])  # the heading in metres at the outline's radius
        m0 = pose_margins(spec, est[:, None, :], points)
        sign = np.where(lit, -1.0, 1.0)  # lit: pull inside (m > 0); dark: push outside
        weight = sign / (1.0 + np.exp(-np.clip(sign * m0 / s, -50, 50)))  # d softplus(sign m / s) / d(m / s)
        grad = np.zeros_like(est)
        for k in range(3):
            bump = np.zeros(3)
            bump[k] = _FD * scale[k]
            dm = (pose_margins(spec, (est + bump)[:, None, :], points) - m0) / _FD  # d m / d(pose in metres)
            grad[:, k] = np.sum(weight * dm, axis=1)
        return self.gradient_step * s * grad * scale
