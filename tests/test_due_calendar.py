"""The sorter's due-tick calendar (issue 32 item 6): the cells the time wakes at a tick, kept as cells are stepped,
are those ``Sorter.due`` finds by looking at every cell, and a run driven by it is the run of stepping every cell
every tick, to the last bit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.sorting import Sorter
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run.sim import NetworkRun


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 3]), st.sampled_from([0.0, 0.03, 0.07]),
       st.sampled_from([4, 6]))
def test_the_calendar_names_the_cells_due_names_on_random_runs(seed, max_age, heartbeat, P):
    """From a random state (ports last heard at random ticks, some never), cells stepped in random subsets on random
    sentences arriving (in place, as the stepper steps them) for 40 ticks: every tick the calendar names exactly the
    cells ``due`` names over the whole array."""
    rng = np.random.default_rng(seed)
    n = 30
    program = Sorter(0.3, max_age=max_age, heartbeat=heartbeat, reach=8)
    config = {"entry_no": rng.integers(0, 3000, n)}
    state = program.init(n, P, config)
    k0 = int(rng.integers(0, 10**5))
    state["heard_at"] = k0 - rng.choice([0, 1, 2, 5, 9, 2**40], (n, P))
    connected = rng.random((n, P)) < 0.9
    calendar = program.calendar(n, config)
    calendar.restart(k0 * 0.01, state)
    inbox = Mailbox.empty(program.schema, n, P)
    outbox = wheels = None
    for k in range(k0 + 1, k0 + 41):
        t = k * 0.01
        assert calendar.due(t, state).tolist() == program.due(t, state, config).tolist(), k
        inbox.present[:] = (rng.random((n, P)) < rng.choice([0.0, 0.3, 0.9])) & connected
        inputs = CellInputs(t, rng.random((n, 1)) < 0.1, inbox, connected, config)
        if outbox is None:  # the first step makes the arrays the others write into
            state, outbox, wheels = program.step(state, inputs)
            wheels = np.array(wheels)
            rows = np.arange(n)
        else:
            rows = np.flatnonzero(rng.random(n) < rng.choice([0.1, 0.5, 1.0]))
            assert program.step_rows(state, inputs, rows, outbox, wheels) is not None
        calendar.stepped(t, state, rows)


def _scenario(name, duration, **control):
    sc, _ = load_scenario(name)
    return sc.model_copy(update={"duration": duration, "control": sc.control.model_copy(update=control)})


CASES = {  # (heartbeat 1 s unless named: trust 198 ticks; max_age > 0: the trusted span is not the heartbeats')
    "heartbeat, lossy": lambda: _scenario("sorting_junction", 2.0, loss_rate=0.005),
    "short heartbeat, max_age, lossy": lambda: _scenario("sorting_junction", 2.0, loss_rate=0.005, heartbeat=0.05,
                                                         max_age=2),
    "no heartbeat, ideal": lambda: _scenario("sorting_junction", 2.0, heartbeat=0.0),
    "hexagonal, short heartbeat, lossy": lambda: _scenario("hex_sorting_junction", 1.5, loss_rate=0.005,
                                                           heartbeat=0.04),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_run_driven_by_the_calendar_is_the_run_of_stepping_every_cell(case):
    """The changed-cells stepper, waking cells by the calendar, gives the run of stepping every cell every tick:
    the parcels' trajectories, every tick's traffic and the cells' state at the end; and it used the calendar."""
    sc = CASES[case]()
    setups = {flag: sc.model_copy(update={"control": sc.control.model_copy(update={"changed_only": flag})}).build()
              for flag in (True, False)}
    program, asked = setups[True].control.program, []
    make = program.calendar

    def calendar(n, config):  # count the ticks the calendar names the cells due
        made = make(n, config)
        due = made.due
        made.due = lambda t, state: asked.append(t) or due(t, state)
        return made

    program.calendar = calendar
    jobs = {flag: NetworkRun(setup) for flag, setup in setups.items()}
    res = {flag: job.run(None) for flag, job in jobs.items()}
    for p, q in zip(res[True].parcels, res[False].parcels, strict=True):
        np.testing.assert_array_equal(p.trajectory.states, q.trajectory.states)
    for key, v in res[True].network.per_tick.items():
        np.testing.assert_array_equal(v, res[False].network.per_tick[key], err_msg=key)
    for name, v in jobs[False].state.items():
        pairs = [(v[w], jobs[True].state[name][w]) for w in v] if isinstance(v, dict) else [(v, jobs[True].state[name])]
        for a, b in pairs:
            np.testing.assert_array_equal(a, b, err_msg=name)
    assert asked  # (on lossy rounds the stepper often steps every cell: then no calendar is asked)
