"""Program ``"diffusion"``: wheel speeds relax toward the neighbours' (the discrete heat equation,
:class:`~virtual_vehicle.cells.control.Diffusion`). Units: m/s."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from virtual_vehicle.cells.programs.base import (BuildContext, ControlSetup, FieldError, ProgramOptions, Speed,
                                                 no_markers, setup_for)


class DiffusionOptions(ProgramOptions):
    """``program = "diffusion"``: every cell's wheel speeds relax toward its neighbours' at rate ``alpha`` per tick
    (the discrete heat equation); ``sources`` = [[cell, v0, v1], ...] hold their wheel speeds (m/s)."""

    program: Literal["diffusion"]
    alpha: Annotated[float, Field(gt=0, le=1)] = 0.2
    sources: list[tuple[Annotated[int, Field(ge=0)], Speed, Speed]] = []

    def top_speed(self) -> float:
        """The fastest source's speed (m/s): by the maximum principle no wheel runs faster."""
        return max((float(np.hypot(v0, v1)) for _, v0, v1 in self.sources), default=0.0)



Options = DiffusionOptions
"""The ``[control]`` table of this program."""

def build(options: DiffusionOptions, ctx: BuildContext) -> ControlSetup:
    """Every cell runs the diffusion step; source cells are told their fixed speeds."""
    from virtual_vehicle.cells.control import Diffusion

    n = ctx.cells.n
    fixed = np.zeros(n, dtype=bool)
    speed = np.zeros((n, 2))
    for k, (cell, v0, v1) in enumerate(options.sources):
        if cell >= n:
            raise FieldError(f"control.sources[{k}]", f"cell {cell} does not exist (the array has {n})")
        fixed[cell] = True
        speed[cell] = (v0, v1)
    program = Diffusion(options.alpha, max_age=options.max_age)
    return setup_for(options, ctx, program, {"fixed": fixed, "speed": speed})


SUMMARY = None
"""No task report: diffusion has no goal to judge it by."""
report = None
COMPARED = ()
CENTRAL = False
LABELS = False
markers = no_markers
