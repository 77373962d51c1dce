"""The compiled mode decision (physics.stick_modes.decide_compiled / decide_kernel) against the readable reference
(decide_mode, project_twist, stick_facets, breaking_wheels) on random wheel sets: many sticking wheels (redundant,
> 3), mu_s > mu_k, stuck wheels (surface speed 0) and free ones (no friction), wheel accelerations."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.physics.stick_modes import (Wheels, arrays_of, breaking_kernel, breaking_wheels, decide_compiled,
                                                 decide_mode, project_twist, stick_facets)

MASS, INERTIA = 1.5, 0.02


def _wheels(seed: int, m: int, sticking: int, ratio: float, stuck: int, free: int, accel: bool):
    """``m`` wheels on a 0.4 m patch; the first ``sticking`` at zero slip under the parcel's twist, ``stuck`` others
    with surface speed 0, ``free`` others without friction; static coefficient ``ratio`` times the kinetic one."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.2, 0.2, (m, 2))
    angle = rng.choice([0.0, np.pi / 2, np.pi, 3 * np.pi / 2], m) + (rng.uniform(-1, 1, m) if seed % 2 else 0.0)
    u = np.column_stack([np.cos(angle), np.sin(angle)])
    y = np.array([*rng.uniform(-0.05, 0.05, 2), 0.3, *rng.uniform(-0.3, 0.3, 2), rng.uniform(-2, 2)])
    rows = np.column_stack([u, (points[:, 0] - y[0]) * u[:, 1] - (points[:, 1] - y[1]) * u[:, 0]])
    speeds = rng.uniform(-0.4, 0.4, m)
    speeds[:sticking] = rows[:sticking] @ y[3:]
    speeds[sticking:sticking + stuck] = 0.0
    mu_k = np.full(m, rng.uniform(0.1, 0.8))
    mu_s = mu_k * ratio
    mu_k[m - free:] = mu_s[m - free:] = 0.0
    weight = 9.81 * MASS
    wheels = Wheels(points=points, directions=u, speeds=speeds, accels=rng.uniform(-2, 2, m) * accel, t0=0.0,
                    force_lin=rng.uniform(-5, 5, (m, 2)), force_const=np.full(m, weight / m) * rng.uniform(0.5, 1.5, m),
                    origin=np.zeros(2), mu_static=mu_s, mu_kinetic=mu_k)
    return wheels, y


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**31), m=st.integers(1, 14), stick_share=st.floats(0, 1),
       ratio=st.sampled_from([1.0, 1.2, 2.0]), stuck=st.integers(0, 3), free=st.integers(0, 2),
       accel=st.booleans(), t=st.sampled_from([0.0, 0.37]))
def test_compiled_decision_equals_the_reference(seed, m, stick_share, ratio, stuck, free, accel, t):
    sticking = round(stick_share * m)
    stuck, free = min(stuck, m - sticking), min(free, m - sticking)
    wheels, y = _wheels(seed, m, sticking, ratio, stuck, free, accel)
    try:
        mode = decide_mode(wheels, t, y, MASS, INERTIA)
    except ValueError:
        with pytest.raises(ValueError):
            decide_compiled(wheels, t, y, MASS, INERTIA)
        return
    fast, projected, (rank, anchor, index) = decide_compiled(wheels, t, y, MASS, INERTIA)
    assert fast == mode
    np.testing.assert_allclose(projected, project_twist(wheels, mode, t, y, MASS, INERTIA), rtol=0, atol=1e-12)
    if not len(mode.stick):
        assert rank == 0 and len(index) == 0
        return
    r, a, idx = stick_facets(wheels, mode, t, projected, MASS, INERTIA)
    assert (rank, anchor) == (r, a)
    np.testing.assert_array_equal(index, np.reshape(idx, (len(idx), -1)) if rank == 3 else np.column_stack([idx, idx]))
    minv = np.array([1 / MASS, 1 / MASS, 1 / INERTIA])
    for f in range(len(index)):  # which wheels break where the wrench crosses each facet
        ref = breaking_wheels(wheels, mode, t, projected, MASS, INERTIA, (r, a, idx), f)
        got = breaking_kernel(*arrays_of(wheels), minv, t, projected, np.array(mode.state), mode.stick, rank,
                              np.array(anchor or (0, 0)), index, f)
        assert dict(zip(got[0].tolist(), got[1].tolist())) == ref


@pytest.mark.parametrize("sticking", [4, 8])
def test_redundant_sticking_wheels_on_a_turning_field_decide_alike(sticking):
    """More than three wheels at zero slip, the wheels' field turning (their speeds a rigid twist): both keep every
    such wheel sticking or both break the same ones, and they say the same about wheels told to break."""
    wheels, y = _wheels(7, sticking, sticking, 1.2, 0, 0, False)
    mode = decide_mode(wheels, 0.0, y, MASS, INERTIA)
    assert decide_compiled(wheels, 0.0, y, MASS, INERTIA)[0] == mode
    assert len(mode.stick) > 3
    breaking = {int(mode.stick[0]): 1}
    ref = decide_mode(wheels, 0.0, y, MASS, INERTIA, breaking=breaking)
    assert decide_compiled(wheels, 0.0, y, MASS, INERTIA, breaking=breaking)[0] == ref
