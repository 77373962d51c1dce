"""Pictures show what went wrong: stuck parcels, dead cells, entries and exits, honest axes, arrays of any size."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_vehicle import viz


def _fault_rows():
    """A fault study whose deliveries fall while nothing collides, is misrouted or lost (issue 30)."""
    return [dict(rate=r, runs=5, failed=0, parcels_due=20, delivered_fraction=f, delivered_fraction_std=0.05,
                 delivery_time_mean_s=t, collisions=0.0, misrouted=0.0, lost=0.0)
            for r, f, t in [(0.0, 0.67, 9.375), (0.02, 0.41, 9.5), (0.05, 0.09, 9.55)]]


def test_the_fault_study_picture_shows_the_stuck_parcels_and_starts_its_axes_at_zero():
    fig = viz.plot_fault_study(_fault_rows(), "dead_cell_rate", "study")
    bars = {c.get_label(): [p.get_height() for p in c.patches] for ax in fig.axes for c in ax.containers if hasattr(c, "patches")}
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
