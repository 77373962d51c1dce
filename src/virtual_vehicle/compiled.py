"""How the package compiles its hot inner functions: :data:`leaf`.

A root module (below every layer), because leaves live in several: the event engine's loop
(:mod:`virtual_vehicle.engine._kernel`) and the support solve's tests it calls (:mod:`virtual_vehicle.physics.contact`).
"""

from __future__ import annotations

from numba import njit

leaf = njit(cache=True, _nrt=False)
"""The compiler for leaves: functions that allocate nothing and return no array (numbers, or nothing: they write
into arrays given). Numba's runtime counts a reference to every array argument on entry and drops it on exit, two
atomic calls an array, which its pruning leaves in place in branching code: a call taking the event loop's
:class:`~virtual_vehicle.engine._kernel.Segment` (16 arrays) cost ~500 cycles so, against ~100 for its work (one
margin), measured. Compiled without the runtime (numba's ``_nrt`` option) a leaf counts nothing. A leaf may call only
leaves, inlined helpers and compiled functions that return no array (one returned to a leaf would never be released);
the compiler refuses one that allocates ("NRT required but not enabled"). A leaf may take views of its arrays (no
count is taken of them either)."""
