"""Reinforcement-learning starter: three policies on the pose-control task, to show the environments' shape.

* a random policy on :class:`~virtual_vehicle.ui.envs.ArrayEnv` (central; wheel speeds as the action),
* a proportional twist policy on the same task (action = the parcel's twist, from its observed pose): what a
  learned policy should at least match,
* random agents on :class:`~virtual_vehicle.ui.envs.CellsEnv` (every cell an agent, local observations only).

Prints each policy's mean return and final pose error. Run: ``python examples/rl_random_policy.py [--episodes 5]
[--steps 100] [--video episode.gif]`` (``--video`` animates the last proportional episode).
"""

from __future__ import annotations

import argparse

import numpy as np

from virtual_vehicle.ui.envs import ArrayEnv, CellsEnv


def rollout(env: ArrayEnv, policy, seed: int) -> tuple[float, dict]:
    obs, info = env.reset(seed=seed)
    env.action_space.seed(seed)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        total += reward
        done = terminated or truncated
    return total, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--steps", type=int, default=100, help="decisions per episode (0.05 s each)")
    ap.add_argument("--video", default=None, help="animate the last proportional-policy episode to this file")
    args = ap.parse_args()
    noise = (0.03, 0.2)  # m, rad: each episode starts somewhere else

    def report(name, runs):
        returns = [r for r, _ in runs]
        err_mm = [1e3 * float(i["error_m"].max()) for _, i in runs]
        ok = sum(bool(i["success"]) for _, i in runs)
        print(f"{name:>20}: mean return {np.mean(returns):8.3f}, final error {np.mean(err_mm):6.1f} mm, "
              f"{ok}/{len(runs)} reached the target")

    env = ArrayEnv("pose_control", observe="poses", action="wheels", max_steps=args.steps, start_noise=noise)
    report("random policy", [rollout(env, lambda obs: env.action_space.sample(), s) for s in range(args.episodes)])

    env = ArrayEnv("pose_control", observe="poses", action="twist", max_steps=args.steps, start_noise=noise)
    targets = env.episode.targets

    def proportional(obs, gain=3.0):
        err = targets - obs[:, :3]
        err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return gain * err

    report("proportional twist", [rollout(env, proportional, s) for s in range(args.episodes)])
    if args.video:
        from virtual_vehicle.ui.animate import animate

        print(f"{'':>20}  video: {animate(env.episode.result(), args.video, targets=targets)}")

    cells = CellsEnv("pose_control", max_steps=args.steps, start_noise=noise)
    runs = []
    for s in range(args.episodes):
        obs, info = cells.reset(seed=s)
        total = 0.0
        while cells.agents:
            actions = {a: cells.action_space(a).sample() for a in cells.agents}
            obs, rewards, terms, truncs, infos = cells.step(actions)
            total += next(iter(rewards.values()))
            info = next(iter(infos.values()))
        runs.append((total, info))
    report("random cells", runs)


if __name__ == "__main__":
    main()
