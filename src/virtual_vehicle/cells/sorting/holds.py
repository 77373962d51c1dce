"""Who waits on whom in the distributed sorter (:class:`~virtual_vehicle.cells.sorting.Sorter`), read from its
cells' state: the wait-for graph of the vehicles and its cycles, the deadlocks no rule of the sorter breaks.

A vehicle ``V`` waits on a vehicle ``W`` when

- *it is held up by it*: ``V`` stands (a stop is within ``reach`` of its front cell), and of the ``gap + 1`` cells
  straight ahead of one of its front cells (those whose request goes out) the first that is not ``V``'s carries
  ``W`` or is held for ``W``; a missing or dead cell there ends the walk (``V`` waits on the floor, not on a
  vehicle);
- *it is not due*: its label carries a sequence number above the one due next (``nxt``), and ``W`` carries the due
  number: ``V`` cannot leave before ``W`` has, whether it parks, looks for a bay or stands.

A cycle of these (a strongly connected set of two or more vehicles) is a deadlock: each member waits, through the
others, on itself, and none of the sorter's rules moves a member whose every way is held (a vehicle backs off or
gives way only to one before it in the order holds go by, to any while it is not due, parked or not, through an
open side: the package notes argue which cycles can stand, and where that argument has gaps). The
cells are read at one instant; a cycle seen while its vehicles stand is kept by the rules, since every member's
cells stay held while it stands. Units: cells and hops.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_array
from scipy.sparse.csgraph import connected_components

from virtual_vehicle.cells.sorting.rules import NONE, hop_bits, split_goal


def waits_for(state: dict, neighbor: np.ndarray, alive: np.ndarray, gap: int, reach: int) -> list[tuple[int, int, int]]:
    """The wait-for edges ``(V, W, cell)`` of the vehicles (ids) in the sorter's cell ``state`` (the dict of
    :meth:`~virtual_vehicle.cells.sorting.Sorter.init`): ``V`` waits on ``W`` at ``cell`` (the cell of ``W`` that
    holds ``V`` up; -1 for a wait on the due sequence number). ``neighbor`` (n, P): the cell on each port, -1 none;
    ``alive`` (n,) installed and working cells; ``gap`` and ``reach`` the sorter's (see the module notes)."""
    vid, hold, direction = (np.asarray(state[k]) for k in ("vid", "hold", "dir"))
    stop, park = np.asarray(state["stop"]), np.asarray(state["park"])
    none = (1 << hop_bits(neighbor.shape[1])) - 1  # the stop word's hop field (square 6 bits, hexagonal 5)
    edges = set()
    for i in np.flatnonzero((vid >= 0) & (direction >= 0) & alive):
        v, d = int(vid[i]), int(direction[i])
        if (stop[i] & none) > reach or park[i] <= reach:  # moving, or parked (it waits on the sequence only)
            continue
        c = int(neighbor[i, d])
        if c >= 0 and vid[c] == v:  # not a front cell
            continue
        for _ in range(gap + 1):
            if c < 0 or not alive[c]:
                break
            w = int(vid[c]) if vid[c] >= 0 else int(hold[c])
            if w >= 0 and w != v:
                edges.add((v, w, c))
                break
            c = int(neighbor[c, d])
    goal = np.asarray(state["goal"])
    on = (vid >= 0) & (goal >= 0) & alive
    if on.any():
        nxt = int(np.asarray(state["nxt"])[alive].max())
        _, seq = split_goal(goal[on].astype(np.int64))
        due = {int(v) for v, s in zip(vid[on], seq) if s == nxt}
        late = {int(v) for v, s in zip(vid[on], seq) if s > nxt}
        edges |= {(v, w, NONE) for v in late for w in due}
    return sorted(edges)


def cycles(edges) -> list[list[int]]:
    """The strongly connected sets of two or more vehicles of the wait-for ``edges`` ``(V, W, ...)``, each sorted,
    in the order of their smallest id (scipy's strongly connected components)."""
    ids = sorted({v for v, w, *_ in edges} | {w for v, w, *_ in edges})
    if not ids:
        return []
    at = {v: k for k, v in enumerate(ids)}
    rows = [at[v] for v, _, *_ in edges]
    cols = [at[w] for _, w, *_ in edges]
    graph = coo_array((np.ones(len(rows)), (rows, cols)), shape=(len(ids), len(ids))).tocsr()
    _, label = connected_components(graph, directed=True, connection="strong")
    groups: dict[int, list[int]] = {}
    for v, c in zip(ids, label.tolist()):
        groups.setdefault(c, []).append(v)
    return sorted(g for g in groups.values() if len(g) > 1)


def held_cells(state: dict, vehicles) -> list[int]:
    """The cells that carry one of ``vehicles`` (ids) or are held for one of them."""
    ids = np.asarray(sorted(vehicles), dtype=np.int64)
    vid, hold = np.asarray(state["vid"]), np.asarray(state["hold"])
    return np.flatnonzero(np.isin(vid, ids) | ((vid < 0) & np.isin(hold, ids))).tolist()
