"""A randomized stress test of the sorter's liveness: small generated sorting floors, each run for a short time.

:func:`random_floor` draws, from a seed, a square-lattice map (`model.layout.from_map` letters) with holes, one-way
aisles, sometimes parking bays with a sequenced stream, 1-3 entries on the west edge and 1-3 exits on the east and
north edges, every exit reachable from every entry by a parcel-sized block of cells (checked, redrawn otherwise),
and a stream of mixed parcels; :func:`stress` runs floors and counts what the sorting report finds: stalls
(``sorting.stalls``: deadlocks and lone waits), collisions, misroutes, losses. :func:`explain` says in one line where
a stall stands (which map features its cells touch). Units: m, s.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

PITCH = 0.1
"""m between cell centres of a generated floor."""
BLOCK = 3
"""Cells a side of the square block a parcel covers (parcels of 0.22-0.3 m at 0.1 m pitch)."""
_AGAINST = {">": (0, -1), "<": (0, 1), "^": (1, 0), "v": (-1, 0)}
"""Per arrow, the move (rows down, columns right) that runs against it."""


@dataclass
class Floor:
    """A generated floor: ``rows`` of the map (first line north), the ``features`` drawn (for the report) and the
    scenario's table (:func:`~virtual_vehicle.config.scenario.parse_scenario` takes it)."""

    seed: int
    rows: list[str]
    features: dict
    table: dict

    def scenario(self):
        """The floor as a validated scenario."""
        from virtual_vehicle.config.scenario import parse_scenario

        return parse_scenario(self.table)


def _reachable(grid: np.ndarray, starts: list[tuple[int, int]], goals: set[tuple[int, int]]) -> bool:
    """Whether a BLOCK x BLOCK window of cells (``grid``: map letters, "." no cell) gets from any of ``starts`` to
    any of ``goals`` (top-left corners), moving a row or column at a time over cells only, never against an arrow
    of a cell it leaves or enters."""
    H, W = grid.shape
    cell = grid != "."

    def fits(r, c):
        return 0 <= r <= H - BLOCK and 0 <= c <= W - BLOCK and cell[r:r + BLOCK, c:c + BLOCK].all()

    def allowed(r, c, move):
        window = grid[r:r + BLOCK, c:c + BLOCK]
        return not any(_AGAINST.get(ch) == move for ch in set(window.ravel().tolist()))

    seen = {s for s in starts if fits(*s)}
    queue = deque(seen)
    while queue:
        r, c = queue.popleft()
        if (r, c) in goals:
            return True
        for move in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            nr, nc = r + move[0], c + move[1]
            if (nr, nc) not in seen and fits(nr, nc) and allowed(r, c, move) and allowed(nr, nc, move):
                seen.add((nr, nc))
                queue.append((nr, nc))
    return False


def _windows(mask: np.ndarray) -> list[tuple[int, int]]:
    """Top-left corners of the BLOCK x BLOCK windows wholly inside ``mask``."""
    H, W = mask.shape
    return [(r, c) for r in range(H - BLOCK + 1) for c in range(W - BLOCK + 1)
            if mask[r:r + BLOCK, c:c + BLOCK].all()]


def _draw(rng: np.random.Generator):
    """One map and its features, not yet checked."""
    W, H = int(rng.integers(16, 25)), int(rng.integers(12, 17))
    grid = np.full((H, W), "o")
    features: dict = {"size": (W, H), "holes": 0, "one_way": [], "parking": 0}
    # entries: 3 x 4 blocks on the west edge, a row apart
    n_in = int(rng.integers(1, 4))
    free = list(range(0, H - 3, 5))
    starts_r = sorted(rng.choice(free, size=min(n_in, len(free)), replace=False).tolist())
    for r in starts_r:
        grid[r:r + 4, 0:3] = "E"
    # exits: lanes of 4 x 3 cells reaching the east or the north edge
    n_out = int(rng.integers(1, 4))
    lanes = []
    east = list(range(0, H - 3, 5))
    north = list(range(6, W - 7, 6))
    sides = [("east", r) for r in east] + [("north", c) for c in north]
    for k in rng.permutation(len(sides))[:n_out].tolist():
        side, at = sides[k]
        lanes.append((side, at))
    for k, (side, at) in enumerate(lanes):
        if side == "east":
            grid[at:at + 4, W - 3:W] = str(k)
        else:
            grid[0:3, at:at + 4] = str(k)
    features["entries"], features["exits"] = len(starts_r), len(lanes)
    interior = (grid == "o")
    # one-way aisles: bands of 4 rows (or 4 columns) with one arrow
    for _ in range(int(rng.integers(0, 3))):
        if rng.random() < 0.6:
            r = int(rng.integers(0, H - 3))
            arrow = ">" if rng.random() < 0.8 else "<"
            band = np.zeros_like(interior)
            band[r:r + 4, 3:W - 3] = True
        else:
            c = int(rng.integers(3, W - 6))
            arrow = "^" if rng.random() < 0.7 else "v"
            band = np.zeros_like(interior)
            band[3:H, c:c + 4] = True
        grid[band & interior] = arrow
        features["one_way"].append(arrow)
    # holes: small missing patches inside
    for _ in range(int(rng.integers(0, 5))):
        h, w = int(rng.integers(1, 4)), int(rng.integers(1, 4))
        r, c = int(rng.integers(1, H - h)), int(rng.integers(4, W - 3 - w))
        patch = grid[r:r + h, c:c + w]
        if np.isin(patch, list("o<>^v")).all():
            grid[r:r + h, c:c + w] = "."
            features["holes"] += 1
    # parking bays: a 4 x 4 pocket along the south edge with its parking cell in the second row
    if rng.random() < 0.3:
        for _ in range(int(rng.integers(1, 3))):
            c = int(rng.integers(4, W - 7))
            if (grid[H - 4:H, c:c + 4] == "o").all():
                grid[H - 2, c + 1] = "P"
                features["parking"] += 1
    return grid, features, starts_r, lanes


def bays_needed(order) -> int:
    """The most parcels of a sequenced stream that must park at once, the parcels arriving in the order given
    (``order[i]``: the sequence number of the i-th to arrive): after each arrival, those whose number is above the
    one due next (all smaller numbers have arrived, and leave in order as soon as they have)."""
    arrived, due, most = set(), 0, 0
    for q in order:
        arrived.add(q)
        while due in arrived:
            due += 1
        most = max(most, sum(a > due for a in arrived))
    return most


def bay_order(parcels: int, bays: int, rng: np.random.Generator) -> list[int]:
    """Sequence numbers 0..parcels-1 in a random arrival order that never needs more than ``bays`` parked at once
    (:func:`bays_needed`): each arrival takes one of the smallest numbers not yet given, as many to choose from as
    bays are free, plus the number due (which needs no bay). A stream that needs more bays than the floor has cannot
    be sequenced there, whatever the rules: such floors are not drawn."""
    left = list(range(parcels))
    order: list[int] = []
    for _ in range(parcels):
        due = left[0]
        parked = sum(q > due for q in order)
        pick = left[int(rng.integers(max(1, min(len(left), bays + 1 - parked))))]
        order.append(pick)
        left.remove(pick)
    return order


def random_floor(seed: int, *, parcels: int = 8, duration: float = 16.0, wait_bound: float = 4.0) -> Floor:
    """A floor drawn from ``seed`` (see the module notes) with a stream of ``parcels`` parcels (one every 1.5-3 s
    from random entries to random exits; with parking bays a sequenced stream to exit 0 whose arrival order never
    needs more bays than the floor has, :func:`bay_order`), run for ``duration`` s,
    stalls reported after ``wait_bound`` s of standing still. Deterministic in its arguments."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        grid, features, entries, lanes = _draw(rng)
        ok = bool(entries) and bool(lanes)
        for r in entries:
            starts = [(r, 0), (r + 1, 0)]
            for k in range(len(lanes)):
                goals = set(_windows(grid == str(k)))
                ok = ok and _reachable(grid, starts, goals)
        if ok:
            break
    else:  # pragma: no cover - the draws above nearly always succeed within a few tries
        raise ValueError(f"seed {seed}: no floor with every exit reachable in 200 draws")
    H = grid.shape[0]
    sequenced = features["parking"] > 0
    items, t = [], 0.0
    order = rng.permutation(parcels).tolist()
    if sequenced:  # an order the bays can hold (the draw above is kept, so that the rest of the floor is the same)
        order = bay_order(parcels, features["parking"], np.random.default_rng([seed, 1]))
    for i in range(parcels):
        length, width = float(rng.choice([0.22, 0.25, 0.3])), float(rng.choice([0.22, 0.25]))
        r = entries[int(rng.integers(len(entries)))]
        item = {"name": f"p{i:02d}", "length": length, "width": width, "mass": float(rng.choice([1.0, 1.5, 2.0])),
                "mu": 2.0, "x": 0.13, "y": round((H - 1 - (r + 1.5)) * PITCH, 6), "t_start": round(t, 3),
                "destination": 0 if sequenced else int(rng.integers(len(lanes)))}
        if sequenced:
            item["sequence"] = order[i]
        items.append(item)
        t += float(rng.uniform(1.5, 3.0))
    rows = ["".join(row) for row in grid]
    table = {"name": f"stress_{seed}", "duration": duration, "output_dt": 0.05,
             "array": {"kind": "map", "pitch": PITCH, "map": "\n".join(rows)},
             "control": {"program": "sort", "speed": 0.3, "gap": 2, "reach": 8, "wait_bound": wait_bound},
             "friction": {"law": "viscous"}, "contacts": {"mu": 0.3}, "parcels": items}
    return Floor(seed, rows, features, table)


def explain(floor: Floor, setup, stall: dict) -> str:
    """One line on a stall: its kind, parcels, when, and the map features its cells and their neighbours touch
    (entry, exit lane, one-way arrows, parking, holes or the edge)."""
    rows = floor.rows
    H, W = len(rows), len(rows[0])
    pos = setup.cells.positions[stall["cells"]] if stall["cells"] else np.zeros((0, 2))
    near = set()
    for x, y in pos:
        c, r = int(round(x / PITCH)), H - 1 - int(round(y / PITCH))
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                rr, cc = r + dr, c + dc
                near.add("edge" if not (0 <= rr < H and 0 <= cc < W) else rows[rr][cc])
    names = {"E": "entry", "P": "parking", ".": "hole", "edge": "edge", ">": "aisle >", "<": "aisle <",
             "^": "aisle ^", "v": "aisle v"}
    touched = sorted({names.get(ch, f"exit {ch}" if ch.isdigit() else None) for ch in near} - {None})
    return (f"seed {floor.seed}: {stall['kind']} of {', '.join(stall['parcels'])} from {stall['t_s']:.1f} s, "
            f"near {', '.join(touched) or 'open floor'}")


def stress(seeds, *, parcels: int = 8, duration: float = 16.0, wait_bound: float = 4.0) -> list[dict]:
    """Run :func:`random_floor` of each seed and report, a row a seed: the floor's features, parcels delivered
    correctly, misrouted, lost, collisions, still on the array, never put on, the stalls by kind and one line on
    each (:func:`explain`)."""
    from virtual_vehicle.run.sim import run
    from virtual_vehicle.run.tasks import sorting_report

    out = []
    for seed in seeds:
        floor = random_floor(seed, parcels=parcels, duration=duration, wait_bound=wait_bound)
        setup = floor.scenario().build()
        rep = sorting_report(run(setup))
        stalls = rep["stalls"]
        out.append({"seed": seed, **{k: floor.features[k] for k in ("entries", "exits", "holes", "parking")},
                    "one_way": "".join(floor.features["one_way"]) or "-",
                    **{k: rep[k] for k in ("correct", "misrouted", "lost", "collisions", "on_array", "waiting")},
                    "deadlocks": sum(s["kind"] == "deadlock" for s in stalls),
                    "waits": sum(s["kind"] == "waiting" for s in stalls),
                    "why": [explain(floor, setup, s) for s in stalls]})
    return out
