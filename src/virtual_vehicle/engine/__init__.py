"""The event integrator (pieces, support events), the fixed step, batched quiet steps, the plant of many parcels, and
the compiled kernels.
"""
