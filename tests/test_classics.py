"""The field's classic results (issue 35), each against its source's own statement: the seed paper's 2x2 inward
field and end-reversed row, squeeze fields (Böhringer, Donald et al. 1994), elliptic fields (Kavraki 1997), and the
``reproduce`` command. Tolerances are those the sources allow (closed forms: numerical; continuous theories on a
discrete array: a few degrees at 5 mm cells under 80 mm parts)."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from virtual_vehicle.analysis.classics import CLASSICS, reproduce
from virtual_vehicle.analysis.classics import elliptic, seed_paper, squeeze
from virtual_vehicle.model.parcel import rectangle
from virtual_vehicle.ui.cli import app

G = 9.81


def read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_inward_2x2_has_R_zero_a_diagonal_no_torque_and_the_closed_form_oscillation(tmp_path):
    """Paper eqs. 20-26 with the bundled scenario's d = 0.1 m, mu = 0.5, m = 1 kg: R = 0, a-hat = -(2 mu W / d) I,
    the heading never changes, and x, y oscillate at sqrt(2 mu g / d)."""
    r = seed_paper.inward_2x2(tmp_path)
    n = r.numbers
    assert n["R_max_abs_m"] < 1e-12
    np.testing.assert_allclose(n["a_hat_N_per_m"], -2 * 0.5 * 1.0 * G / 0.1 * np.eye(2), rtol=1e-9, atol=1e-9)
    assert n["zero_torque_heading_range_rad"] == pytest.approx(2 * np.pi)
    assert n["theta_drift_rad"] < 1e-12 and n["amplitude_x_m"] == pytest.approx(0.02)
    for omega in (n["omega_x_rad_per_s"], n["omega_y_rad_per_s"]):
        assert omega == pytest.approx(np.sqrt(2 * 0.5 * G / 0.1), rel=1e-4)
    assert r.passed
    rows = read_csv(tmp_path / "inward_2x2.csv")
    assert len(rows) > 1000 and {"t", "x", "y", "theta", "x_closed"} <= set(rows[0])
    assert (tmp_path / "inward_2x2.png").stat().st_size > 10_000


def test_row_oscillator_is_harmonic_per_support_set_and_changes_with_it(tmp_path):
    """On cells at 0.5, 0.6, 0.7 m (the last reversed) a bar on equal springs feels k = mu W sum(-F_i (s_i - s))/S:
    0.3 * 9.81 * 0.2 / 0.02 = 29.43 N/m under Coulomb; with mu = 1 s/m and |V| = 1 m/s, 98.1 N/m viscous (and
    damping mu W = 9.81 N s/m). The engine must show these oscillators, and more than one per law."""
    r = seed_paper.row_oscillator(tmp_path)
    coulomb, viscous = r.numbers["Coulomb"], r.numbers["viscous"]
    assert np.sqrt(0.3 * G * 0.2 / 0.02) == pytest.approx(5.424942, abs=1e-6)
    assert 5.424942 in coulomb["frequencies_rad_per_s"] and 9.904544 in viscous["frequencies_rad_per_s"]
    for law in (coulomb, viscous):
        assert law["distinct_oscillators"] >= 2
        assert law["stiffness_rel_error"] < 1e-3 and law["centre_error_m"] < 1e-5 and law["max_deviation_m"] < 1e-7
    rows = read_csv(tmp_path / "row_oscillator.csv")
    damped = [float(x["damping_engine"]) for x in rows if x["law"] == "viscous"]
    np.testing.assert_allclose(damped, 1.0 * 1.0 * G, rtol=1e-3)  # eq. 33: mu W
    undamped = [float(x["damping_engine"]) for x in rows if x["law"] == "Coulomb"]
    np.testing.assert_allclose(undamped, 0.0, atol=1e-3)
    assert r.passed


def test_bisector_construction_of_a_rectangle():
    """The continuous theory for a 2:1 rectangle: no torque with a side along the line, restoring toward the long
    side along it (stable at 0), away from the crosswise heading (unstable at pi/2)."""
    bar = rectangle(0.2, 0.1, 1.0, 0.5)
    for theta in (0.0, np.pi / 2):
        assert abs(squeeze.bisector_torque(bar.footprint, theta)[1]) < 1e-12
    assert squeeze.bisector_torque(bar.footprint, 0.2)[1] < 0 < squeeze.bisector_torque(bar.footprint, -0.2)[1]
    assert squeeze.bisector_torque(bar.footprint, np.pi / 2 + 0.2)[1] > 0
    c, _ = squeeze.bisector_torque(bar.footprint, 0.3)
    assert abs(c) < 1e-9  # a centrally symmetric part is bisected through its centre


def test_squeeze_equilibria_are_at_the_area_bisectors():
    """Random polygons: every stable orientation of the bisector construction (shapely) is one of the package's
    (engine forces on a 5 mm array), within 3 deg, with the centre of mass offset from the line as the bisector
    says, to a fraction of a cell."""
    rng = np.random.default_rng(7)
    for _ in range(3):
        spec = squeeze.random_polygon(rng, 0.08)
        c = squeeze.compare_polygon(spec, pitch=0.005)
        assert len(c["bisector_stable"]) >= 1
        assert squeeze.match(c["bisector_stable"], c["package_stable"]) < np.radians(3)
        for s in c["bisector_stable"]:
            i = int(np.argmin(np.abs(c["headings"] - s)))
            assert abs(c["package_offset"][i] + c["bisector_offset"][i]) < 0.2 * 0.005


def test_two_squeezes_leave_a_part_in_one_orientation():
    """A part with several stable squeeze orientations: after the first squeeze simulated starts rest in more than
    one orientation; the planned second squeeze brings them all to one (modulo pi, the field's symmetry)."""
    rng = np.random.default_rng(35)
    spec = [squeeze.random_polygon(rng, 0.08) for _ in range(5)][4]
    c = squeeze.compare_polygon(spec, pitch=0.005)
    assert len(c["package_stable"]) >= 2
    alpha, margin = squeeze.two_squeeze_plan(c["package_stable"], c["package_unstable"])
    assert np.isfinite(alpha) and margin > np.radians(5)
    final = squeeze.run_plan(spec, 0.005, [0.0, alpha], np.linspace(0, np.pi, 6, endpoint=False) + 0.05)
    after_first, after_second = final[:, 0], final[:, 1]
    assert max(gap(a, b) for a in after_first for b in after_first) > np.radians(20)
    assert max(gap(a, b) for a in after_second for b in after_second) < np.radians(1)


def gap(a, b):
    """Distance between two headings modulo pi, rad."""
    return abs((a - b + np.pi / 2) % np.pi - np.pi / 2)


def test_elliptic_field_gives_most_parts_two_stable_orientations(tmp_path):
    """Kavraki: "two stable equilibria for most parts". A majority of random polygons has exactly two, pi apart, at
    the continuous theory's heading; an isotropic part (a square, a regular hexagon) does not have exactly two."""
    r = elliptic.elliptic_fields(tmp_path, parts=8)
    n = r.numbers
    assert n["fraction_exactly_two"] > 0.5
    assert n["exactly_two"] == sum(k == 2 for k in n["stable_counts"])
    assert n["worst_error_to_continuous_deg"] < 3
    assert all(k != 2 for k in n["control_stable_counts"].values())
    rows = read_csv(tmp_path / "elliptic.csv")
    assert len(rows) == 8 and r.passed


def test_continuous_elliptic_orientation_of_a_bar():
    """A bar's long axis goes along the weaker pull: with k1 > k2 (stronger along x) it lies along y."""
    bar = rectangle(0.2, 0.05, 1.0, 0.5)
    assert elliptic.continuous_orientation(bar, (1.0, 0.5)) == pytest.approx(np.pi / 2)
    assert elliptic.continuous_orientation(bar, (0.5, 1.0)) == pytest.approx(0.0, abs=1e-12)


def test_reproduce_names_the_results_and_refuses_unknown_ones(tmp_path):
    assert list(CLASSICS) == ["inward_2x2", "row_oscillator", "squeeze", "elliptic"]
    with pytest.raises(ValueError, match="'nope'.*inward_2x2"):
        reproduce(["nope"], tmp_path)
    res = CliRunner().invoke(app, ["reproduce", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "no classic result named 'nope'" in res.output
    assert not any(tmp_path.iterdir())


def test_reproduce_command_writes_the_figure_and_table_and_prints_the_comparison(tmp_path):
    res = CliRunner().invoke(app, ["reproduce", "inward_2x2", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "inward_2x2" in res.output and "reproduced" in res.output and "NOT" not in res.output
    assert (tmp_path / "inward_2x2" / "inward_2x2.png").exists()
    assert (tmp_path / "inward_2x2" / "inward_2x2.csv").exists()
