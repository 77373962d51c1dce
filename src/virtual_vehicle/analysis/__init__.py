"""Studies over a model or many runs: equilibria, field design, the scaling family, sweeps.
"""
