"""The friction-law contract: every registered law passes check_law, a law defined here plugs into the engine and
the plant through its own module alone, and check_law fails laws that break the physics."""

from dataclasses import dataclass
from typing import get_args

import numpy as np
import pytest

from virtual_vehicle.config.scenario import FrictionSpec
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.engine.plant import Integration, Plant
from virtual_vehicle.model import layout
from virtual_vehicle.model.fields import Uniform
from virtual_vehicle.model.parcel import rectangle
from virtual_vehicle.physics.collide import point_reach
from virtual_vehicle.physics.laws import (
    LAWS,
    CoulombLaw,
    FrictionLaw,
    StepperOptions,
    StickSlipLaw,
    ViscousLaw,
    affine,
    check_law,
)
from virtual_vehicle.physics.laws.affine import constants_and_row, drive_constants, f64


@pytest.mark.parametrize("name", list(LAWS))
def test_every_registered_law_passes_check_law(name):
    check_law(LAWS[name])


def test_scenario_law_choices_are_the_registry():
    assert get_args(FrictionSpec.model_fields["law"].annotation) == tuple(LAWS)


@dataclass(frozen=True)
class SoftCoulombLaw(FrictionLaw):
    """A toy law written against the contract alone: Coulomb's, but a wheel slower than ``knee`` (m/s) pushes with
    only ``mu N |speed| / knee`` (a soft start), so its drive vector is ``sum_k clip(V . u_k / knee, -1, 1) u_k``."""

    name: str = "soft_coulomb"
    knee: float = 0.05
    assumes_sliding = True

    def drive_vectors(self, velocities, drive_directions):
        U = np.asarray(drive_directions, dtype=float)
        s = np.clip(np.einsum("ij,ikj->ik", np.asarray(velocities, dtype=float), U) / self.knee, -1.0, 1.0)
        return np.einsum("ik,ikj->ij", s, U)

    def cell_forces(self, points, normal, velocities, drive_directions, mu, state):
        return mu * np.asarray(normal)[:, None] * self.drive_vectors(velocities, drive_directions)

    def constants(self, solution, velocities, drive_directions, mu):
        return drive_constants(solution.points, self.drive_vectors(velocities, drive_directions), solution.force_lin,
                               solution.force_const, solution.weight, mu)

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        drive = f64(self.drive_vectors(velocities, drive_directions))
        return constants_and_row(solution.points, drive, solution.force_lin, solution.force_const, mu, 0.0,
                                 solution.weight, solution.origin, mass, inertia)

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        k = 2.0 * rate  # |drive| <= 2 with two wheels a cell, normal forces summing to the weight
        return s0 * window + 0.5 * k * window * window, s0 + k * window

    def wheel_loads(self, speed, slip):
        return np.clip(speed / self.knee, -1.0, 1.0)

    def scaled_mu(self, mu, length):
        return mu


TOY_LAWS = {**LAWS, "soft_coulomb": SoftCoulombLaw()}
"""A registry with the toy law added: one line."""


def test_a_toy_law_passes_check_law():
    check_law(TOY_LAWS["soft_coulomb"])


def _run_one(law, velocity=(0.3, 0.1)):
    cells = layout.grid(8, 8, 0.1)
    spec = rectangle(0.25, 0.22, 1.0, 0.5)
    model = ParcelModel(cells, spec, Uniform(velocity).velocities(cells), law)
    return integrate(model, np.array([0.3, 0.3, 0.1, 0.0, 0.0, 0.0]), 0.0, 0.5, sample_dt=0.05)


def test_a_toy_law_runs_through_the_event_engine():
    """With a knee far below the wheel speeds the toy law is Coulomb's; with a knee above them it pushes less."""
    coulomb = _run_one(TOY_LAWS["coulomb"])
    hard = _run_one(SoftCoulombLaw(knee=1e-9))
    np.testing.assert_allclose(hard.states, coulomb.states, rtol=0, atol=1e-12)
    soft = _run_one(SoftCoulombLaw(knee=1.0))
    moved = np.hypot(*(soft.states[-1, :2] - soft.states[0, :2]))
    assert 0.0 < moved < 0.9 * np.hypot(*(coulomb.states[-1, :2] - coulomb.states[0, :2]))


def test_a_toy_law_runs_through_the_plant_with_the_quiet_batch():
    """Two parcels carried apart: the plant plans with the toy law's own reach bound and steps their quiet windows
    together; the same run without the batch gives the same states."""
    cells = layout.grid(20, 8, 0.1)
    specs = [rectangle(0.25, 0.22, 1.0, 0.5, name="a"), rectangle(0.25, 0.22, 1.0, 0.5, name="b")]
    velocities = Uniform((0.3, 0.0)).velocities(cells)
    ends = []
    for batch in (True, False):
        plant = Plant(cells, specs, SoftCoulombLaw(knee=0.5), 9.81, Integration(batch=batch))
        ys = [np.array([0.3, 0.2, 0.0, 0.0, 0.0, 0.0]), np.array([0.3, 0.6, 0.0, 0.0, 0.0, 0.0])]
        active = [True, True]
        for k in range(20):  # ticks of a networked run
            plant.advance(ys, active, velocities, 0.02 * k, 0.02 * (k + 1), 0.02)
        ends.append(np.array(ys))
        if batch:
            assert plant.record.quiet_steps > 0
    np.testing.assert_allclose(ends[0], ends[1], rtol=0, atol=1e-9)
    assert np.all(ends[0][:, 3] > 0.01)  # carried along x


def test_the_planner_takes_the_bound_of_the_law_it_holds():
    spec = rectangle(0.25, 0.22, 1.0, 0.5)
    y = [0, 0, 0, 0.1, 0, 0]
    kw = dict(mu_max=0.5, gravity=9.81, wheel_speed=0.3)
    assert point_reach(spec, y, 0.5, law=SoftCoulombLaw(), **kw) == point_reach(spec, y, 0.5, law="coulomb", **kw)
    assert point_reach(spec, y, 0.5, law=ViscousLaw(), **kw) != point_reach(spec, y, 0.5, law="coulomb", **kw)


@dataclass(frozen=True)
class BackwardsLaw(CoulombLaw):
    """Broken: the wheels push against their spin."""

    name: str = "backwards"

    def cell_forces(self, points, normal, velocities, drive_directions, mu, state):
        return -super().cell_forces(points, normal, velocities, drive_directions, mu, state)


@dataclass(frozen=True)
class ShortReachLaw(ViscousLaw):
    """Broken: claims the parcel reaches only half as far as it can."""

    name: str = "short_reach"

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        dist, speed = super().reach(s0, window, rate=rate, wheel_speed=wheel_speed, lever=lever)
        return 0.5 * dist, speed


@dataclass(frozen=True)
class LopsidedLaw(ViscousLaw):
    """Broken: a cell pushes with its own x slip along y as well (not invariant under rotation)."""

    name: str = "lopsided"

    def cell_forces(self, points, normal, velocities, drive_directions, mu, state):
        f = super().cell_forces(points, normal, velocities, drive_directions, mu, state)
        return f + np.column_stack([np.zeros(len(f)), f[:, 0]])


@dataclass(frozen=True)
class CreepLaw(CoulombLaw):
    """Broken: a parcel on stopped wheels still creeps along x."""

    name: str = "creep"

    def cell_forces(self, points, normal, velocities, drive_directions, mu, state):
        f = super().cell_forces(points, normal, velocities, drive_directions, mu, state)
        return f + np.array([1e-3 * mu, 0.0]) * np.asarray(normal)[:, None]


@dataclass(frozen=True)
class UndampedRowLaw(ViscousLaw):
    """Broken: hands the engine a row without its damping."""

    name: str = "undamped_row"

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        k, row = super().constants_and_row(solution, velocities, drive_directions, mu, mass, inertia)
        return k, (*row[:affine.R_DAMPING], 0.0, *row[affine.R_DAMPING + 1:])


@dataclass(frozen=True)
class OptionlessLaw(StickSlipLaw):
    """Broken: time-stepped, but hands its stepper nothing."""

    name: str = "optionless"

    def stepper_options(self):
        return None


@dataclass(frozen=True)
class SteadyReachLaw(ViscousLaw):
    """Broken: claims a parcel never gets faster than its start allows (the energy bound without what uneven
    wheels put in), which holds on a uniform field only."""

    name: str = "steady_reach"

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        dist, speed = super().reach(s0, window, rate=rate, wheel_speed=wheel_speed)
        steady = np.sqrt(lever) * s0
        return np.minimum(dist, steady * window), np.minimum(speed, steady)


@dataclass(frozen=True)
class SteadyStickSlipLaw(StickSlipLaw):
    """Broken: stick-slip claiming a parcel never gets faster than its start allows (its energy bound without what
    the wheels put in where they differ from their common velocity), which holds on a uniform field only; caught by
    stepping its wheels (a law with modes), not by its Coulomb cell forces."""

    name: str = "steady_stick_slip"

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        return super().reach(s0, window, rate=rate, wheel_speed=0.0, lever=lever)


@pytest.mark.parametrize("law, what", [(BackwardsLaw(), "give"), (ShortReachLaw(), "reach bound"),
                                       (LopsidedLaw(), "moved rigidly"), (CreepLaw(), "at rest"),
                                       (UndampedRowLaw(), "row"), (OptionlessLaw(), "stepper"),
                                       (SteadyReachLaw(), "reach bound"), (SteadyStickSlipLaw(), "reach bound"),
                                       (CoulombLaw(), None), (StickSlipLaw(), None)])
def test_check_law_fails_a_broken_law(law, what):
    if what is None:  # the law each broken one is made from passes
        check_law(law, trials=10)
        return
    with pytest.raises(AssertionError, match=what):
        check_law(law, trials=10)


@dataclass(frozen=True)
class HastyStickSlipLaw(StickSlipLaw):
    """Stick-slip whose solver gives up after one sweep, told the stepper only through its stepper options."""

    name: str = "hasty_stick_slip"

    def stepper_options(self):
        return StepperOptions(1, self.tolerance)


def test_a_plant_steps_parcels_pushing_each_other_with_the_solver_limits_the_law_hands_it():
    """The plant's grouped steps (parcels in contact, the wheels in the same problem) take the sweeps and tolerance
    from the law's stepper options: one sweep leaves many steps unconverged that the stick-slip law's own limits
    converge."""
    cells = layout.grid(14, 6, 0.1)
    specs = [rectangle(0.25, 0.22, 1.0, 0.5, name="a"), rectangle(0.25, 0.22, 1.0, 0.5, name="b")]
    velocities = np.where(cells.positions[:, :1] < 0.55, [[0.3, 0.0]], [[0.0, 0.0]])
    unconverged = {}
    for law in (StickSlipLaw(), HastyStickSlipLaw()):
        plant = Plant(cells, specs, law, 9.81, Integration(dt=1e-3))
        ys = [np.array([0.3, 0.3, 0.0, 0.0, 0.0, 0.0]), np.array([0.58, 0.3, 0.0, 0.0, 0.0, 0.0])]
        for k in range(30):
            plant.advance(ys, [True, True], velocities, 0.02 * k, 0.02 * (k + 1), 0.02)
        assert plant.record.grouped_steps > 0
        unconverged[law.name] = plant.record.unconverged_contact_steps
    assert unconverged["hasty_stick_slip"] > 10 * unconverged["stick_slip"] + 100  # measured: 540 against 4


def test_a_law_refuses_geometry_it_cannot_act_on():
    wheels = layout.separate_wheels(layout.grid(4, 4, 0.1))
    with pytest.raises(ValueError, match="lumped cell"):
        ParcelModel(wheels, rectangle(0.25, 0.22, 1.0, 0.5), np.zeros((wheels.n, 2)), ViscousLaw())
    ParcelModel(wheels, rectangle(0.25, 0.22, 1.0, 0.5), np.zeros((wheels.n, 2)), CoulombLaw())


@dataclass(frozen=True)
class ModalLaw(CoulombLaw):
    """A law with modes of its own asking for a time stepper the engine has not got."""

    name: str = "modal"
    time_stepper = "no_such_stepper"


def test_the_engine_refuses_a_time_stepper_it_does_not_have():
    cells = layout.grid(4, 4, 0.1)
    with pytest.raises(ValueError, match="no_such_stepper"):
        ParcelModel(cells, rectangle(0.25, 0.22, 1.0, 0.5), np.zeros((cells.n, 2)), ModalLaw())
