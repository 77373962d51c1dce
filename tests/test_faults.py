"""Broken hardware: faults listed or drawn at random do what they say, to the wheels, the contacts, the network and
the parcels."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_vehicle.config.scenario import FaultEvent, load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run


def _with_faults(name: str, **faults):
    sc, _ = load_scenario(name)
    return sc.model_copy(update={"faults": sc.faults.model_copy(update=faults)})


def test_listed_faults_hold_wheels_free_contacts_and_are_reported():
    sc = _with_faults("crossing_30x30", dead_cells=[5], stuck_wheels=[[7, 0]], free_wheels=[[9, 1]])
    sc = sc.model_copy(update={"friction": sc.friction.model_copy(update={"law": "coulomb"})})
    setup = sc.build()
    clean = load_scenario("crossing_30x30")[0].build()
    U = setup.cells.drive_directions
    assert np.all(setup.velocities[5] == 0) and np.any(clean.velocities[5] != 0)
    assert setup.velocities[7] @ U[7, 0] == 0 and setup.velocities[7] @ U[7, 1] == clean.velocities[7] @ U[7, 1]
    others = np.setdiff1d(np.arange(setup.cells.n), [5, 7])
    np.testing.assert_array_equal(setup.velocities[others], clean.velocities[others])
    assert setup.contact_layer.wheel_active[9].tolist() == [True, False]
    assert setup.contact_layer.wheel_active.sum() == 2 * setup.cells.n - 1
    faults = run(sc.model_copy(update={"duration": 0.1}).build()).summary()["faults"]
    assert faults["dead_cells"] == [5] and faults["stuck_wheels"] == [[7, 0]] and faults["free_wheels"] == [[9, 1]]


def test_random_faults_follow_their_rates_and_seed():
    sc = _with_faults("crossing_30x30", dead_cell_rate=0.1, stuck_wheel_rate=0.05, dead_link_rate=0.2,
                      stuck_sensor_rate=0.02, seed=3)
    f = sc.build().faults
    n = f.dead_cells.size  # 900 cells: binomial counts well inside 5 standard deviations
    for count, trials, rate in ((f.dead_cells.sum(), n, 0.1), (f.stuck_wheels.sum(), 2 * n, 0.05),
                                ((f.stuck_on | f.stuck_off).sum(), f.stuck_on.size, 0.02),
                                (len(f.dead_links), 2 * 30 * 29, 0.2)):
        assert abs(count - rate * trials) < 5 * np.sqrt(trials * rate * (1 - rate))
    assert f.stuck_on.sum() > 0 and f.stuck_off.sum() > 0 and not (f.stuck_on & f.stuck_off).any()
    again = sc.build().faults
    assert np.array_equal(again.dead_cells, f.dead_cells) and again.dead_links == f.dead_links
    other = sc.model_copy(update={"faults": sc.faults.model_copy(update={"seed": 4})}).build().faults
    assert not np.array_equal(other.dead_cells, f.dead_cells)
    assert not load_scenario("crossing_30x30")[0].build().faults.any()
    sensors = sc.build().sensors
    assert np.array_equal(sensors.stuck_on, f.stuck_on) and np.array_equal(sensors.stuck_off, f.stuck_off)


@pytest.mark.parametrize("kind", [None, "free_wheels", "stuck_wheels"])
def test_free_and_stuck_wheels_act_as_their_names_say(kind):
    """Stick-slip law, rollers running at 0.3 m/s along x, a carton sliding along x at 0.1 m/s. Sound wheels take it
    up to 0.3 m/s; free x-wheels give no friction along x, so it keeps 0.1 m/s (Newton's first law); held x-wheels
    grip the other way and stop it."""
    sc, _ = load_scenario("stick_slip_pickup")
    parcels = [sc.parcels[0].model_copy(update={"vx": 0.1})]
    n = sc.array.nx * sc.array.ny
    faults = sc.faults if kind is None else sc.faults.model_copy(update={kind: [[c, 0] for c in range(n)]})
    res = run(sc.model_copy(update={"duration": 0.3, "parcels": parcels, "faults": faults}).build())
    vx = res.parcels[0].trajectory.states[-1, 3]
    expected = {None: 0.3, "free_wheels": 0.1, "stuck_wheels": 0.0}[kind]
    assert vx == pytest.approx(expected, abs=1e-6)


def test_cells_sort_parcels_past_a_dead_cell_that_stays_silent_and_still():
    """A dead cell on the way east: the parcels are delivered as on a healthy array, those whose body goes over it
    carried by the live cells beside it; it never drives, sends nor hears."""
    sc = _with_faults("sorting_junction", dead_cells=[5 * 24 + 12])  # mid-array, on the way east
    sc = sc.model_copy(update={"duration": 20.0, "sensors": sc.sensors.model_copy(update={"record": True})})
    res = run(sc.build())
    so = res.summary()["sorting"]
    assert so["misrouted"] == 0 and so["lost"] == 0 and so["collisions"] == 0 and so["correct"] >= 3
    log = res.cell_log
    dead = 5 * 24 + 12
    assert np.all(log.wheels[:, dead] == 0) and log.sent[:, dead].sum() == 0 and log.received[:, dead].sum() == 0
    assert res.network.per_cell["cell_sent"][dead] == 0


def test_bad_faults_are_named():
    with pytest.raises(ScenarioError, match=r"faults\.dead_cells\[0\]"):
        _with_faults("crossing_30x30", dead_cells=[900]).build()
    with pytest.raises(ScenarioError, match="free-spinning wheels need"):
        sc = _with_faults("paper_2x2_inward", free_wheels=[[0, 0]])
        sc.model_copy(update={"friction": sc.friction.model_copy(update={"law": "viscous"})}).build()
    with pytest.raises(ScenarioError, match="dead_link_rate"):
        from virtual_vehicle.config.scenario import parse_text

        parse_text(load_scenario("crossing_30x30")[1] + "\n[faults]\ndead_link_rate = 2.0\n")


def test_the_fault_study_measures_delivery_against_failure_rate(tmp_path):
    import json

    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app

    out = tmp_path / "study"
    res = CliRunner().invoke(app, ["fault-study", "sorting_junction", "--rates", "0,0.3", "--samples", "2",
                                   "--duration", "14", "--out", str(out), "--workers", "2"])
    assert res.exit_code == 0, res.output
    study = json.loads((out / "study.json").read_text())
    clean, broken = study["rows"]
    assert (clean["rate"], broken["rate"]) == (0.0, 0.3) and clean["runs"] == broken["runs"] == 2
    # at rate 0 both seeds draw no fault: one run, counted for each; at 30 % two draws, two runs
    assert (clean["distinct_runs"], broken["distinct_runs"]) == (1, 2)
    assert len(list((out / "runs").glob("*.json"))) == 3
    sc, _ = load_scenario("sorting_junction")
    direct = run(sc.model_copy(update={"duration": 14.0}).build()).summary()["sorting"]
    due = sum(p.t_start <= 14.0 for p in sc.parcels)
    assert clean["parcels_due"] == due < len(sc.parcels)
    assert clean["delivered_fraction"] == pytest.approx(direct["correct"] / due)
    assert clean["delivered_fraction_std"] == 0.0 and clean["delivered_fraction"] > 0
    assert broken["delivered_fraction"] < clean["delivered_fraction"]  # 30% of the cells dead
    for row in (clean, broken):  # each kept draw's own figure, whose mean the row gives
        draws = row["draws"]
        assert draws["seed"] == sorted(draws["seed"]) and set(draws["seed"]) <= {0, 1}
        assert len(draws["delivered_fraction"]) == row["runs"] - row["failed"] - row["unreachable"]
        assert np.mean(draws["delivered_fraction"]) == pytest.approx(row["delivered_fraction"])
    assert clean["draws"]["delivered_fraction"] == [pytest.approx(direct["correct"] / due)] * 2
    # the parcels due but neither delivered nor lost: still on the array, or never put on
    assert clean["stuck"] == clean["on_array"] + clean["waiting"] == direct["on_array"] + direct["waiting"] - (
        len(sc.parcels) - due)
    assert all(0 <= r["stuck"] <= due for r in (clean, broken))
    assert (out / "study.png").stat().st_size > 10_000 and (out / "summary.parquet").is_file()


def test_a_fault_study_of_a_scenario_file_is_titled_by_the_scenario_s_name(tmp_path):
    """A study of a scenario file names the scenario (its ``name``), not the file's path, in its table and picture."""
    import json

    from typer.testing import CliRunner

    from virtual_vehicle.config.scenario import dump_toml
    from virtual_vehicle.ui.cli import app

    sc, _ = load_scenario("sorting_junction")
    path = tmp_path / "somewhere" / "my.toml"
    path.parent.mkdir()
    path.write_text(dump_toml(sc.model_copy(update={"name": "hall_b_west"})), encoding="utf-8")
    out = tmp_path / "study"
    res = CliRunner().invoke(app, ["fault-study", str(path), "--rates", "0", "--samples", "1", "--duration", "1",
                                   "--out", str(out), "--workers", "1"], terminal_width=200)
    assert res.exit_code == 0, res.output
    assert "hall_b_west: dead_cell_rate" in res.output and "somewhere" not in res.output
    assert json.loads((out / "study.json").read_text())["scenario"] == "hall_b_west"


@pytest.mark.parametrize("args, message", [
    (["sorting_junction", "--kind", "bad_rate"], "not a fault rate"),
    (["prototype_18"], "sorting scenario"),
    (["sorting_junction", "--rates", "0,x"], "--rates"),
    (["sorting_junction", "--rates", "1.5"], "rates in [0, 1]"),
])
def test_bad_fault_studies_exit_2(tmp_path, args, message):
    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app

    res = CliRunner().invoke(app, ["fault-study", *args, "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and message in res.output, res.output


def _inject(sc, **event):
    return sc.model_copy(update={"faults": sc.faults.model_copy(update={"events": [FaultEvent(**event)]})})


def test_a_cell_that_dies_mid_run_goes_silent_and_still_from_then_on(tmp_path):
    sc, _ = load_scenario("sorting_junction")
    dead = 5 * 24 + 12
    sc = _inject(sc.model_copy(update={"duration": 20.0, "sensors": sc.sensors.model_copy(update={"record": True})}),
                 t=6.0, dead_cells=[dead], stuck_on=[[0, 0]])
    res = run(sc.build())
    log = res.cell_log
    before, after = log.t < 6.0 - 1e-9, log.t >= 6.0 - 1e-9
    assert log.sent[before, dead].sum() > 0 and log.sent[after, dead].sum() == 0
    assert log.received[after, dead].sum() == 0 and np.all(log.wheels[after, dead] == 0)
    assert not log.readings[before, 0, 0].all() and log.readings[after, 0, 0].all()  # the stuck sensor
    (event,) = res.summary()["faults_injected"]
    assert event["t_s"] == 6.0 and event["dead_cells"] == [dead] and event["stuck_on_sensors"] == [[0, 0]]
    so = res.summary()["sorting"]
    assert so["misrouted"] == 0 and so["collisions"] == 0 and so["lost"] == 0 and so["correct"] >= 3
    # the same run, checkpointed across the event and resumed, ends the same
    from virtual_vehicle.run.sim import resume

    whole = run(sc.build(), checkpoint=tmp_path / "c.ckpt", checkpoint_every=8.0)
    again = resume(tmp_path / "c.ckpt")
    for a, b in zip(whole.parcels, again.parcels):
        assert np.array_equal(a.trajectory.states, b.trajectory.states)


def test_a_revived_cell_talks_and_drives_again():
    sc, _ = load_scenario("sorting_junction")
    cell = 5 * 24 + 12
    events = [FaultEvent(t=2.0, dead_cells=[cell]), FaultEvent(t=4.0, revived_cells=[cell])]
    sc = sc.model_copy(update={"duration": 6.0, "sensors": sc.sensors.model_copy(update={"record": True}),
                               "faults": sc.faults.model_copy(update={"events": events})})
    log = run(sc.build()).cell_log
    dead, back = (log.t >= 2.0 - 1e-9) & (log.t < 4.0 - 1e-9), log.t >= 4.0 - 1e-9
    assert log.sent[dead, cell].sum() == 0 and log.sent[back, cell].sum() > 0


@pytest.mark.parametrize("name, event, message", [
    ("sorting_junction", {"t": 50.0, "dead_cells": [1]}, "not before the end"),
    ("sorting_junction", {"t": 1.0, "dead_cells": [9999]}, r"faults\.events\[0\]\.dead_cells\[0\]"),
    ("sorting_junction", {"t": 1.0, "stuck_on": [[0, 7]]}, "no sensor 7"),
    ("crossing_30x30", {"t": 1.0, "dead_cells": [1]}, "need \\[control\\]"),
    ("sorting_junction", {"t": 1.0, "dead_cells": [3], "revived_cells": [3]}, "the same event kills"),
    ("sorting_junction", {"t": 1.0, "revived_cells": [9999]}, r"revived_cells\[0\]"),
])
def test_bad_fault_events_are_named(name, event, message):
    with pytest.raises(ScenarioError, match=message):
        _inject(load_scenario(name)[0], **event).build()


@pytest.mark.parametrize("law", ["viscous", "stick_slip"])
def test_a_parcel_passes_over_a_line_of_dead_cells_and_the_run_reports_it(law):
    """Redundancy the other way: under a constant field a parcel is simply carried over broken cells. A dead cell
    still carries weight and holds its wheels still, so under the viscous law (eq. 30; crossing_30x30's former
    1 s/m) it brakes the parcel while under it: the parcel arrives, later than on a healthy array. Under stick-slip
    (the scenario's own law) the dead column's cells (a quarter of those under the carton) drag with mu N each while
    the healthy ones can hold with up to mu_static N each, so the parcel rides on at exactly the wheel speed."""
    def on_law(sc):
        if law == "stick_slip":
            return sc
        return sc.model_copy(update={"friction": sc.friction.model_copy(update={"law": law}),
                                     "parcels": [p.model_copy(update={"mu": 1.0, "mu_static": None})
                                                 for p in sc.parcels]})

    column = [j * 30 + 10 for j in range(30)]  # x = 1.0 m, every row
    sc = on_law(_with_faults("crossing_30x30", dead_cells=column))
    broken = run(sc.build())
    healthy = run(on_law(load_scenario("crossing_30x30")[0]).build())
    end, clean = broken.parcels[0].trajectory.states[-1], healthy.parcels[0].trajectory.states[-1]
    assert end[0] > 1.3 and broken.parcels[0].trajectory.status == "completed"  # passed over the dead column
    if law == "viscous":
        assert clean[0] - end[0] > 1e-3  # held back while the dead cells were under it
    else:
        np.testing.assert_allclose(end, clean, rtol=0, atol=1e-9)  # held at the wheel speed by the healthy cells
    row = broken.summary()["parcels"][0]
    assert row["name"] == "carton" and row["status"] == "completed" and row["tipped_at_s"] is None
    assert row["path_length_m"] > 0.8
    assert broken.summary()["faults"]["dead_cells"] == column


def test_a_cell_dies_mid_run_over_the_wire_model():
    """Under the paper's RS232 hardware a cell that dies loses its queue and its transfers; its neighbours' sentences
    to it time out and are dropped; the rest of the array goes on talking."""
    sc, _ = load_scenario("prototype_18_network")
    dead = 8  # middle row
    sc = _inject(sc.model_copy(update={"duration": 3.0, "sensors": sc.sensors.model_copy(update={"record": True})}),
                 t=1.0, dead_cells=[dead])
    res = run(sc.build())
    log = res.cell_log
    before, after = log.t < 1.0 - 1e-9, log.t >= 1.0 - 1e-9
    assert log.sent[before, dead].sum() > 0 and log.received[before, dead].sum() > 0
    assert log.sent[after, dead].sum() == 0 and log.received[after, dead].sum() == 0
    assert np.all(log.wheels[after, dead] == 0)
    alive = np.setdiff1d(np.arange(18), [dead])
    assert log.received[after][:, alive].sum() > 0
    net = res.network.per_tick
    t_net = net["t"]
    rate = [net["dropped"][m].sum() / m.sum() for m in (t_net < 1.0 - 1e-9, t_net >= 1.0 - 1e-9)]
    assert rate[1] > rate[0]  # sentences for the dead cell give up
    assert res.summary()["faults_injected"][0]["dead_cells"] == [dead]


def test_a_fault_draw_that_cuts_an_exit_off_is_told_apart():
    """The fault study's draw filter: every exit reachable from an entry over live cells and links, or not. A wall
    of dead cells across the array between the entry (west) and the exits (east and north) cuts them all off; with
    a gap in the wall they are reachable again, and a wall around the north exit's lane alone cuts only that one."""
    from virtual_vehicle.analysis.sweep import exits_reachable

    sc, _ = load_scenario("sorting_junction")  # 24 x 12 cells, cell id = row * 24 + column

    def with_dead(cells):
        return sc.model_copy(update={"faults": sc.faults.model_copy(update={"dead_cells": cells})})

    wall = [row * 24 + 10 for row in range(12)]
    assert exits_reachable(sc, "dead_cell_rate", 0.0, 0)
    assert not exits_reachable(with_dead(wall), "dead_cell_rate", 0.0, 0)
    assert exits_reachable(with_dead(wall[:-1]), "dead_cell_rate", 0.0, 0)
    # the north exit's lane is columns 14-17 of rows 8-11: dead cells on its three inner sides
    around = [row * 24 + col for row in (8, 9, 10, 11) for col in (13, 18)] + [7 * 24 + c for c in range(13, 19)]
    assert not exits_reachable(with_dead(around), "dead_cell_rate", 0.0, 0)
    assert exits_reachable(with_dead([c for c in around if c != 7 * 24 + 15]), "dead_cell_rate", 0.0, 0)
    assert exits_reachable(sc, "stuck_wheel_rate", 0.5, 1)  # held wheels cut no way


def test_dead_cells_beside_an_exit_lane_do_not_move_its_way_out():
    """An exit's way out is the side its cells have no neighbour installed on: dead cells all along the south side
    of the north exit's lane are no way out, and the lane still leaves north (judged from the live links, the dead
    south side tied with the north edge and the scenario failed to build)."""
    sc, _ = load_scenario("sorting_junction")
    cfg = sc.build().control.config
    lane = np.flatnonzero(cfg["exit"] == 2)
    bottom = lane[(lane // 24) == (lane // 24).min()]
    dead = (bottom - 24).tolist()  # the cells just south of the lane's bottom row
    setup = sc.model_copy(update={"faults": sc.faults.model_copy(update={"dead_cells": dead})}).build()
    cfg = setup.control.config
    assert len(dead) == 4 and set(cfg["exit_port"][cfg["exit"] == 2].tolist()) == {1}  # port 1: +y, north


def test_parcels_pass_a_fence_of_dead_cells_whose_gaps_are_narrower_than_they_are():
    """A vehicle passes over a dead cell while the live cells beside it carry it: a fence of dead cells across the
    whole junction (column 10, every other row) leaves only gaps of one cell, narrower than every parcel (22-30 cm on
    10 cm cells), so every way to an exit runs over dead cells. Each dead cell's live neighbour across the vehicle
    carries it (a dead cell brakes with mu N, the live ones hold with up to mu_static N each), the parcels are
    delivered, none collides, and the dead cells stay silent and still."""
    import shapely

    fence = [row * 24 + 10 for row in range(0, 12, 2)]
    sc = _with_faults("sorting_junction", dead_cells=fence)
    sc = sc.model_copy(update={"duration": 14.0, "sensors": sc.sensors.model_copy(update={"record": True})})
    res = run(sc.build())
    so = res.summary()["sorting"]
    assert so["collisions"] == 0 and so["misrouted"] == 0 and so["lost"] == 0
    assert so["correct"] >= 2
    centres = [shapely.Point(res.setup.cells.positions[c]) for c in fence]
    over = [pr.spec.name for pr in res.parcels if any(pr.spec.world_polygon(y).contains(p)
                                                       for y in pr.trajectory.states for p in centres)]
    assert len(over) >= so["correct"]  # every delivered parcel went over a dead cell
    assert np.all(res.cell_log.wheels[:, fence] == 0) and res.cell_log.sent[:, fence].sum() == 0


def _first_parcel_delivered_past(dead: list[int]) -> None:
    """The junction with cells ``dead`` (row * 24 + column) for 12 s: its first parcel is delivered at its exit, with
    no collision, misroute or loss."""
    sc = _with_faults("sorting_junction", dead_cells=dead)
    res = run(sc.model_copy(update={"duration": 12.0}).build())
    so = res.summary()["sorting"]
    first = res.summary()["parcels"][0]
    assert first["name"] == "p00" and first["outcome"] == "delivered" and first["exit"] == 0
    assert so["collisions"] == 0 and so["misrouted"] == 0 and so["lost"] == 0


def test_a_vehicle_beside_its_lane_with_dead_cells_on_that_side_moves_along_before_it_turns_in():
    """The north-east exit's lane (columns 20-23 of rows 7-10, leaving east) with dead cells just west of its
    first row (columns 17-19 of row 7) and two more south of the way there (the 5 % fault draw seed 7 there): the
    first parcel, heading east on rows 4-6, reaches the lane's corner cell with its north-east corner while the
    cells of its body north of it face dead cells with no live cell beside. The corner cell pulls it north into
    the lane only once that side is open to the whole vehicle: it used to pull at once, the body's cell facing the
    dead wall said stop, and the parcel stood still there for the rest of the run (0 delivered in 20 s)."""
    dead = [3 * 24 + 18, 4 * 24 + 18, 7 * 24 + 17, 7 * 24 + 18, 7 * 24 + 19, 9 * 24 + 19]  # row * 24 + column
    _first_parcel_delivered_past(dead)


def test_a_parcel_does_not_drive_a_second_dead_cell_under_it_in_line_with_the_first():
    """The first parcel covers four cells at the entry, one of them dead ((2, 6)), and (3, 6) east of it is dead
    too (the 10 % fault draw seed 19 there): driving east put both under it, half its weight on held wheels, which
    hold with up to mu_static N while the live ones slide with mu N, and it stood from 0.75 s for the rest of the
    run. The cell beside the dead one under the body hears the live cell ahead say a dead neighbour on the same
    side, the way east closes to the vehicle and the gradient leads it round."""
    dead = [6 * 24 + 2, 6 * 24 + 3]  # row * 24 + column
    _first_parcel_delivered_past(dead)


def _carton_over_dead_front(dead_wheels: str, duration: float = 0.1):
    """A 0.18 m square carton (1 kg, mu 0.4, mu_static 0.5) put down at rest on the four cells centred at x = 0.3,
    0.4 m and y = 0.1, 0.2 m of a 10 x 4 grid at 0.1 m pitch, rollers running at 0.3 m/s along x under stick-slip;
    the two cells of its front column dead."""
    front = [1 * 10 + 4, 2 * 10 + 4]  # cell id = row * nx + column; column 4 is x = 0.4 m
    table = {"name": "dead_front", "duration": duration, "output_dt": 0.01,
             "array": {"kind": "grid", "nx": 10, "ny": 4, "pitch": 0.1},
             "field": {"kind": "uniform", "velocity": [0.3, 0.0]}, "friction": {"law": "stick_slip"},
             "faults": {"dead_cells": front, "dead_wheels": dead_wheels},
             "parcels": [{"name": "carton", "length": 0.18, "width": 0.18, "mass": 1.0, "mu": 0.4,
                          "mu_static": 0.5, "x": 0.35, "y": 0.15}]}
    return parse_scenario(table)


def test_a_dead_cell_s_held_wheels_stop_a_parcel_its_free_wheels_let_pass():
    """What a dead cell's wheels do decides whether its neighbours can carry a parcel over it (paper Section 1:
    "simply passing parcels over" a broken cell). Closed forms: the carton's weight W is shared by its rear (live)
    and front (dead) columns as its centre of mass lies between them (eq. 19: the rear bears (0.4 - x) / 0.1 of it,
    half at the start). With the dead wheels held, the rear's slipping wheels push with mu W / 2 = 1.96 N against up
    to mu_static W / 2 = 2.45 N of static grip, and the carton stays where it was put. With them free (``dead_wheels
    = "free"``: back-drivable) nothing holds it, and the rear's slipping wheels push with mu W (0.4 - x) / 0.1 (eq.
    22): x'' = -(mu g / 0.1) (x - 0.4), a harmonic pull toward the dead column, so x = 0.4 - 0.05 cos(w t) with w =
    sqrt(mu g / 0.1) while the wheels outrun it (0.18 m/s at 0.1 s, on the same four cells)."""
    g, mu, t = 9.81, 0.4, 0.1
    held = run(_carton_over_dead_front("held").build()).parcels[0].trajectory.states[-1]
    np.testing.assert_allclose(held, [0.35, 0.15, 0.0, 0.0, 0.0, 0.0], atol=1e-9)
    free_setup = _carton_over_dead_front("free").build()
    assert free_setup.faults.free_wheels[[14, 24]].all() and free_setup.faults.free_wheels.sum() == 4
    free = run(free_setup).parcels[0].trajectory.states[-1]
    w = np.sqrt(mu * g / 0.1)
    np.testing.assert_allclose(free, [0.4 - 0.05 * np.cos(w * t), 0.15, 0.0, 0.05 * w * np.sin(w * t), 0.0, 0.0],
                               atol=1e-9)


def test_free_dead_wheels_keep_the_fault_draws_and_refuse_what_they_cannot_model():
    """``dead_wheels = "free"`` draws no random number (the dead cells of a seed are those of ``"held"``), leaves a
    stuck wheel of a dead cell held, and is refused where it cannot be modelled: the viscous law (no free
    direction), events that kill or revive cells (their contacts are built once), hexagonal cells."""
    sc = _with_faults("sorting_junction", dead_cell_rate=0.1, stuck_wheel_rate=0.3, seed=4)
    held = sc.build().faults
    free = sc.model_copy(update={"faults": sc.faults.model_copy(update={"dead_wheels": "free"})}).build().faults
    assert np.array_equal(held.dead_cells, free.dead_cells) and np.array_equal(held.stuck_wheels, free.stuck_wheels)
    expected = held.free_wheels | (held.dead_cells[:, None] & ~held.stuck_wheels)
    assert np.array_equal(free.free_wheels, expected) and (held.dead_cells[:, None] & held.stuck_wheels).any()
    viscous = _carton_over_dead_front("free")
    viscous = viscous.model_copy(update={"friction": viscous.friction.model_copy(update={"law": "viscous"})})
    with pytest.raises(ScenarioError, match="faults"):
        viscous.build()
    killing = _with_faults("sorting_junction", dead_wheels="free",
                           events=[FaultEvent(t=1.0, dead_cells=[30])])
    with pytest.raises(ScenarioError, match=r"faults\.dead_wheels.*from the start"):
        killing.build()
    hexes = _with_faults("hex_sorting_junction", dead_cells=[3], dead_wheels="free")
    with pytest.raises(ScenarioError, match=r"faults\.dead_wheels.*hexagonal"):
        hexes.build()
