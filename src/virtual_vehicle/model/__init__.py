"""Immutable descriptions: cell layouts (lattices, maps, belts), parcel specs, wheel-velocity fields, fault schedules.
Imports nothing of the package but errors.
"""
