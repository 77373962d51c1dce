"""Gymnasium and PettingZoo environments: their libraries' own checks, and physics identical to a run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run import tables
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.envs import FALL_PENALTY, ArrayEnv, CellsEnv

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("observe", ["sensors", "poses", "both"])
@pytest.mark.parametrize("action", ["wheels", "twist"])
def test_array_env_passes_gymnasiums_checker(observe, action):
    env = gymnasium.make("virtual_vehicle/Array-v0", observe=observe, action=action, max_steps=10,
                         render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)


def test_the_registered_env_is_made_by_gymnasium():
    env = gymnasium.make("virtual_vehicle/Array-v0", observe="poses", max_steps=5)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (1, 6)
    check_env(env.unwrapped)


@pytest.mark.parametrize("message_size", [0, 4])
def test_cells_env_passes_pettingzoos_api_test(message_size):
    parallel_api_test(CellsEnv(message_size=message_size, max_steps=8), num_cycles=20)


def _field_scenario(duration=1.0):
    sc, _ = load_scenario("prototype_18")
    return sc.model_copy(update={"duration": duration, "output_dt": 0.05})


def test_holding_a_fields_wheel_speeds_moves_the_parcel_as_a_run_does():
    sc = _field_scenario()
    reference = run(sc.build()).parcels[0].trajectory
    env = ArrayEnv(sc, observe="poses", period=0.05, max_steps=20, targets=[[0.0, 0.0, 0.0]], vmax=1.0)
    setup = env.episode.setup
    wheels = np.einsum("ij,ikj->ik", setup.velocities, setup.cells.drive_directions)
    obs, _ = env.reset(seed=0)
    states = [obs[0].copy()]
    for _ in range(20):
        obs, *_ = env.step(wheels)
        states.append(obs[0].copy())
    np.testing.assert_allclose(np.array(states)[:, :2], reference.states[:, :2], atol=1e-7)
    np.testing.assert_allclose(np.array(states)[:, 3:], reference.states[:, 3:], atol=1e-6)


def test_reward_is_the_documented_pose_error_and_a_fall_ends_the_episode():
    sc = _field_scenario()
    target = np.array([[0.2, 0.06, 0.3]])
    env = ArrayEnv(sc, observe="poses", period=0.1, max_steps=100, targets=target, vmax=1.0)
    pitch = env.episode.setup.cells.pitch
    obs, _ = env.reset(seed=0)
    push = np.zeros((env.episode.n, 2))
    push[:, 0] = 0.5  # everything east, off the array's edge
    returns, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(push)
        steps += 1
        returns += reward
        if terminated or truncated:
            break
        d = np.hypot(*(obs[0, :2] - target[0, :2]))
        a = abs((obs[0, 2] - target[0, 2] + np.pi) % (2 * np.pi) - np.pi)
        assert reward == pytest.approx(-0.1 * (d / pitch + a), rel=1e-12)
    assert terminated and not truncated and not info["success"] and not info["on_array"][0]
    assert reward < -FALL_PENALTY
    assert steps < 100


def test_an_episode_starting_on_its_target_succeeds_at_once_and_one_that_cannot_is_truncated():
    sc = _field_scenario()
    start = sc.build().states[0][:3]
    env = ArrayEnv(sc, observe="poses", max_steps=3, targets=[start])
    env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step(np.zeros(env.action_space.shape))
    assert terminated and not truncated and info["success"] and reward == pytest.approx(0.0, abs=1e-9)
    env = ArrayEnv(sc, observe="poses", max_steps=3, targets=[start + [0.1, 0.0, 0.0]])
    env.reset(seed=0)
    flags = [env.step(np.zeros(env.action_space.shape))[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]


def test_seeds_make_episodes_reproducible():
    def rollout(seed):
        env = ArrayEnv("pose_control", observe="both", max_steps=5, start_noise=(0.02, 0.1))
        obs, _ = env.reset(seed=seed)
        env.action_space.seed(seed)
        out = [obs["poses"].copy()]
        for _ in range(5):
            obs, *_ = env.step(env.action_space.sample())
            out.append(obs["poses"].copy())
        return np.array(out)

    np.testing.assert_array_equal(rollout(3), rollout(3))
    assert not np.allclose(rollout(3)[0], rollout(4)[0])


def test_cells_hear_their_neighbours_one_step_later_on_the_right_port():
    env = CellsEnv("pose_control", message_size=2, max_steps=4)
    obs, _ = env.reset(seed=0)
    ep, topo = env.episode, env.topology
    S = ep.sensors_per_cell
    ids = np.array([int(a.removeprefix("cell_")) for a in env.agents])  # agent "cell_i" is cell i
    actions = {a: np.array([0.0, 0.0, i / ep.n, -0.5], dtype=np.float32) for a, i in zip(env.agents, ids)}
    obs, rewards, *_ = env.step(actions)
    assert len(set(rewards.values())) == 1  # one shared reward
    for a, i in zip(env.agents, ids):
        inbox = obs[a][S + 2:].reshape(topo.ports, 2)
        for p in range(topo.ports):
            j = topo.neighbor[i, p]
            want = [j / ep.n, -0.5] if j >= 0 and topo.connected[i, p] else [0.0, 0.0]
            np.testing.assert_allclose(inbox[p], want, rtol=1e-6)
    log = ep.result().cell_log
    np.testing.assert_array_equal(log.received[0], (topo.neighbor >= 0).sum(axis=1))


def test_cells_env_and_array_env_agree_on_the_same_wheel_speeds():
    rng = np.random.default_rng(0)
    a, c = ArrayEnv("pose_control", observe="poses", max_steps=6), CellsEnv("pose_control", max_steps=6)
    a.reset(seed=0)
    c.reset(seed=0)
    for _ in range(6):
        wheels = rng.uniform(-0.1, 0.1, (a.episode.n, 2))
        obs, *_ = a.step(wheels)
        c.step({f"cell_{i}": np.concatenate([wheels[i], np.zeros(4)]).astype(np.float32) for i in range(c.episode.n)})
    np.testing.assert_allclose(np.array(c.episode.ys), np.array(a.episode.ys), atol=1e-6)


def test_an_episode_becomes_tables_and_an_animation(tmp_path):
    from PIL import Image

    from virtual_vehicle.ui.animate import animate

    env = ArrayEnv("pose_control", action="twist", observe="poses", max_steps=6)
    env.reset(seed=0)
    for _ in range(6):
        env.step(np.array([[0.05, 0.0, 0.2]]))
    result = env.episode.result()
    tab = tables.build(result)
    assert tab["trajectories"].num_rows == 7  # t = 0 and every decision
    out = animate(result, tmp_path / "episode.gif", fps=20, targets=env.episode.targets)
    with Image.open(out) as im:
        assert im.n_frames == 7


def test_bad_environment_arguments_are_refused():
    with pytest.raises(ValueError, match="observe"):
        ArrayEnv(observe="pixels")
    with pytest.raises(ValueError, match="action"):
        ArrayEnv(action="forces")
    with pytest.raises(ScenarioError, match="targets"):
        ArrayEnv("prototype_18")
    with pytest.raises(ScenarioError, match="targets"):
        ArrayEnv("pose_control", targets=[[0.0, 0.0]])
    with pytest.raises(ScenarioError, match="period"):
        ArrayEnv(period=0.0)
    env = ArrayEnv(max_steps=2)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.full(env.action_space.shape, np.nan))
    cells = CellsEnv(max_steps=2)
    cells.reset(seed=0)
    with pytest.raises(ValueError, match="no live agent"):
        cells.step({"cell_99999": np.zeros(6, np.float32)})


def test_the_example_script_runs():
    res = subprocess.run([sys.executable, str(ROOT / "examples" / "rl_random_policy.py"), "--episodes", "2",
                          "--steps", "10"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert "random policy" in res.stdout and "proportional twist" in res.stdout and "cells" in res.stdout


def test_a_cell_that_dies_mid_episode_stops_driving_and_talking():
    from virtual_vehicle.config.scenario import FaultEvent

    sc, _ = load_scenario("pose_control")
    dead = 5 * 20 + 5  # an inner cell of the 20 x 20 grid
    sc = sc.model_copy(update={"faults": sc.faults.model_copy(update={"events": [FaultEvent(t=0.1,
                                                                                             dead_cells=[dead])]})})
    env = CellsEnv(sc, message_size=1, period=0.05, max_steps=4)
    env.reset(seed=0)
    S, topo = env.episode.sensors_per_cell, env.topology
    (j, port), *_ = [(j, p) for j in range(env.episode.n) for p in range(topo.ports) if topo.neighbor[j, p] == dead]
    heard, driven = [], []
    for _ in range(4):  # decisions at t = 0, 0.05 (alive), 0.1, 0.15 (dead from 0.1 s on)
        obs, *_ = env.step({a: np.array([0.1, -0.1, 1.0], np.float32) for a in env.agents})
        heard.append(float(obs[f"cell_{j}"][S + 2 + port]))
        driven.append(obs[f"cell_{dead}"][S:S + 2].tolist())
    assert heard == [1.0, 0.0, 0.0, 0.0]  # its neighbours hear nothing from the decision at 0.1 s on
    assert driven[:2] == [[pytest.approx(0.1), pytest.approx(-0.1)]] * 2 and driven[2:] == [[0.0, 0.0]] * 2
    assert env.episode.result().summary()["faults_injected"][0]["dead_cells"] == [dead]
