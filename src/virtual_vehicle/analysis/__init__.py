"""Studies over a model or many runs: equilibria, the scaling family, sweeps, distributed against central control.
"""
