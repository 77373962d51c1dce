"""Pictures show what went wrong: stuck parcels, dead cells, entries and exits, honest axes, arrays of any size."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_vehicle.ui import viz


def _fault_rows():
    """A fault study whose deliveries fall while nothing collides, is misrouted or lost (issue 30)."""
    return [dict(rate=r, runs=5, failed=0, parcels_due=20, delivered_fraction=f, delivered_fraction_std=0.05,
                 delivery_time_mean_s=t, collisions=0.0, misrouted=0.0, lost=0.0)
            for r, f, t in [(0.0, 0.67, 9.375), (0.02, 0.41, 9.5), (0.05, 0.09, 9.55)]]


def test_the_fault_study_picture_shows_the_stuck_parcels_and_starts_its_axes_at_zero():
    fig = viz.plot_fault_study(_fault_rows(), "dead_cell_rate", "study")
    bars = {c.get_label(): [p.get_height() for p in c.patches] for ax in fig.axes for c in ax.containers
            if hasattr(c, "patches")}
    stuck = next(v for k, v in bars.items() if k.startswith("stuck"))
    np.testing.assert_allclose(stuck, [20 * 0.33, 20 * 0.59, 20 * 0.91])
    delivered = bars["delivered to the right exit"]
    np.testing.assert_allclose(np.add(stuck, delivered), 20)  # every parcel due is accounted for
    time_ax = next(ax for ax in fig.axes if ax.get_ylabel() == "delivery time (s)")
    assert time_ax.get_ylim()[0] == 0.0 and time_ax.get_ylim()[1] >= 9.55  # 9.375..9.55 s is not a drama


def test_the_fault_study_splits_stuck_parcels_when_the_table_has_the_columns():
    rows = [dict(r, on_array=4.0, waiting=r["parcels_due"] * (1 - r["delivered_fraction"]) - 4.0)
            for r in _fault_rows()]
    out = viz.fault_study_outcomes(rows)
    assert set(out) == {"delivered", "misrouted", "lost", "on_array", "waiting"}
    np.testing.assert_allclose(sum(out.values()), 20)


def test_the_fault_study_picture_shows_deadlocked_parcels_apart_from_those_waiting():
    rows = [dict(r, on_array=4.0, deadlocked=float(k), waiting=r["parcels_due"] * (1 - r["delivered_fraction"]) - 4.0)
            for k, r in enumerate(_fault_rows())]
    out = viz.fault_study_outcomes(rows)
    np.testing.assert_allclose(out["deadlocked"], [0, 1, 2])
    np.testing.assert_allclose(out["on_array"], [4, 3, 2])  # the rest of those on the array
    np.testing.assert_allclose(sum(out.values()), 20)
    fig = viz.plot_fault_study(rows, "dead_cell_rate", "study")
    labels = {c.get_label() for ax in fig.axes for c in ax.containers if hasattr(c, "patches")}
    assert {"deadlocked (a cycle of holds)", "waiting on the array at the end", "never put on (entry blocked)",
            "delivered to the right exit"} <= labels


def _delivered_axis(fig):
    return next(ax for ax in fig.axes if ax.get_ylabel() == "fraction delivered to the right exit")


def test_the_fault_study_picture_shows_each_draw_where_the_draws_split():
    """At 10 % dead cells some draws deliver nearly all and others nothing: each draw is a dot, the mean a line;
    the mean +- one standard deviation (0.45 +- 0.5 here) would reach below nothing and above everything."""
    rows = [dict(r, draws={"seed": [0, 1, 2, 3], "delivered_fraction": f}, delivered_fraction=float(np.mean(f)),
                 delivered_fraction_std=float(np.std(f)))
            for r, f in zip(_fault_rows(), [[1.0, 1.0, 1.0, 0.95], [1.0, 0.9, 0.1, 0.95], [0.0, 0.9, 0.0, 0.9]])]
    ax = _delivered_axis(viz.plot_fault_study(rows, "dead_cell_rate", "study"))
    dots = next(line for line in ax.lines if line.get_label() == "one fault draw")
    assert len(dots.get_ydata()) == 4 and sorted(dots.get_ydata()) == [0.95, 1.0, 1.0, 1.0]  # the first rate's
    seen = sorted(y for line in ax.lines if line.get_marker() == "o" for y in line.get_ydata())
    assert seen == sorted(y for r in rows for y in r["draws"]["delivered_fraction"])
    mean = next(line for line in ax.lines if line.get_label() == "mean over the draws")
    np.testing.assert_allclose(mean.get_ydata(), [r["delivered_fraction"] for r in rows])
    assert not ax.containers  # no error bars


def test_the_fault_study_picture_cuts_a_deviation_at_what_a_fraction_can_be():
    """Rows without their draws (a study.json from before they were kept): one standard deviation, within [0, 1]."""
    rows = [dict(r, delivered_fraction=f, delivered_fraction_std=0.5) for r, f in zip(_fault_rows(), [1.0, 0.45, 0.1])]
    ax = _delivered_axis(viz.plot_fault_study(rows, "dead_cell_rate", "study"))
    (_, caps, (segments,)), = [c for c in ax.containers]
    ends = np.concatenate([seg[:, 1] for seg in segments.get_segments()])
    assert ends.min() == 0.0 and ends.max() == 1.0


def test_a_one_rate_fault_study_has_an_axis_about_its_rate():
    rows = [dict(_fault_rows()[1], draws={"seed": [0, 1], "delivered_fraction": [0.5, 0.3]})]
    fig = viz.plot_fault_study(rows, "dead_cell_rate", "study")
    ax = _delivered_axis(fig)
    assert ax.get_xlim() == (0.01, 0.03)
    time_ax = next(a for a in fig.axes if a.get_ylabel() == "delivery time (s)")
    assert time_ax.get_xlim() == (0.01, 0.03)
    dots = next(line for line in ax.lines if line.get_label() == "one fault draw")
    assert 0.019 < min(dots.get_xdata()) < max(dots.get_xdata()) < 0.021  # the draws side by side at the rate


def _built(name: str, duration: float, **update):
    from virtual_vehicle.config.scenario import load_scenario

    sc, _ = load_scenario(name)
    parts = {}
    for key, value in update.items():
        parts[key] = getattr(sc, key).model_copy(update=value)
    return sc.model_copy(update={"duration": duration, **parts}).build()


@pytest.fixture(scope="module")
def dead_field_run():
    from virtual_vehicle.run.sim import run

    return run(_built("prototype_18", 0.2, faults={"dead_cells": [7]}))


def _labelled(ax, label):
    return [c for c in ax.collections if c.get_label() == label]


def test_dead_cells_are_crossed_out_and_start_and_end_outlines_are_in_the_legend(dead_field_run):
    fig = viz.plot_paths(dead_field_run)
    ax = fig.axes[0]
    (dead,) = _labelled(ax, "dead cell")
    np.testing.assert_allclose(dead.get_offsets(), dead_field_run.setup.cells.positions[[7]])
    labels = ax.get_legend_handles_labels()[1]
    assert "start (dashed outline)" in labels and "end (filled)" in labels


def test_dead_cells_whose_wheels_turn_freely_say_so_in_the_legend():
    from virtual_vehicle.run.sim import run

    res = run(_built("prototype_18", 0.2, faults={"dead_cells": [7], "dead_wheels": "free"}))
    (dead,) = _labelled(viz.plot_paths(res).axes[0], "dead cell, wheels free")
    np.testing.assert_allclose(dead.get_offsets(), res.setup.cells.positions[[7]])


def test_cell_ids_drawn_are_the_layouts_numbering_row_by_row_from_the_bottom():
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.model import layout

    text = "oo.\nooo\nooo\n"  # 8 cells: the bottom line first, left to right
    cells, _ = layout.from_map(text, pitch=0.1)
    np.testing.assert_allclose(cells.positions, [[0, 0], [0.1, 0], [0.2, 0], [0, 0.1], [0.1, 0.1], [0.2, 0.1],
                                                 [0, 0.2], [0.1, 0.2]], atol=1e-12)
    sc = parse_scenario({"name": "ids", "duration": 0.1, "array": {"kind": "map", "pitch": 0.1, "map": text},
                         "field": {"kind": "uniform", "velocity": [0.1, 0.0]},
                         "parcels": [{"name": "box", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 0.5,
                                      "x": 0.1, "y": 0.1}]})
    setup = sc.build()
    fig = viz.plot_layout(setup)
    ids = [t for t in fig.axes[0].texts if t.get_gid() == "cell-id"]
    assert [t.get_text() for t in ids] == [str(i) for i in range(setup.cells.n)]
    np.testing.assert_allclose([t.xy for t in ids], setup.cells.positions)
    with pytest.raises(ValueError, match="at most"):
        viz.draw_cells(fig.axes[0], _big_setup(), cell_ids=True)


def _big_setup():
    from virtual_vehicle.config.scenario import parse_scenario

    return parse_scenario({"name": "big", "duration": 0.05, "array": {"kind": "grid", "nx": 60, "ny": 50,
                                                                      "pitch": 0.1},
                           "field": {"kind": "uniform", "velocity": [0.3, 0.0]}, "friction": {"law": "viscous"},
                           "parcels": [{"name": "box", "length": 0.3, "width": 0.25, "mass": 2.0, "mu": 1.0,
                                        "x": 3.0, "y": 2.5}]}).build()


def test_a_large_array_is_drawn_as_one_image_not_a_marker_per_cell(monkeypatch):
    from matplotlib.image import AxesImage

    from virtual_vehicle.run.sim import run

    setup = _big_setup()  # 3000 cells; the threshold is lowered so the test stays small
    result = run(setup)
    monkeypatch.setattr(viz, "LARGE_ARRAY", 1000)
    fig = viz.plot_paths(result)
    ax = fig.axes[0]
    (image,) = [a for a in ax.get_children() if isinstance(a, AxesImage)]
    assert image.get_array().shape == (50, 60)
    assert max(len(c.get_offsets()) for c in ax.collections) <= setup.cells.n // 4  # arrows every other cell
    monkeypatch.setattr(viz, "LARGE_ARRAY", 10_000)
    fig = viz.plot_paths(result)
    assert not any(isinstance(a, AxesImage) for a in fig.axes[0].get_children())  # small arrays as before
    assert max(len(c.get_offsets()) for c in fig.axes[0].collections) == setup.cells.n


def test_the_raster_puts_each_cell_on_its_own_pixel():
    setup = _big_setup()
    img, extent = viz.cell_raster(setup.cells, np.arange(setup.cells.n))
    np.testing.assert_array_equal(img, np.arange(3000).reshape(50, 60))  # row j, column i: cell j * nx + i
    np.testing.assert_allclose(extent, (-0.05, 5.95, -0.05, 4.95))


def test_traffic_under_ideal_rounds_writes_the_constant_latency_instead_of_plotting_it():
    from virtual_vehicle.run.sim import run

    result = run(_built("prototype_18_network_ideal", 0.6, faults={"dead_cells": [7]}))
    fig = viz.plot_traffic(result)
    assert not any(ax.get_ylabel().endswith("latency (ms)") for ax in fig.axes)
    (note,) = [t for ax in fig.axes for t in ax.texts if t.get_gid() == "latency-note"]
    assert "10 ms" in note.get_text() and "ideal" in note.get_text()
    ticks = next(ax for ax in fig.axes if ax.get_ylabel() == "sentences per tick")
    assert ticks.get_ylim()[0] == 0.0
    (dead,) = _labelled(fig.axes[0], "dead cell")
    np.testing.assert_allclose(dead.get_offsets(), result.setup.cells.positions[[7]])


def test_the_layout_command_draws_the_ids_and_refuses_what_it_cannot_draw(tmp_path):
    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app

    out = tmp_path / "layout.png"
    res = CliRunner().invoke(app, ["layout", "prototype_18", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert out.stat().st_size > 10_000
    res = CliRunner().invoke(app, ["layout", "prototype_18", "--out", str(tmp_path / "layout.jpg")])
    assert res.exit_code == 2 and "--out" in res.output
    big = tmp_path / "big.toml"
    big.write_text('name = "big"\nduration = 0.05\n[array]\nkind = "grid"\nnx = 60\nny = 50\npitch = 0.1\n'
                   '[field]\nkind = "uniform"\nvelocity = [0.3, 0.0]\n[[parcels]]\nname = "box"\nlength = 0.3\n'
                   'width = 0.25\nmass = 2.0\nmu = 1.0\nx = 3.0\ny = 2.5\n')
    for args in (["layout", str(big), "--out", str(out)], ["run", str(big), "--cell-ids", "--out",
                                                            str(tmp_path / "run")]):
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2 and "--cell-ids" in res.output and len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_a_legend_under_a_short_plot_keeps_clear_of_its_axis_label():
    """A row of cells drawn to scale makes a short plot; the legend under it sits below the x label (it used to be
    placed a fraction of the axes' height down, which on such a plot put it over the label)."""
    from virtual_vehicle.run.sim import run

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = viz.plot_paths(run(_built("stick_slip_pickup", 0.05)))
    canvas = FigureCanvasAgg(fig)  # the figure was closed once drawn: a canvas to lay it out and measure it on again
    canvas.draw()
    renderer = canvas.get_renderer()
    for ax in fig.axes[:2]:
        label = ax.xaxis.label.get_window_extent(renderer)
        ticks = ax.xaxis.get_tightbbox(renderer)
        legend = ax.get_legend().get_window_extent(renderer)
        assert legend.y1 < min(label.y0, ticks.y0) + 1e-9  # display coordinates: y grows upward
        assert all(t.get_window_extent(renderer).y0 > 0 for t in ax.get_legend().get_texts())  # within the picture


def test_the_torque_colours_do_not_magnify_rounding():
    """Under the paper's inward field a square parcel feels no torque anywhere (~1e-17 N m of rounding): the colour
    scale spans at least a thousandth of the largest force at the parcel's reach, so the map shows none."""
    from virtual_vehicle.config.scenario import load_scenario

    setup = load_scenario("paper_2x2_inward")[0].build()
    spec = setup.specs[0]
    fig = viz.plot_force_field(setup.cells, spec, setup.contact_velocities, setup.law, 0.0)
    mesh = fig.axes[0].collections[0]
    torques = np.abs(mesh.get_array()).max()
    assert torques < 1e-12 and mesh.norm.vmax >= 1e-3 * 0.1  # the force ~6.9 N, the reach ~0.2 m
