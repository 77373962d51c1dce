"""Stick-slip friction (paper Section 5): each wheel sticks to the parcel or slides, a law with modes of its own. The
event-driven engine integrates it exactly, mode by mode (:mod:`virtual_vehicle.physics.stick_modes`: each wheel
sticks or slips with a known sign between events); fixed mode, and parcels pushing each other, solve it as a
complementarity problem every time step instead (the engine's time stepper,
:mod:`virtual_vehicle.engine.stickslip`). The parcel's ``mu`` is the kinetic coefficient and ``mu_static``
(default ``mu``) the static one, both dimensionless. In the sliding mode every wheel pushes with its kinetic bound
in its direction of spin: the paper's Coulomb law, whose constants, wrench and bounds it shares.

Units: N, N m, m, m/s, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virtual_vehicle.physics.laws.base import StepperOptions, energy_reach
from virtual_vehicle.physics.laws.coulomb import CoulombLaw
from virtual_vehicle.physics.stick_modes import Wheels, wheel_arrays, wheels_on


@dataclass(frozen=True)
class StickSlipLaw(CoulombLaw):
    """Stick-slip friction (paper Section 5), a law with modes: exact between events in event mode, time-stepped in
    fixed mode. Its per-support-set constants (for reference only) are those of the sliding regime: the paper's
    Coulomb constants. ``max_sweeps`` and ``tolerance`` (relative
    to the largest impulse bound) control the projected Gauss-Seidel solver."""

    name: str = "stick_slip"
    max_sweeps: int = 1000
    tolerance: float = 1e-12
    time_stepper = "stick_slip"
    modes = True
    assumes_sliding = False  # the stepper decides which wheels slide
    galilean = True  # each wheel's force is its slip's (sign, or stuck where the slip is zero), eq. 21 per wheel

    def reach(self, s0, window, *, rate, wheel_speed, lever=None):
        """The smaller of two bounds, both true whatever the supports and the modes (each wheel's force at most
        ``mu_s N`` along its drive direction, two wheels a cell, normal forces summing to W, eqs. 3-5):

        - force: the Coulomb law's ``S0 T + rate T^2`` (net force at most ``2 mu W``, torque ``2 mu W R``);
        - energy (with ``lever`` = ``1 + m R^2 / I``): a wheel takes energy out of the parcel where it slips and
          none where it sticks, so the power of wheel j on the parcel is at most ``|f_j| |w_j|``, its force times
          its surface speed ``w_j`` (a sticking wheel moves the parcel at ``w_j``; a slipping one pushes toward
          ``w_j``): at most ``2 mu W w`` in all. So ``E <= m S0^2 / 2 + 2 mu W w t`` (``I <= m R^2``) and, as
          ``S^2 <= (lever / m) 2 E``, ``S(t)^2 <= lever S0^2 + 4 rate w t``; the reach is its integral
          ``(2 T / 3) (x + sqrt(x y) + y) / (sqrt(x) + sqrt(y))`` with ``y = lever S0^2``, ``x = y + 4 rate w T``.
          The law is :attr:`galilean`: seen from a frame moving with the wheels' common velocity ``w`` is their
          speed relative to it, 0 on a uniform field, where a parcel riding its wheels (``S0`` = 0) never leaves
          them: the planner's windows then last as long as it allows (``[contacts] window``)."""
        dist, speed = super().reach(s0, window, rate=rate, wheel_speed=wheel_speed, lever=lever)
        if lever is None:  # the parcel's inertia unknown: the force bound alone
            return dist, speed
        y = lever * np.square(s0)
        x = y + 4.0 * rate * wheel_speed * window  # S^2 <= lever S0^2 + 4 rate w t (eq. 21 per wheel)
        energy, fastest = energy_reach(y, x, window)
        return np.minimum(dist, energy), np.minimum(speed, fastest)

    def frame_power(self, mu_weight, wheel_slack):
        """Each wheel pushes along its drive direction with at most ``mu_s N`` of its entry's normal force N, the
        normal forces summing to the weight (eqs. 3-5, 21 per wheel); where it slips it takes energy out of the
        parcel relative to its own surface, where it sticks it moves the parcel with it. So in any frame its
        power on the parcel is at most its force times its surface speed relative to the frame: in all at most
        ``mu_s W`` times the largest sum of those speeds over one entry's wheels."""
        return mu_weight * wheel_slack

    def stepper_options(self) -> StepperOptions:
        """The solver's limits, ``max_sweeps`` and ``tolerance``."""
        return StepperOptions(self.max_sweeps, self.tolerance)

    def wheel_loads(self, speed, slip):
        """A sliding wheel pushes with ``mu N`` along its slip; a sticking one (no slip) is reported as none."""
        return np.where(np.abs(slip) > 1e-9, np.sign(slip), 0.0)

    def wheel_contacts(self, cells, support, solution, velocities, mu, mu_static=None) -> Wheels:
        """Each present wheel of the supporting entries a 1-D friction contact along its drive direction, moving at
        its entry's surface velocity projected on it (a stuck wheel's is 0 already; a free one is not present),
        carrying its entry's whole normal force (eq. 21): :func:`~virtual_vehicle.physics.stick_modes.wheels_on`."""
        return wheels_on(cells, support, solution, velocities, mu, mu_static)

    def wheel_arrays(self, cells, support, solution, velocities, mu, mu_static=None) -> tuple:
        """:meth:`wheel_contacts`' wheels as plain arrays (:func:`~virtual_vehicle.physics.stick_modes.wheel_arrays`)."""
        return wheel_arrays(cells, support, solution, velocities, mu, mu_static)
