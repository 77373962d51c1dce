"""Supports and normal forces (paper eqs. 3-19, lift-off, tipping), friction laws (eqs. 20-38), parcel-parcel contact
geometry, the literal reference of eq. 19.
"""
