"""Reinforcement-learning environments over the simulator (install the ``rl`` extra: gymnasium, pettingzoo).

* :class:`ArrayEnv` (Gymnasium): one central controller. Observation: the cells' binary sensor pattern and/or
  the parcels' states; action: every wheel's surface speed, or a twist per parcel (turned into wheel speeds under
  that parcel, :func:`~virtual_vehicle.cells.design.twist_design`).
* :class:`CellsEnv` (PettingZoo, parallel API): every cell is an agent that sees only its own sensors, its own
  wheel speeds and the messages its neighbours sent one step before, and acts with its two wheel speeds and a
  message to its neighbours.

The task in both: bring each parcel to its target pose (x, y m, theta rad), by default the targets of a ``pose``
scenario. Each decision is a control tick of a run (:class:`~virtual_vehicle.run.network.TickedRun`, the same code a
networked run ticks with), the agent's action in place of the cell programs and their network: the wheels hold
their speeds for ``period`` s (zero-order hold; plain belts at their own speed, motor wheels through their
dynamics, dead cells and stuck wheels still), the scenario's fault events and cell changes happen at their times,
and the plant integrates every parcel exactly as a run does. Reward per step, shared by all agents:
``-period * sum_k (|xy_k - goal_k| / pitch + |theta_k - goal_k|)`` (s; heading error wrapped to [-pi, pi]),
and -10 more when a parcel falls off the array. An episode terminates when every parcel is within ``tolerance``
(m, rad) of its target or one falls off, and is truncated after ``max_steps`` decisions.

``gymnasium.make("virtual_vehicle/Array-v0", **kwargs)`` makes an :class:`ArrayEnv` once this module is imported.

Units are SI: m, s, rad, m/s, rad/s.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from pathlib import Path

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from virtual_vehicle.cells.design import twist_design
from virtual_vehicle.config.scenario import Scenario, load_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.network import TickedRun
from virtual_vehicle.run.results import CellLog, RunResult

FALL_PENALTY = 10.0


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class Episode:
    """The simulation under an environment: a scenario's array, parcels, friction, wheels, faults and cell changes,
    driven by wheel speeds set from outside every ``period`` s. ``start_noise`` = (m, rad) spreads each reset's
    starting poses uniformly.

    Each decision is one control tick of :class:`~virtual_vehicle.run.network.TickedRun`, the code a networked run
    ticks with, the agent's wheel speeds in place of the cell programs and their network: plain belts run at their
    own speed, motor wheels follow through their dynamics, the scenario's fault events and cell changes happen at
    their times (dead and absent cells do not drive, stuck wheels stay still), and the plant moves the parcels as the
    run does. (Before, environments held belts and motors to the agent's speeds and ignored fault events and cell
    changes.)"""

    def __init__(self, scenario: str | Path | Scenario = "pose_control", *, period: float = 0.05,
                 max_steps: int = 200, targets=None, tolerance=(0.005, np.radians(2.0)), vmax: float | None = None,
                 start_noise=(0.0, 0.0)):
        sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)[0]
        if targets is None and sc.control is not None:
            targets = getattr(sc.control, "targets", None)  # a pose program's
        if targets is None:
            raise ScenarioError("targets", "an environment needs a target pose [x, y, theta] per parcel (or a "
                                "scenario with program = \"pose\")")
        targets = np.asarray(targets, dtype=float)
        if targets.shape != (len(sc.parcels), 3) or not np.all(np.isfinite(targets)):
            raise ScenarioError("targets", f"need {len(sc.parcels)} finite [x, y, theta] rows, got shape "
                                f"{targets.shape}")
        if not (period > 0 and np.isfinite(period)):
            raise ScenarioError("period", f"must be a positive number of seconds, got {period}")
        if int(max_steps) < 1:
            raise ScenarioError("max_steps", f"must be at least 1, got {max_steps}")
        if any(p.t_start > 0 for p in sc.parcels):
            raise ScenarioError("parcels.t_start", "environments start every parcel at t = 0")
        tol = np.asarray(tolerance, dtype=float)
        if tol.shape != (2,) or not np.all(tol > 0):
            raise ScenarioError("tolerance", "needs two positive numbers: (m, rad)")
        self.scenario = sc.model_copy(update={"control": None, "duration": period * int(max_steps)})
        # built with its [control] (fault events and cell changes need one; the agent replaces its program) and at
        # least the scenario's duration (its events stay within it)
        self.setup = sc.model_copy(update={"duration": max(sc.duration, period * int(max_steps))}).build()
        self.period = float(period)
        self.max_steps = int(max_steps)
        self.targets = targets
        self.tolerance = tol
        self.vmax = float(vmax if vmax is not None else (sc.control.top_speed() if sc.control is not None else 0.5))
        if not self.vmax > 0:
            raise ScenarioError("vmax", f"must be a positive speed in m/s, got {self.vmax}")
        self.start_noise = np.asarray(start_noise, dtype=float)
        cells = self.setup.cells
        self.n, self.sensors_per_cell, self.parcels = cells.n, self.setup.sensors.count, len(sc.parcels)
        lo, hi = np.array(cells.bounds[:2]), np.array(cells.bounds[2:])
        reach = max(s.radius for s in self.setup.specs) + cells.pitch
        self.position_bounds = (lo - reach, hi + reach)

    def reset(self, rng: np.random.Generator) -> None:
        """Back to t = 0 with the scenario's starting poses (spread by ``start_noise``), faults and cells."""
        ys = []
        for y in self.setup.states:
            y = y.copy()
            y[:2] += rng.uniform(-1, 1, 2) * self.start_noise[0]
            y[2] += rng.uniform(-1, 1) * self.start_noise[1]
            ys.append(y)
        self.run = TickedRun(self.setup, self.period, end=math.inf, record=True, states=ys,
                             sensor_rng=np.random.default_rng(rng.integers(2**63)))
        self.t = 0.0
        self.wheels = np.zeros((self.n, 2))
        self.readings = self.run.begin()

    @property
    def ys(self) -> list[np.ndarray]:
        """Every parcel's state now: x, y m, theta rad, vx, vy m/s, omega rad/s."""
        return self.run.ys

    @property
    def active(self) -> list[bool]:
        """Which parcels are on the array."""
        return self.run.active

    @property
    def k(self) -> int:
        """Decisions taken since the reset."""
        return self.run.k

    def advance(self, wheels: np.ndarray, sent=None, received=None) -> tuple[float, bool]:
        """Hold ``wheels`` ((n, 2) speeds along each cell's drive directions, m/s, clipped to ``vmax``) for one
        period; returns (reward, terminated). ``sent``/``received`` (n,) messages, for the cell log only."""
        wheels = np.clip(np.asarray(wheels, dtype=float).reshape(self.n, 2), -self.vmax, self.vmax)
        zero = np.zeros(self.n, dtype=np.int64)
        was = list(self.active)
        _, self.t = self.run.span()
        self.wheels = np.array(self.run.finish(wheels, self.readings, zero if sent is None else sent,
                                               zero if received is None else received), dtype=float)
        self.readings = self.run.begin()  # the next tick's faults, cell changes and sensors: what the agent sees
        pos, ang = self.errors()
        reward = -self.period * float(np.sum(pos / self.setup.cells.pitch + ang))
        fell = any(w and not a for w, a in zip(was, self.active))
        if fell:
            reward -= FALL_PENALTY
        return reward, fell or self.success
    def errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Each parcel's distance (m) and heading error (rad) from its target."""
        Y = np.array(self.ys)
        return np.hypot(*(Y[:, :2] - self.targets[:, :2]).T), np.abs(_wrap(Y[:, 2] - self.targets[:, 2]))

    @property
    def success(self) -> bool:
        """Every parcel on the array and within tolerance of its target."""
        pos, ang = self.errors()
        return all(self.active) and bool(np.all(pos <= self.tolerance[0]) and np.all(ang <= self.tolerance[1]))

    @property
    def truncated(self) -> bool:
        """True once ``max_steps`` decisions have been taken."""
        return self.k >= self.max_steps

    def info(self) -> dict:
        """The step's info dict: ``t`` (s), ``error_m`` and ``error_rad`` per parcel, ``success``, ``on_array``."""
        pos, ang = self.errors()
        return {"t": self.t, "error_m": pos, "error_rad": ang, "success": self.success,
                "on_array": np.array(self.active)}

    def result(self) -> RunResult:
        """The episode so far as a :class:`~virtual_vehicle.run.results.RunResult`, e.g. for
        :func:`~virtual_vehicle.ui.animate.animate` or :func:`~virtual_vehicle.run.tables.build`: a sample per
        decision (and the Coulomb check there, as a run makes it at its output samples); its cell log has a row per
        decision (readings then, wheel speeds held from then) and a last row for now (wheels as last held)."""
        parcels = []
        for pr, on in zip(self.run.parcel_results(), self.active):
            tr = pr.trajectory
            parcels.append(replace(pr, trajectory=replace(tr, status="running" if on else "tipped")))
        sc = self.scenario.model_copy(update={"duration": max(self.t, self.period)})
        now = (self.t, self.readings.astype(bool), self.wheels.copy(), self.wheels.copy(), np.zeros(self.n, np.int64),
               np.zeros(self.n, np.int64))
        stats = {"faults_injected": self.run.injected} if self.run.injected else {}
        if self.run.reconfigured:
            stats["reconfigured"] = self.run.reconfigured
        return RunResult(replace(self.setup, scenario=sc, control=None), parcels, 0.0, stats, None,
                         CellLog.stack([*self.run.cell_log, now]))


class ArrayEnv(gymnasium.Env):
    """A central controller for an array (Gymnasium API).

    Args:
        scenario: a bundled scenario name, a TOML path or a :class:`~virtual_vehicle.config.scenario.Scenario` (its
            array, parcels, friction and sensors; its field or control is replaced by the agent).
        observe: ``"sensors"`` ((n, S) int8 readings), ``"poses"`` ((P, 6) x, y m, theta rad wrapped to
            [-pi, pi), vx, vy m/s, omega rad/s) or ``"both"`` (a dict of the two).
        action: ``"wheels"`` ((n, 2) wheel surface speeds, m/s, within +-vmax) or ``"twist"`` ((P, 3) vx, vy m/s,
            omega rad/s per parcel, turned into wheel speeds under it and scaled to vmax).
        period: seconds between decisions. max_steps: decisions per episode. targets: (P, 3) target poses
            (default: the scenario's). tolerance: (m, rad) of success. vmax: wheel speed limit, m/s (default: the
            scenario's control speed, else 0.5). start_noise: (m, rad) spread of the starting poses.
        render_mode: ``"rgb_array"`` for :meth:`render` frames like those of the animations.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, scenario: str | Path | Scenario = "pose_control", *, observe: str = "both",
                 action: str = "wheels", period: float = 0.05, max_steps: int = 200, targets=None,
                 tolerance=(0.005, np.radians(2.0)), vmax: float | None = None, start_noise=(0.0, 0.0),
                 render_mode: str | None = None):
        if observe not in ("sensors", "poses", "both"):
            raise ValueError(f"observe must be 'sensors', 'poses' or 'both', got {observe!r}")
        if action not in ("wheels", "twist"):
            raise ValueError(f"action must be 'wheels' or 'twist', got {action!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.episode = ep = Episode(scenario, period=period, max_steps=max_steps, targets=targets,
                                    tolerance=tolerance, vmax=vmax, start_noise=start_noise)
        self.observe, self.action_kind, self.render_mode = observe, action, render_mode
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / ep.period))}
        lo, hi = ep.position_bounds
        sensors = spaces.MultiBinary([ep.n, ep.sensors_per_cell])
        big = np.finfo(np.float64).max
        poses = spaces.Box(np.tile([lo[0], lo[1], -np.pi, -big, -big, -big], (ep.parcels, 1)),
                           np.tile([hi[0], hi[1], np.pi, big, big, big], (ep.parcels, 1)), dtype=np.float64)
        if observe == "both":
            self.observation_space = spaces.Dict({"sensors": sensors, "poses": poses})
        else:
            self.observation_space = sensors if observe == "sensors" else poses
        if action == "wheels":
            self.action_space = spaces.Box(-ep.vmax, ep.vmax, (ep.n, 2), dtype=np.float64)
        else:
            w = ep.vmax / max(s.radius for s in ep.setup.specs)
            self.action_space = spaces.Box(np.tile([-ep.vmax, -ep.vmax, -w], (ep.parcels, 1)),
                                           np.tile([ep.vmax, ep.vmax, w], (ep.parcels, 1)), dtype=np.float64)

    def _obs(self):
        ep = self.episode
        Y = np.array(ep.ys)
        Y[:, 2] = _wrap(Y[:, 2])
        lo, hi = ep.position_bounds
        Y[:, :2] = np.clip(Y[:, :2], lo, hi)
        obs = {"sensors": ep.readings.astype(np.int8), "poses": Y}
        return obs if self.observe == "both" else obs[self.observe]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.episode.reset(self.np_random)
        return self._obs(), self.episode.info()

    def wheel_speeds(self, action) -> np.ndarray:
        """(n, 2) wheel speeds (m/s) for an action of this environment's kind (values beyond the action space's
        bounds are clipped to them; a wrong shape or a non-finite value is a ValueError)."""
        ep = self.episode
        a = np.asarray(action, dtype=float)
        if a.shape != self.action_space.shape or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be a finite array of shape {self.action_space.shape}, got "
                             f"{a.shape if a.shape != self.action_space.shape else 'non-finite values'}")
        a = np.clip(a, self.action_space.low, self.action_space.high)
        if self.action_kind == "wheels":
            return a
        speeds = np.zeros((ep.n, 2))
        for k, spec in enumerate(ep.setup.specs):  # a cell under two parcels serves the later one
            if ep.active[k]:
                d = twist_design(ep.setup.cells, spec, ep.ys[k], a[k], ep.vmax)
                speeds[d.support] = d.wheel_speeds[d.support]
        return speeds

    def step(self, action):
        ep = self.episode
        reward, terminated = ep.advance(self.wheel_speeds(action))
        return self._obs(), reward, terminated, ep.truncated and not terminated, ep.info()

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return render_rgb(self.episode)

    def close(self):
        pass


def render_rgb(ep: Episode) -> np.ndarray:
    """(H, W, 3) uint8 picture of the episode now, drawn like a frame of :func:`~virtual_vehicle.ui.animate.animate`."""
    import matplotlib.pyplot as plt

    from virtual_vehicle.ui.animate import scene, frame_data

    result = ep.result()
    t = result.setup.scenario.duration if ep.k else 0.0
    fig, _ = scene(result, frame_data(result, [t]), ep.targets)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb


class CellsEnv(ParallelEnv):
    """Every cell an agent (PettingZoo parallel API): ``"cell_0"``, ``"cell_1"``, ... for the live cells.

    Each agent observes a flat float32 vector: its S sensor readings (0/1), its two wheel speeds (m/s), and for each
    of its P ports the ``message_size`` numbers the neighbour on that port sent at the previous step (zeros where
    there is none, or the link or neighbour is dead, from the start or since a fault event). Each acts with a vector
    of 2 + ``message_size`` numbers: its wheel speeds (m/s, within +-vmax; a dead or absent cell's do not turn) and
    the message its neighbours read next step (within +-1; an all-zero message counts as silence in the traffic the
    cell log records). Its wheel speeds observed are those its wheels held over the last step (a motor wheel's mean).
    Reward, task and the other arguments are those of :class:`ArrayEnv`; the reward is shared by all agents.
    ``state()`` is the parcels' states, flattened.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "virtual_vehicle_cells_v0"}

    def __init__(self, scenario: str | Path | Scenario = "pose_control", *, message_size: int = 4,
                 period: float = 0.05, max_steps: int = 200, targets=None, tolerance=(0.005, np.radians(2.0)),
                 vmax: float | None = None, start_noise=(0.0, 0.0), render_mode: str | None = None):
        from virtual_vehicle.cells.network.topology import from_layout

        if int(message_size) < 0:
            raise ValueError(f"message_size must be >= 0, got {message_size}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.episode = ep = Episode(scenario, period=period, max_steps=max_steps, targets=targets,
                                    tolerance=tolerance, vmax=vmax, start_noise=start_noise)
        self.render_mode = render_mode
        self.message_size = int(message_size)
        self.topology = topo = from_layout(ep.setup.cells)
        self.possible_agents = [f"cell_{i}" for i in range(ep.n) if topo.alive[i]]
        self._index = {a: int(a.split("_")[1]) for a in self.possible_agents}
        self.agents: list[str] = []
        S, P, M = ep.sensors_per_cell, topo.ports, self.message_size
        self._obs_size = S + 2 + P * M
        low = np.concatenate([np.zeros(S), np.full(2, -ep.vmax), np.full(P * M, -1.0)]).astype(np.float32)
        high = np.concatenate([np.ones(S), np.full(2, ep.vmax), np.full(P * M, 1.0)]).astype(np.float32)
        self._obs_space = spaces.Box(low, high, dtype=np.float32)
        self._act_space = spaces.Box(np.concatenate([np.full(2, -ep.vmax), np.full(M, -1.0)]).astype(np.float32),
                                     np.concatenate([np.full(2, ep.vmax), np.full(M, 1.0)]).astype(np.float32),
                                     dtype=np.float32)
        big = np.finfo(np.float64).max
        self.state_space = spaces.Box(-big, big, (6 * ep.parcels,), dtype=np.float64)
        self._rng = np.random.default_rng()

    @functools.lru_cache(maxsize=None)  # noqa: B019 -- one space object per agent, as PettingZoo asks
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    @functools.lru_cache(maxsize=None)  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    def _observations(self) -> dict[str, np.ndarray]:
        ep, topo, M = self.episode, self.episode.run.topology, self.message_size  # the links now (faults cut some)
        inbox = np.zeros((ep.n, topo.ports, M), dtype=np.float32)
        link = topo.connected & (topo.neighbor >= 0)
        if M:
            src = np.where(link, topo.neighbor, 0)
            inbox[link] = self.outbox[src][link]
        obs = np.concatenate([ep.readings.astype(np.float32), ep.wheels.astype(np.float32),
                              inbox.reshape(ep.n, -1)], axis=1)
        return {a: obs[i] for a, i in self._index.items() if a in self.agents}

    def _infos(self) -> dict[str, dict]:
        info = self.episode.info()
        return {a: info for a in self.agents}

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.agents = list(self.possible_agents)
        self.outbox = np.zeros((self.episode.n, self.message_size), dtype=np.float32)
        self.episode.reset(self._rng)
        return self._observations(), self._infos()

    def step(self, actions: dict[str, np.ndarray]):
        ep, M = self.episode, self.message_size
        wheels = np.zeros((ep.n, 2))
        outbox = np.zeros((ep.n, M), dtype=np.float32)
        for a, act in actions.items():
            if a not in self._index or a not in self.agents:
                raise ValueError(f"no live agent named {a!r}")
            act = np.clip(np.asarray(act, dtype=np.float32), self._act_space.low, self._act_space.high)
            wheels[self._index[a]] = act[:2]
            outbox[self._index[a]] = act[2:]
        topo = ep.run.topology  # the links now: a dead cell or link carries no message
        link = topo.connected & (topo.neighbor >= 0)
        sent = np.where(np.any(outbox != 0, axis=1), link.sum(axis=1), 0) if M else None
        received = None
        if M:
            received = np.zeros(ep.n, dtype=np.int64)
            np.add.at(received, topo.neighbor[link], np.repeat(sent > 0, link.sum(axis=1)))
        reward, terminated = ep.advance(wheels, sent, received)
        self.outbox = outbox
        truncated = ep.truncated and not terminated
        obs = self._observations()
        rewards = {a: reward for a in self.agents}
        terms = {a: terminated for a in self.agents}
        truncs = {a: truncated for a in self.agents}
        infos = self._infos()
        if terminated or truncated:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return render_rgb(self.episode)

    def state(self) -> np.ndarray:
        """The global state: every parcel's (x, y, theta, vx, vy, omega), flattened."""
        return np.array(self.episode.ys).ravel()

    def close(self):
        pass


gymnasium.register(id="virtual_vehicle/Array-v0", entry_point="virtual_vehicle.ui.envs:ArrayEnv",
                   kwargs={"scenario": "pose_control"})
