"""One tick for runs and environments: an environment fed the wheel commands a run's cell programs gave moves the
parcels as the run does (belts, motors, fault events included), because both tick with the same code."""

from __future__ import annotations

import numpy as np

from virtual_vehicle.config.scenario import FaultEvent, load_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.envs import ArrayEnv


def _recorded(sc, **update):
    """``sc`` changed by ``update``, its cells' log kept (the commands of every tick)."""
    return sc.model_copy(update={**update, "sensors": sc.sensors.model_copy(update={"record": True})})


def _replay(sc, commands, period, targets):
    """An ArrayEnv on ``sc`` driven with ``commands`` (one (n, 2) array a decision); every parcel's state at t = 0
    and after every decision, and those times (s)."""
    env = ArrayEnv(sc, observe="poses", period=period, max_steps=len(commands), targets=targets, vmax=10.0)
    env.reset(seed=0)
    times, states = [0.0], [np.array(env.episode.ys)]
    for command in commands:
        env.step(command)
        times.append(env.episode.t)
        states.append(np.array(env.episode.ys))
    return env, np.array(times), np.array(states)


def _assert_same_as_run(result, times, states):
    """Every output sample of the run taken at a decision time is the replay's state then (the run's sample grid
    and its tick ends may differ in the last bit of the time); the end is the same to the last bit."""
    for i, pr in enumerate(result.parcels):
        tr = pr.trajectory
        at = np.abs(times[:, None] - tr.times[None, :]) <= 1e-12  # (decision, sample) at the same time
        assert at.sum() == min(len(times), len(tr.times))  # all the coarser of the two
        for j, k in zip(*np.nonzero(at)):
            np.testing.assert_allclose(states[j, i], tr.states[k], rtol=0, atol=1e-12)
        assert tr.times[-1] == times[-1]
        np.testing.assert_array_equal(states[-1, i], tr.states[-1])


def test_the_feed_belt_carries_its_parcel_in_an_environment_as_in_a_run():
    sc, _ = load_scenario("hybrid_junction")
    sc = _recorded(sc, duration=0.5, parcels=sc.parcels[:1])  # the first parcel, on the feed belt
    result = run(sc.build())
    log = result.cell_log
    env, times, states = _replay(sc, log.commands, sc.control.period, [[3.0, 0.85, 0.0]])
    _assert_same_as_run(result, times, states)
    assert states[0, 0, 0] == 0.3 and states[-1, 0, 0] > 0.43  # 0.3 m/s for 0.5 s, less the start from rest
    np.testing.assert_allclose(states[:, 0, 1], 0.55, atol=1e-9)
    # the belt moves whatever the agent asks: still wheels everywhere move the parcel the same
    still = _replay(sc, np.zeros_like(log.commands), sc.control.period, [[3.0, 0.85, 0.0]])[2]
    np.testing.assert_array_equal(still[-1], states[-1])


def test_a_fault_event_breaks_the_same_wheels_in_an_environment_as_in_a_run():
    sc, _ = load_scenario("pose_control")
    cells = sc.build().cells
    start = np.array([sc.parcels[0].x, sc.parcels[0].y])
    under = np.flatnonzero(np.hypot(*(cells.positions - start).T) < 0.09).tolist()  # the cells under the carton
    event = FaultEvent(t=0.1, dead_cells=under[::2], stuck_wheels=[[c, 0] for c in under[1::2]])
    broken = _recorded(sc, duration=0.4, faults=sc.faults.model_copy(update={"events": [event]}))
    result = run(broken.build())
    assert result.summary()["faults_injected"][0]["dead_cells"] == under[::2]
    commands = result.cell_log.commands
    targets = sc.control.targets
    env, times, states = _replay(broken, commands, sc.control.period, targets)
    _assert_same_as_run(result, times, states)
    assert env.episode.result().summary()["faults_injected"] == result.summary()["faults_injected"]
    # the event mattered: without it the same commands carry the carton elsewhere
    intact = _replay(_recorded(sc, duration=0.4), commands, sc.control.period, targets)[2]
    np.testing.assert_array_equal(intact[times <= 0.1 + 1e-9], states[times <= 0.1 + 1e-9])
    assert np.abs(intact[-1, 0, :2] - states[-1, 0, :2]).max() > 1e-3


def test_motor_wheels_follow_the_same_commands_in_an_environment_as_in_a_run():
    sc, _ = load_scenario("crossing_30x30")
    motor = _recorded(sc, duration=0.3, wheels=sc.wheels.model_copy(update={"model": "motor"}))
    setup = motor.build()
    result = run(setup)
    log = result.cell_log
    targets = [[0.0, 0.0, 0.0]] * len(sc.parcels)
    env, times, states = _replay(motor, log.commands, setup.control.period, targets)
    _assert_same_as_run(result, times, states)
    np.testing.assert_array_equal(env.episode.result().cell_log.wheels[:-1], log.wheels)  # the motors' speeds
    # the motors mattered: ideal wheels given the same commands carry the parcels elsewhere
    ideal = _replay(sc.model_copy(update={"duration": 0.3}), log.commands, setup.control.period, targets)[2]
    assert np.abs(ideal[-1, :, :2] - states[-1, :, :2]).max() > 1e-4


def test_cells_taken_out_carry_nothing_in_an_environment_as_in_a_run():
    from virtual_vehicle.config.scenario import CellChange, ReconfigurationSpec

    sc, _ = load_scenario("prototype_18_network")
    setup = sc.build()
    start = setup.states[0][:2]
    under = np.argsort(np.hypot(*(setup.cells.positions - start).T))[:2].tolist()  # the two cells nearest the parcel
    changes = ReconfigurationSpec(changes=[CellChange(t=0.2, remove=under), CellChange(t=0.6, add=under)])
    changed = _recorded(sc, duration=0.8, reconfiguration=changes)
    result = run(changed.build())
    assert [c["removed"] for c in result.summary()["reconfigured"]] == [sorted(under), []]
    period = setup.control.period
    targets = [[0.0, 0.0, 0.0]] * len(sc.parcels)
    env, times, states = _replay(changed, result.cell_log.commands, period, targets)
    _assert_same_as_run(result, times, states)
    # the change mattered: with the cells left in, the same commands carry the parcel elsewhere
    kept = _replay(_recorded(sc, duration=0.8), result.cell_log.commands, period, targets)[2]
    assert np.abs(kept[-1, :, :2] - states[-1, :, :2]).max() > 1e-4
