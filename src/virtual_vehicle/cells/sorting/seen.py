"""What one computer sees of the parcels in the cells' sensors (the central sorter's and the reservation router's
view): groups of lit cells, each the vehicle it was. Units: none (cell indices and vehicle ids)."""

from __future__ import annotations

import numpy as np

from virtual_vehicle.cells.sorting.rules import NONE


def parcels_seen(lit, connected, neighbor, before) -> list[tuple[int, np.ndarray]]:
    """The parcels one computer sees in the cells' sensors: connected groups of ``lit`` cells (n,) through live links
    (``connected``, ``neighbor``: (n, P)), each as (vehicle id, cells): the vehicle whose cells the group holds in
    ``before`` (n,; the last tick's owners), NONE where it holds none. Two parcels that come so near that their lit
    cells join make one group holding cells of two vehicles: it is shared among them, so that each keeps its own
    record and exit. Each keeps the cells it had; a cell newly lit goes to the vehicle of the lit neighbour it is
    first reached from, breadth-first in cell order."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(lit)
    idx = np.flatnonzero(lit)
    pos = np.full(n, -1, dtype=np.int64)
    pos[idx] = np.arange(len(idx))
    a, p = np.nonzero(connected[idx])
    b = neighbor[idx[a], p]
    keep = lit[b]
    graph = coo_matrix((np.ones(int(keep.sum())), (a[keep], pos[b[keep]])), shape=(len(idx),) * 2)
    count, comp = connected_components(graph, directed=False) if len(idx) else (0, np.zeros(0, int))
    out = []
    for k in range(count):
        blob = idx[comp == k]
        prev = before[blob]
        held = np.unique(prev[prev >= 0])
        if len(held) <= 1:
            out.append((int(held[0]) if len(held) else NONE, blob))
            continue
        own = {int(c): int(v) for c, v in zip(blob, prev) if v >= 0}
        queue = sorted(own)
        for c in queue:  # breadth-first from the cells owned, in cell order (a list grown while read)
            for q in range(neighbor.shape[1]):
                d = int(neighbor[c, q])
                if d >= 0 and connected[c, q] and lit[d] and d not in own:
                    own[d] = own[c]
                    queue.append(d)
        for v in held:
            out.append((int(v), np.array(sorted(c for c, w in own.items() if w == v), dtype=np.int64)))
    return out
