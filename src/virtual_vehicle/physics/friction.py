"""The friction laws' old home, kept so that ``from virtual_vehicle.physics.friction import CoulombLaw`` still works:
every name here is :mod:`virtual_vehicle.physics.laws`'s (one module a law, the contract, the registry)."""

from virtual_vehicle.physics.laws import (
    LAWS,
    CoulombLaw,
    FrictionConstants,
    FrictionLaw,
    J,
    StickSlipLaw,
    ViscousLaw,
    check_law,
    coulomb_constants,
    drive_constants,
    viscous_constants,
)

__all__ = ["FrictionConstants", "FrictionLaw", "CoulombLaw", "ViscousLaw", "StickSlipLaw", "LAWS", "check_law",
           "coulomb_constants", "viscous_constants", "drive_constants", "J"]
