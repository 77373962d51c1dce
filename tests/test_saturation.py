"""Saturation throughput: with ``arrivals = "saturate"`` every entry is fed as fast as it accepts, and the sorting
report gives parcels per hour per entry against the kinematic bound, for the distributed sorter and the central
reservation router; the figures are those of the run's per-parcel table."""

import numpy as np
import pytest

from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def saturated(program="sort", duration=16.0):
    sc, _ = load_scenario("sorting_junction")
    data = sc.model_dump(mode="json", exclude_defaults=True) | {"duration": duration, "arrivals": "saturate"}
    data["control"]["program"] = program
    return parse_scenario(data)


@pytest.mark.parametrize("program", ["sort", "reserve"])
def test_saturation_throughput_is_that_of_the_parcel_table(program):
    result = run(saturated(program).build())
    report = sorting_report(result)
    assert report["collisions"] == 0 and report["misrouted"] == 0 and report["lost"] == 0
    sat = result.summary()["sorting"]["saturation"]
    (entry,) = sat["entries"]  # the junction has one entry
    rows = result.summary()["parcels"]
    fed = sorted(r["entered_at_s"] for r in rows if r["entered_at_s"] is not None)
    out = sorted(r["entered_at_s"] + r["delivery_time_s"] for r in rows if r["correct"])
    assert fed[0] == 0.0 and len(out) >= 3
    assert entry["fed"] == len(fed) and entry["delivered"] == len(out)
    assert entry["delivered_per_hour"] == pytest.approx((len(out) - 1) / (out[-1] - out[0]) * 3600)
    assert entry["fed_per_hour"] == pytest.approx((len(fed) - 1) / (fed[-1] - fed[0]) * 3600)
    sc = result.setup.scenario
    length = np.mean([max(p.length, p.width) for p in sc.parcels])
    assert entry["bound_per_hour"] == pytest.approx(0.3 / (length + 2 * 0.1) * 3600)
    assert 0.3 < entry["fraction"] < 1.0  # a stream slower than the wheels allow, but not by much
    # saturated, the entry takes the next parcel as soon as the last has made room, whenever that is
    assert entry["fed"] >= 6


def test_each_entry_has_its_own_queue():
    """Two entries fed at once: each puts its first parcel on at the start, whatever the other's queue does."""
    rows = [["o"] * 24 for _ in range(12)]
    for k in (4, 5, 6):
        rows[k][1] = rows[k][2] = "E"
    for c in (10, 11, 12):
        rows[11][c] = "E"
    for k in (4, 5, 6, 7):
        rows[k][23] = "0"
    parcels = [{"name": f"{side}{k}", "length": 0.25, "width": 0.22, "mass": 1.0, "mu": 2.0, "x": x, "y": y,
                "destination": 0} for k in range(3) for side, x, y in (("w", 0.2, 0.5), ("n", 1.1, 1.0))]
    sc = parse_scenario({"name": "two_entries", "duration": 4.0, "arrivals": "saturate",
                         "array": {"kind": "map", "pitch": 0.1,
                                   "map": "\n".join("".join(row) for row in reversed(rows))},
                         "control": {"program": "sort", "speed": 0.3}, "friction": {"law": "viscous"},
                         "parcels": parcels})
    result = run(sc.build())
    entered = {p.spec.name: p.entered_at for p in result.parcels}
    assert entered["w0"] == 0.0 and entered["n0"] == 0.0
    assert entered["w1"] is None or entered["w1"] > 0  # behind the first at its own place
    assert len(sorting_report(result)["saturation"]["entries"]) == 2


def test_saturating_needs_a_networked_run():
    data = {"duration": 1.0, "arrivals": "saturate", "array": {"kind": "row", "n": 8, "pitch": 0.1},
            "field": {"kind": "uniform", "velocity": [0.1, 0.0]},
            "parcels": [{"name": "box", "length": 0.25, "width": 0.1, "mass": 1.0, "mu": 0.5, "x": 0.25, "y": 0.0}]}
    with pytest.raises(ScenarioError, match="arrivals"):
        parse_scenario(data).build()


def test_run_saturate_on_the_command_line(tmp_path):
    import json

    from typer.testing import CliRunner

    from virtual_vehicle.config.scenario import dump_toml
    from virtual_vehicle.ui.cli import app

    sc, _ = load_scenario("sorting_junction")
    path = tmp_path / "short.toml"
    path.write_text(dump_toml(sc.model_copy(update={"duration": 3.0, "parcels": sc.parcels[:4]})))
    out = CliRunner().invoke(app, ["run", str(path), "--saturate", "--no-plot", "-o", str(tmp_path / "run")])
    assert out.exit_code == 0, out.output
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    entry = summary["sorting"]["saturation"]["entries"][0]
    assert entry["fed"] >= 1 and entry["bound_per_hour"] > 0
    assert 'arrivals = "saturate"' in (tmp_path / "run" / "scenario.toml").read_text()
