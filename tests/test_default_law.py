"""Stick-slip is the default friction law: a scenario that names none gets wheels that grip, the bundled transport
scenarios run it with dimensionless coefficients, and the paper's worked examples keep the laws their analyses are
defined for."""

import numpy as np
import pytest

from virtual_vehicle.config.scenario import bundled_scenarios, load_scenario, parse_scenario
from virtual_vehicle.run.sim import run

PAPER_EXAMPLES = {"paper_2x2_inward": "coulomb", "row_oscillator": "coulomb", "row_oscillator_viscous": "viscous",
                  "prototype_18": "coulomb", "squeeze_align": "viscous", "pose_control": "viscous"}
TRANSPORT = ("crossing_30x30", "sorting_junction", "divert_line", "merge_two_streams", "reorder_stream",
             "hybrid_junction", "prototype_18_network", "prototype_18_network_ideal", "pose_tasks",
             "stick_slip_pickup", "facility_40x40", "hex_sorting_junction")


def test_a_scenario_naming_no_law_rides_at_the_wheel_speed():
    """A carton put down at rest on rollers at V = 0.2 m/s with no [friction] table: it accelerates at mu g until it
    catches up (V / (mu g) = 0.034 s) and then rides at exactly V. The paper's Coulomb law would carry it on past
    V (mu g for ever), the viscous law would leave it below V."""
    sc = parse_scenario({
        "name": "t", "duration": 0.5, "output_dt": 0.01,
        "array": {"kind": "grid", "nx": 20, "ny": 8, "pitch": 0.1},
        "field": {"kind": "uniform", "velocity": [0.2, 0.0]},
        "parcels": [{"name": "c", "length": 0.3, "width": 0.25, "mass": 1.0, "mu": 0.6, "mu_static": 0.8,
                     "x": 0.4, "y": 0.4}],
    })
    assert sc.friction.law == "stick_slip"
    result = run(sc.build())
    assert result.summary()["friction_law"] == "stick_slip"
    tr = result.parcels[0].trajectory
    after = tr.times >= 0.1
    assert np.abs(tr.states[after, 3] - 0.2).max() < 1e-9 and np.abs(tr.states[after, 4]).max() < 1e-9


@pytest.mark.parametrize("name, law", sorted(PAPER_EXAMPLES.items()))
def test_the_paper_s_worked_examples_keep_their_laws_and_say_why(name, law):
    sc, _ = load_scenario(name)
    assert sc.friction.law == law
    assert "not the default stick-slip" in " ".join(sc.description.split())


@pytest.mark.parametrize("name", TRANSPORT)
def test_transport_scenarios_run_stick_slip_with_dimensionless_coefficients(name):
    sc, _ = load_scenario(name)
    assert sc.friction.law == "stick_slip"
    for p in sc.parcels:  # a coefficient of friction, not a viscous s/m; static at least kinetic
        assert 0.3 <= p.mu <= 1.0 and p.mu_static is not None and p.mu <= p.mu_static <= 1.0


def test_every_bundled_scenario_is_either_kind():
    assert set(bundled_scenarios()) == set(PAPER_EXAMPLES) | set(TRANSPORT)
