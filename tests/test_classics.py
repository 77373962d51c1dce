"""The field's classic results (issue 35), each against its source's own statement: the seed paper's 2x2 inward
field and end-reversed row, squeeze fields (Böhringer, Donald et al. 1994), elliptic fields (Kavraki 1997), the
orientation lost to discreteness (Luntz, Messner, Choset 2001), the stick-slip law against the paper's laws, and the
``reproduce`` command. Tolerances are those the sources allow (closed forms: numerical; continuous theories on a
discrete array: a few degrees at 5 mm cells under 80 mm parts)."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from virtual_vehicle.analysis.classics import CLASSICS, reproduce
from virtual_vehicle.analysis.classics import elliptic, laws, orientation, seed_paper, squeeze
from virtual_vehicle.engine.dynamics import ParcelModel
from virtual_vehicle.physics.laws import LAWS
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


def test_open_loop_field_positions_exactly_on_a_discrete_array():
    """The designed field is linear, so with the normal forces balancing the weight and its moment (eqs. 4-5) the
    force on a part at rest is mu W times the field at its centre of mass, whatever cells carry it (eq. 30)."""
    cells = orientation.array_around((0.5, 0.5, 0.3), 0.12, orientation.PITCH)
    for spec in orientation.family(4):
        v = orientation.design_field(cells.positions, spec, (0.5, 0.5, 0.3))
        model = ParcelModel(cells, spec, v, LAWS["viscous"])
        for pose in ((0.47, 0.53, 0.1), (0.55, 0.44, 1.2), (0.5, 0.5, -0.4)):
            y = np.array([*pose, 0.0, 0.0, 0.0])
            acc = model.piece_at(y).rhs(0.0, y)
            expected = spec.mu * spec.weight(G) * orientation.design_field(np.array([pose[:2]]), spec,
                                                                           (0.5, 0.5, 0.3))[0]
            np.testing.assert_allclose(acc[3:5] * spec.mass, expected, rtol=1e-9, atol=1e-12)


def test_discreteness_destabilises_orientation_and_closed_loop_restores_it(tmp_path):
    """Luntz, Messner, Choset 2001: the field that orients every part on a (here 5 mm) fine array leaves the target
    heading unstable for many parts on 5 cm cells; open loop then positions precisely but orients poorly, and the
    pose program on the cells' own sensors brings the heading back within a few degrees."""
    r = orientation.discreteness_orientation(tmp_path, parts=6)
    n = r.numbers
    assert n["parts_not_tipping"] == 6
    assert n["fraction_target_unstable_fine"] == 0 and n["nearest_stable_fine_max_deg"] < 1.5
    assert n["fraction_target_unstable_discrete"] >= 1 / 3
    assert n["open_position_max_mm"] < 0.1 and n["open_heading_mean_deg"] > 3
    assert n["closed_heading_mean_deg"] < 0.5 * n["open_heading_mean_deg"] and n["closed_heading_max_deg"] < 4
    rows = read_csv(tmp_path / "orientation.csv")
    assert len(rows) == 6 and sum(x["target_unstable_discrete"] == "1" for x in rows) >= 2
    assert (tmp_path / "orientation.png").stat().st_size > 10_000 and r.passed


def test_coulomb_runs_away_stick_slip_rides_at_wheel_speed_viscous_relaxes(tmp_path):
    """A parcel put down at rest on wheels at V: the paper's Coulomb law accelerates it at mu g past V for ever;
    stick-slip accelerates it at mu g until V / (mu g) and then holds it at V exactly; viscous approaches V as
    V (1 - exp(-mu g t)) and stays below it."""
    r = laws.realistic_law(tmp_path, duration=0.4)
    for scene in ("stick_slip_pickup", "crossing_30x30"):
        c, s, v = (r.numbers[scene][law] for law in ("coulomb", "stick_slip", "viscous"))
        assert c["max_speed_over_wheel"] > 2 and c["acceleration_over_mu_g"] == pytest.approx(1, rel=1e-3)
        assert s["slip_acceleration_over_mu_g"] == pytest.approx(1, rel=1e-3)
        assert s["speed_after_pickup_max_error_m_per_s"] < 1e-12 and s["max_speed_over_wheel"] < 1 + 1e-12
        assert v["max_speed_over_wheel"] < 1 and v["max_error_to_closed_form_m_per_s"] < 1e-7
    rows = read_csv(tmp_path / "realistic_law.csv")
    after = [float(x["vx"]) for x in rows if x["law"] == "stick_slip" and x["scene"] == "stick_slip_pickup"
             and float(x["t"]) > 0.1]
    assert after and all(v == 0.3 for v in after)
    assert (tmp_path / "realistic_law.png").stat().st_size > 10_000 and r.passed


def test_reproduce_names_the_results_and_refuses_unknown_ones(tmp_path):
    assert list(CLASSICS) == ["inward_2x2", "row_oscillator", "squeeze", "elliptic", "orientation", "realistic_law"]
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
