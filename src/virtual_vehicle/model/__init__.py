"""Immutable descriptions: cell layouts (lattices, maps, belts), parcel specs, wheel-velocity fields, fault schedules;
and the data form a run's state is written in (state_data). Imports nothing of the package but errors.
"""
