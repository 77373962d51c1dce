"""Typed errors. Each says what went wrong and, where it can, what to fix."""

from __future__ import annotations


class VirtualVehicleError(Exception):
    """Base class of every error this package raises on purpose."""


class ScenarioError(VirtualVehicleError, ValueError):
    """A scenario (file or object) is invalid. ``field`` names the offending field, dotted."""

    def __init__(self, field: str, message: str):
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}" if field else message)


class TippingError(VirtualVehicleError):
    """The supports cannot carry the parcel: its centre of mass lies outside their support polygon
    (or off the line of collinear supports), so no set of non-negative normal forces balances it."""


class IntegrationError(VirtualVehicleError):
    """The integrator could not make progress (e.g. events accumulating at one instant)."""
