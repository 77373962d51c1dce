"""Scalability (issue 6): one scenario from millimetre cells and micrograms to metre cells and tonnes is one run in
units of the pitch and sqrt(pitch / g) (Froude similarity); what breaks similarity does break it; a 100 x 100 array
carries hundreds of parcels."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from virtual_vehicle.analysis.scaling import dimensionless, scale_scenario, similarity_study
from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.cli import app


@pytest.mark.parametrize("name", ["paper_2x2_inward", "prototype_18", "row_oscillator_viscous", "stick_slip_pickup",
                                  "squeeze_align"])
def test_micro_to_large_scale_runs_are_one_dimensionless_run(name):
    sc, _ = load_scenario(name)
    rows = similarity_study(sc, [(1.0, 1.0), (0.01, 1e-6), (10.0, 1e3)])  # 1 mm .. 1 m cells, ug .. t parts
    assert rows[1]["pitch_m"] == pytest.approx(0.01 * rows[0]["pitch_m"])
    assert rows[2]["mass_kg"] == pytest.approx(1e3 * rows[0]["mass_kg"])
    for r in rows[1:]:
        assert r["max_deviation"] < 1e-8, r
    assert np.ptp(rows[0]["states"][:, :3], axis=0).max() > 0.1  # it did move (a tenth of a pitch or radian)


def test_the_2x2_inward_oscillation_keeps_its_dimensionless_frequency():
    """Paper eq. 23 for the 2x2 inward field: a = -(2 mu W / d) I, so x'' = -(2 mu g / d) x and the period in units
    of sqrt(d / g) is 2 pi / sqrt(2 mu) at every scale."""
    sc, _ = load_scenario("paper_2x2_inward")
    for s in (0.001, 1.0, 30.0):
        member = scale_scenario(sc, s, s ** 3)
        tr = run(member.build()).parcels[0].trajectory
        d, mu = member.array.pitch, member.parcels[0].mu
        tau, st = dimensionless(tr.times, tr.states, d, member.gravity)
        centre = (member.array.origin[0] + d / 2) / d
        expected = (st[0, 0] - centre) * np.cos(np.sqrt(2 * mu) * tau) + centre
        np.testing.assert_allclose(st[:, 0], expected, atol=1e-8)


def test_what_breaks_similarity_breaks_it():
    """Keeping the viscous mu (s/m) or the wheel speeds unscaled is not similar: the dimensionless runs part."""
    sc, _ = load_scenario("row_oscillator_viscous")
    good = scale_scenario(sc, 0.01, 1.0)
    bad_mu = good.model_copy(update={"parcels": [p.model_copy(update={"mu": q.mu})
                                                 for p, q in zip(good.parcels, sc.parcels)]})
    bad_speed = good.model_copy(update={"field": sc.field})
    curves = {}
    for key, member in (("ref", sc), ("good", good), ("mu", bad_mu), ("speed", bad_speed)):
        tr = run(member.build()).parcels[0].trajectory
        curves[key] = dimensionless(tr.times, tr.states, member.array.pitch, member.gravity)[1]

    def apart(key):
        n = min(len(curves[key]), len(curves["ref"]))
        return np.max(np.abs(curves[key][:n] - curves["ref"][:n]))

    assert len(curves["good"]) == len(curves["ref"]) and apart("good") < 1e-8
    assert apart("mu") > 1e-2 and apart("speed") > 1e-2


def test_what_cannot_be_scaled_is_named():
    with pytest.raises(ScenarioError, match="networked runs"):
        scale_scenario(load_scenario("sorting_junction")[0], 0.1)
    with pytest.raises(ScenarioError, match="positive"):
        scale_scenario(load_scenario("prototype_18")[0], -1.0)
    with pytest.raises(ScenarioError, match=r"parcels\[0\]\.x"):
        scale_scenario(load_scenario("prototype_18")[0], 1e9)


def test_scale_study_command(tmp_path):
    res = CliRunner().invoke(app, ["scale-study", "paper_2x2_inward", "--lengths", "1,0.01", "--masses", "1,1e-6",
                                   "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "scale_study.json").read_text())
    assert [r["length_factor"] for r in data["runs"]] == [1.0, 0.01] and data["runs"][1]["max_deviation"] < 1e-8
    assert (tmp_path / "scale_study.png").stat().st_size > 0
    bad = CliRunner().invoke(app, ["scale-study", "--lengths", "1,2", "--masses", "1", "--out", str(tmp_path)])
    assert bad.exit_code == 2 and "one mass factor per length factor" in bad.output


def test_a_100_by_100_array_carries_hundreds_of_parcels():
    parcels = [{"name": f"p{k}", "length": 0.25, "width": 0.2, "mass": 1.0 + 0.1 * (k % 5), "mu": 1.0,
                "x": 0.5 + 0.6 * (k % 15), "y": 0.3 + 0.48 * (k // 15), "theta": 0.1 * (k % 7)} for k in range(300)]
    sc = parse_scenario({"name": "hall", "duration": 0.1, "array": {"kind": "grid", "nx": 100, "ny": 100,
                                                                     "pitch": 0.1},
                         "field": {"kind": "uniform", "velocity": [0.2, 0.05]}, "friction": {"law": "viscous"},
                         "parcels": parcels})
    res = run(sc.build())
    assert len(res.parcels) == 300 and all(p.trajectory.status == "completed" for p in res.parcels)
    g, mu = 9.81, 1.0
    for p in res.parcels:  # every parcel obeys the uniform-field closed form v = V (1 - exp(-mu g t)) (eq. 33)
        t, v = p.trajectory.times[-1], p.trajectory.states[-1, 3:5]
        np.testing.assert_allclose(v, np.array([0.2, 0.05]) * (1 - np.exp(-mu * g * t)), atol=1e-9)
    summary = res.summary()["plant"]
    assert summary["undetected_overlaps"] == 0 and summary["parcel_contacts"] == 0
