"""The field's classic results, reproduced with the package's own physics (issue 35): each is a function of an
output folder that computes the result, writes a figure (PNG) and a table (CSV) there and returns a
:class:`~virtual_vehicle.analysis.classics.base.Result` with the source's statement beside our numbers.

``CLASSICS`` registers them by name; :func:`reproduce` runs some or all (``virtual-vehicle reproduce``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from virtual_vehicle.analysis.classics.base import Result
from virtual_vehicle.analysis.classics.elliptic import elliptic_fields
from virtual_vehicle.analysis.classics.laws import realistic_law
from virtual_vehicle.analysis.classics.orientation import discreteness_orientation
from virtual_vehicle.analysis.classics.seed_paper import inward_2x2, row_oscillator
from virtual_vehicle.analysis.classics.squeeze import squeeze_fields

CLASSICS: dict[str, Callable[[Path], Result]] = {
    "inward_2x2": inward_2x2,
    "row_oscillator": row_oscillator,
    "squeeze": squeeze_fields,
    "elliptic": elliptic_fields,
    "orientation": discreteness_orientation,
    "realistic_law": realistic_law,
}
"""Each classic result by name, in the order ``reproduce`` runs them."""


def reproduce(names: list[str] | None = None, out: str | Path = "results/classics") -> list[Result]:
    """Run the classic results ``names`` (all when None or empty), each writing into ``out``/NAME. Raises
    ValueError naming the unknown ones before anything runs."""
    names = list(names or CLASSICS)
    unknown = [n for n in names if n not in CLASSICS]
    if unknown:
        raise ValueError(f"no classic result named {', '.join(map(repr, unknown))}; the results are "
                         f"{', '.join(CLASSICS)}")
    return [CLASSICS[n](Path(out) / n) for n in dict.fromkeys(names)]


__all__ = ["CLASSICS", "Result", "reproduce"]
