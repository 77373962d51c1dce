"""The plant: planar parcel motion on a cell array, integrated piecewise between support changes (paper 4.5).

Units: SI (m, s, kg, N, rad). The state of a parcel is ``[x, y, theta, vx, vy, omega]`` (centre of mass, heading,
their rates); the equations of motion are ``m Xddot_c = f``, ``I thetaddot = tau`` with f and tau from the friction
law's per-support-set constants.

Paper 4.5, made exact: compute the cells under the parcel, form the mask (here: the contact set), compute the
constants, integrate, and when the supports change recompute the constants and continue. "The supports change" is
located as an event to the integrator's tolerance: a cell entering or leaving the footprint (a zero of its margin), a
cell lifting off or touching down (a zero of its spring force), or the centre of mass leaving the supports (tipping).
Constants are cached per (support set, contact set), so a configuration seen again is not solved again.

Two integrators share the model:
- ``"event"``: adaptive 8th-order Dormand-Prince (scipy's DOP853 scheme) on each smooth piece, events located by
  root finding on the dense output, restarted with the new constants. One parcel's event loop is compiled
  (:func:`~virtual_vehicle.engine._kernel.run_events`): each piece's steps, event search and location, then the next
  piece from the model's solved supports held as arrays (:class:`_PieceTable`), or made there from a solved pattern
  with the law's compiled drive, or from a pattern solved there (contact's compiled planar solve, the Python solve's
  arithmetic); candidate cells are gathered again there too, and the cells under the parcel found there where the
  probe's event values cannot tell them. Python takes over only for what the arrays cannot give: supports on one
  line, a collinear contact set or tipping (the solve in :mod:`~virtual_vehicle.physics.contact`), a full table, a
  candidate refresh within a rounding step of its threshold, a chatter, a pause for a progress callback; and it
  makes the Python objects of the new pieces after each call, and those of the new solutions and events as shells
  whose arrays (a solution's) and changed cells (an event's) are unpacked from the loop's records only when read;
- ``"fixed"``: classical RK4 at a fixed step that looks up the supports at every stage and never locates events,
  for comparison (first-order accurate across support changes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, partial
from itertools import compress
from typing import Callable, Literal, get_args

import numpy as np

from virtual_vehicle.engine import _kernel, _modeloop
from virtual_vehicle.engine._kernel import accelerations
from virtual_vehicle.engine.stepping import Event, Trajectory, diff_event, fixed_steps, sample_grid
from virtual_vehicle.engine.stickslip import run_stick_slip
from virtual_vehicle.errors import IntegrationError, TippingError
from virtual_vehicle.model.layout import CellArray
from virtual_vehicle.model.parcel import ALL_PRESENT, ParcelSpec
from virtual_vehicle.physics.contact import SupportSolution, solve_prechecked
from virtual_vehicle.physics.laws import FrictionConstants, FrictionLaw, affine
from virtual_vehicle.physics.stick_modes import breaking_kernel, decide_kernel

TIME_STEPPERS = {"stick_slip": run_stick_slip}
"""The engine's time steppers by the name a time-stepped law gives (its ``time_stepper``): each solves the law's
modes every step at ``dt`` (s) instead of integrating affine pieces between events."""

Mode = Literal["event", "fixed"]
MODES = get_args(Mode)
"""The modes of :func:`integrate` (and of a plant's :class:`~virtual_vehicle.engine.plant.Integration`)."""

_PATTERN_RESOLUTION = 1e-9
"""Relative positions of supporting cells are compared to this fraction of the pitch when matching patterns."""


class _GeometryCache:
    """Solved support geometries by pattern, for the models of one parcel that differ only in wheel velocities.

    ``shared`` holds the planar solutions whose contact set is not collinear, solved in the pattern's own coordinates
    (its integer offsets times ``_PATTERN_RESOLUTION`` pitches): the normal-force map of eqs. 13-19 then depends on
    the pattern, the weight and the contact set alone, not on where or by which parcel it was first met, so parcels
    of the same weight on the same array may share them and each still runs bit for bit as it would alone. ``own``
    holds the rest (a 1-D or collinear contact set, whose solution depends on the centre of mass it was solved
    at). ``solves`` counts the problems this parcel had to solve."""

    def __init__(self, shared: dict | None = None):
        self.shared: dict[bytes, list[SupportSolution]] = {} if shared is None else shared
        self.own: dict[bytes, list[SupportSolution]] = {}
        self.solves = 0


@dataclass(frozen=True, eq=False)
class Piece:
    """One smooth piece of the dynamics: a support set, its contact set, the normal-force map and the constants.

    ``rhs(t, y)`` is the state derivative valid while the pieces' support and contact sets hold.
    """

    support: np.ndarray
    solution: SupportSolution
    constants: FrictionConstants
    rhs: Callable[[float, np.ndarray], np.ndarray]
    mass: float = 1.0
    inertia: float = 1.0
    row: tuple[float, ...] = ()
    """The constants as :func:`constants_row` lists them (what the compiled engine integrates)."""

    @cached_property
    def key(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """(supporting cell ids, ids of those in contact)."""
        return tuple(self.support.tolist()), tuple(self.support[self.solution.in_contact].tolist())

    @cached_property
    def sets(self) -> tuple[frozenset[int], frozenset[int]]:
        """:attr:`key` as sets: (supporting cell ids, ids of those in contact)."""
        return frozenset(self.key[0]), frozenset(self.key[1])

    def normal_forces(self, y) -> np.ndarray:
        """Normal forces (N) of the supporting cells at state ``y``."""
        return self.solution.forces(np.asarray(y[:2], dtype=float))

    @classmethod
    def of(cls, support: np.ndarray, solution: SupportSolution, constants: FrictionConstants, mass: float,
           inertia: float, row: tuple[float, ...], support_key: tuple[int, ...]) -> "Piece":
        """The piece of these parts (``row`` is :func:`constants_row` of them), its :attr:`key` made from
        ``support_key``, ``tuple(support.tolist())``, which a model looking pieces up by their cells has made
        already (converting the cells again took a good part of a new piece's bookkeeping)."""
        piece = cls(support, solution, constants, _make_rhs(row), mass, inertia, row)
        piece.__dict__["key"] = support_key, tuple(compress(support_key, solution.in_contact.tolist()))
        return piece


def constants_row(k: FrictionConstants, origin: np.ndarray, mass: float, inertia: float) -> tuple[float, ...]:
    """A piece's constants as plain floats, in the order :func:`~virtual_vehicle.engine._kernel.accelerations`
    takes them (named by :data:`~virtual_vehicle.physics.laws.affine.ROW_FIELDS`): local origin (m), the force and
    torque constants of eqs. 23 and 29, the viscous coefficient and weight, the moments of eqs. 33 and 38, then
    1 / mass and 1 / inertia. (A law's ``constants_and_row`` makes the same row
    with its constants, in one compiled call.)"""
    f64 = affine.f64
    return tuple(affine.row(*map(f64, (k.a, k.b, k.c, k.d, k.e)), float(k.f), float(k.damping), float(k.weight),
                            *map(f64, (k.moment_lin, k.moment_const, k.second_lin)), float(k.second_const),
                            f64(origin), 1.0 / mass, 1.0 / inertia).tolist())


def _make_rhs(row: tuple[float, ...]):
    """State derivative from the constants row (eqs. 23, 29, 33, 38), in plain floats for speed."""
    def rhs(t, y):
        x, yy, _th, vx, vy, om = y.tolist()
        return np.array((vx, vy, om, *accelerations(row, x, yy, vx, vy, om)))

    return rhs


class _PieceTable:
    """What a model has solved, as the arrays its compiled event loop (:func:`~virtual_vehicle.engine._kernel.
    run_events`) reads (layout in :mod:`virtual_vehicle.engine._kernel`: :data:`~virtual_vehicle.engine._kernel.
    TABLE_FIELDS`), mirroring the model's caches so that the loop finds what :meth:`ParcelModel.piece_for` would:

    - each support set the model has pieces for is in the table with all of them, in the model's order (:meth:`sync`
      adds what the model met elsewhere), so the loop tries them as ``piece_for`` does;
    - each pattern of the model's shared store is in the table with a prefix of its solutions, in the store's order;
      for a support set the model has never met, the loop takes the first of them that holds (``solution_for``'s
      first choice, the store searched before the model's own); when none does, it solves the pattern itself if
      the table mirrors the whole store (:meth:`mirror_store`; then Python would solve it too) and the pattern has no
      solutions of the model's own, else hands back to Python. Solutions it makes are made Python objects and added
      to the model's store after the call (:meth:`adopt_solved`), in order; pieces it makes join the model's cache
      as table entries (:meth:`adopt_born`), made :class:`Piece` objects only when Python asks for one
      (:meth:`piece`: most are only ever named in events, by :meth:`key`).

    Arrays grow by doubling. Past ``max_pieces`` pieces the table and the model's piece cache are emptied (the
    solved patterns stay): memory stays bounded over long runs, and a support set met again is made again from its
    pattern, as the model's first meeting it made it."""

    max_pieces = 1 << 15
    """Pieces held before the table and the model's piece cache are emptied (a piece: ~300 bytes in the table)."""
    spare = 64
    """Pieces (and support sets, and solves) the loop may add in one call: the arrays have room for them when it
    starts. A call that fills it doubles it for the next (up to :attr:`max_spare`), so a parcel that makes many
    pieces hands back to Python a number of times logarithmic in them, not linear."""
    max_spare = 512
    """The most :attr:`spare` grows to: the arrays' room follows it (the float pool a few KiB a piece of room), and
    a table is kept per parcel, so this bounds what the growth can add to ~2 MiB a parcel."""

    def __init__(self, model: "ParcelModel", row_length: int):
        self.row_length = row_length
        law, spec = model.law, model.spec
        self.drive = _kernel.drive_code(law)
        self.damping = law.affine_damping(spec.mu) if self.drive else 0.0
        self.law_args = (self.drive, _readonly(model.cells.positions), _PATTERN_RESOLUTION * model.cells.pitch,
                         _readonly(model.velocities),
                         _readonly(np.ascontiguousarray(model.cells.active_directions, dtype=float)),
                         float(spec.mu), float(self.damping), 1.0 / spec.mass, 1.0 / spec.inertia,
                         np.empty((self.spare, affine._TERMS)), float(model.weight),
                         np.zeros((self.spare + 1, 2), np.int64), np.zeros((self.spare, 2)))
        self.full = False  # the last call filled its room (see spare)
        self.owner: ParcelModel | None = None  # the model whose pieces the table holds (see renew)
        self.loop_args: tuple | None = None
        """The mode loop's arguments that do not change between calls for the parcel (grid, scales, wheel cells,
        logs, chatter ring), with the ``present`` mask they were made for: kept by :func:`_run_modes`."""
        self.blank: tuple | None = None
        """A (wheels, mode) pair as the mode loop takes them, passed where it finds the first piece itself (only
        their types count): kept from a run that had them."""
        self.clear()

    def clear(self) -> None:
        self.slots = np.full(64, -1, np.int64)
        self.kmeta = np.zeros((16, 4), np.int64)
        self.ipool = np.zeros(256, np.int64)
        self.psol = np.zeros(16, np.int64)
        self.porigin = np.zeros((16, 2))
        self.pnext = np.zeros(16, np.int64)
        self.pkey = np.zeros(16, np.int64)
        self.rows = np.zeros((16, self.row_length))
        self.srec = np.zeros((16, 6), np.int64)
        self.fpool = np.zeros(4096)
        self.gslots = np.full(64, -1, np.int64)
        self.gmeta = np.zeros((16, 5), np.int64)
        self.used = np.zeros(6, np.int64)
        self.front = 0, 0  # (patterns, ids) whose ids lead the pool in the patterns' order (see renew)
        self.index: dict[Piece, int] = {}
        self.pieces: list[Piece | None] = []  # None: a piece the loop made, not yet asked for (see piece)
        self.unmade: dict[int, tuple] = {}  # such a piece's index -> (its key, its packed friction terms)
        self.records: list[SupportSolution] = []
        self.record_of: dict[int, int] = {}  # id of a record's holding array -> its index
        self.patterns: dict[bytes, tuple[int, int]] = {}  # key -> (index, solutions chained)
        self.mirrored = 0
        self.solves = -1
        self.store_solves: int | None = None  # the model's solves when the table last mirrored its whole store

    @property
    def arrays(self) -> tuple:
        """What :func:`~virtual_vehicle.engine._kernel.run_events` takes as its table."""
        return (self.slots, self.kmeta, self.ipool, self.psol, self.porigin, self.pnext, self.pkey, self.rows,
                self.srec, self.fpool, self.gslots, self.gmeta, self.used)

    def sync(self, model: "ParcelModel", piece: Piece | None) -> bool:
        """Before a loop on ``piece``: add every support set of the model's cache the table lacks pieces of, if the
        cache has grown since the table last matched it (the plant and quiet steppers look pieces up outside the
        loop); past :attr:`max_pieces` empty the table and the model's piece cache (keeping ``piece``); make room
        for what the loop may add. Returns whether it emptied them. (``piece`` None: the loop finds its first piece
        itself; the caller made sure the table need not be emptied.)"""
        if self.full:  # the last call filled its room: twice as much for this one
            self.full = False
            self.spare = min(2 * self.spare, self.max_spare)
            a = self.law_args
            self.law_args = (*a[:9], np.empty((self.spare, affine._TERMS)), a[10],
                             np.zeros((self.spare + 1, 2), np.int64), np.zeros((self.spare, 2)))
        emptied = len(self.pieces) > self.max_pieces
        if emptied:
            self.clear()
            model._pieces.clear()
            model._by_support.clear()
            model._unmade.clear()
            model._pieces[piece.key] = piece
            model._by_support[piece.key[0]] = [piece]
        if model.pieces_cached != self.mirrored:
            for pieces in list(model._by_support.values()):
                if pieces[-1] not in self.index:
                    self.index_of(model, pieces[-1])
            self.mirrored = model.pieces_cached
        if self.store_solves != model.solves:
            self.mirror_store(model)
        log = self.law_args[-2]
        log[0, 0], log[0, 1] = (1 if self.drive and self.store_solves == model.solves else 0), 0
        n_pieces, n_keys, n_floats, n_ids, n_records, n_patterns = self.used.tolist()
        spare, ids = self.spare, 3 * self.spare * (1 + n_ids // max(1, n_keys)) + 64
        floats = spare * (n_floats // max(1, n_records) + 256)
        if (n_pieces + spare > len(self.psol) or n_keys + spare > len(self.kmeta) or n_ids + ids > len(self.ipool)
                or 2 * (n_keys + spare) > len(self.slots) or n_records + spare > len(self.srec)
                or n_patterns + spare > len(self.gmeta) or 2 * (n_patterns + spare) > len(self.gslots)
                or n_floats + floats > len(self.fpool)):
            self._room(pieces=spare, keys=spare, ids=ids, records=spare, patterns=spare, floats=floats)
        return emptied

    def renew(self, model: "ParcelModel") -> None:
        """Take the table over for ``model``, a copy of its owner under other wheel velocities (a plant makes its
        parcels' models again every control tick): the solved patterns and their records, which depend only on the
        supports' geometry, stay; the pieces, whose friction constants depend on the wheels, go. A 10 ms window of a
        catching-up parcel otherwise built a table from nothing (its arrays grown from their first size, the store's
        patterns copied in again): ~60 % of such a window's Python. The owner's piece cache is emptied with it (as
        :meth:`sync` empties both), so that, should it run again, it runs as it first did, from nothing cached."""
        previous = self.owner
        if previous is not None:  # its piece cache goes with the table, as sync empties both
            previous._pieces, previous._by_support, previous._unmade = {}, {}, {}
            previous._table = None
        used = self.used
        if used[_kernel.U_RECORDS] > self.max_pieces:  # bounded memory, as sync bounds the pieces
            self.clear()
        else:  # the patterns' ids moved to the front of the pool, the support sets' ids dropped
            n_patterns = int(used[_kernel.U_PATTERNS])
            if n_patterns != self.front[0]:  # (else they are there from the last take-over: most ticks learn none)
                spans = self.gmeta[:n_patterns, :2].tolist()
                kept = [self.ipool[off:off + n] for off, n in spans]
                ids = np.concatenate(kept) if kept else np.zeros(0, np.int64)
                self.ipool[:len(ids)] = ids
                self.gmeta[:n_patterns, 0] = np.cumsum([0] + [n for _, n in spans[:-1]]) if spans else 0
                self.front = n_patterns, len(ids)
            used[_kernel.U_IDS] = self.front[1]
            used[_kernel.U_PIECES] = used[_kernel.U_KEYS] = 0
            self.slots.fill(-1)
            self.index, self.pieces, self.unmade = {}, [], {}
            self.mirrored, self.solves = 0, -1
        self.law_args = (*self.law_args[:3], _readonly(model.velocities), *self.law_args[4:])
        self.owner = model

    mirror_limit = 32
    """Patterns in the model's store up to which a table that does not mirror it (new, emptied, or behind a copy of
    the model that solved elsewhere) learns them all, so that its loop may solve new ones: past it the loop hands
    every unsolved pattern back to Python (learning hundreds would cost a control tick more than it saves)."""

    def mirror_store(self, model: "ParcelModel") -> None:
        """Learn every pattern of the model's store (shared solutions, and which patterns have solutions of their
        own), if it is small (:attr:`mirror_limit`): then a pattern the loop finds unsolved is one Python would
        solve, and the loop may solve it (the same arithmetic, the same place in the store)."""
        geometry = model._geometry
        if not self.drive or len(geometry.shared) + len(geometry.own) > self.mirror_limit:
            self.store_solves = None
            return
        for gkey in (*geometry.shared, *geometry.own):
            self._learn_key(model, gkey)
        self.store_solves = model.solves

    def adopt_solved(self, model: "ParcelModel") -> None:
        """Add what the loop solved (``solve_log``) to the model's shared store as
        :class:`~virtual_vehicle.physics.contact.SupportSolution` objects, as :meth:`ParcelModel.solution_for` would
        have (in order, counted in its solves), and to this table's records."""
        log, origins = self.law_args[-2], self.law_args[-1]
        n = int(log[0, 1])
        self.full |= n >= len(origins)
        if not n:
            return
        geometry, ipool = model._geometry, self.ipool
        for (j, g), origin in zip(log[1:1 + n].tolist(), origins[:n].copy()):
            assert j == len(self.records)  # the loop adds records after the table's
            off, m, r, q, nh = self.srec[j, :5].tolist()  # the record's floats as _kernel.table_add_record lays them
            flat = self.fpool[off:off + _kernel.record_floats(m, r, q, nh)].copy()
            flat.setflags(write=False)  # and so every view of it
            holding = flat[len(flat) - nh:]
            in_contact = holding[3 + m * r + 3 * r:3 + m * r + 3 * r + m] > 0.5
            in_contact.setflags(write=False)
            sol = SupportSolution.__new__(SupportSolution)
            sol.__dict__.update(origin=origin, in_contact=in_contact, one_d=False, weight=float(flat[0]),
                                _holding=holding, contact_collinear=False,
                                _unpack=partial(_record_arrays, flat, m, r, q))
            off, length = self.gmeta[g, :2].tolist()
            gkey = ipool[off:off + length].tobytes()
            solved = geometry.shared.setdefault(gkey, [])
            solved.append(sol)
            geometry.solves += 1
            self.records.append(sol)
            self.record_of[id(holding)] = j
            self.patterns[gkey] = g, len(solved)
        log[0, 1] = 0
        if self.store_solves is not None:
            self.store_solves += n

    def learn(self, model: "ParcelModel", piece: Piece) -> None:
        """After the model found ``piece`` outside the loop (a miss): add it (with its support set's pieces) and its
        pattern's solutions, so that the loop finds both next time."""
        if model.solves != self.solves:  # a pattern solved now (or elsewhere, by a copy of the model)
            self.solves = model.solves
            self.learn_pattern(model, piece.support)
            if self.store_solves is not None and model.solves != self.store_solves:  # mirrored if this one solve
                self.store_solves = model.solves if model.solves == self.store_solves + 1 else None
        self.index_of(model, piece)  # after its pattern: a piece of a pattern shares the pattern's record
        if model.pieces_cached - self.mirrored <= 1:  # piece_for adds at most this one: the table matches again
            self.mirrored = model.pieces_cached

    def index_of(self, model: "ParcelModel", piece: Piece) -> int:
        """The index of ``piece`` (one of ``model``'s), adding it and the pieces of its support set before it."""
        found = self.index.get(piece)
        if found is not None:
            return found
        skey = piece.key[0]
        ids = np.array(skey, dtype=np.int64)
        for other in model._by_support.get(skey, [piece]):
            if other in self.index:
                continue
            sol = other.solution
            j = self._record(sol)
            used = self.used
            if (used[_kernel.U_PIECES] >= len(self.psol) or used[_kernel.U_KEYS] >= len(self.kmeta)
                    or used[_kernel.U_IDS] + len(ids) > len(self.ipool) or 2 * (used[_kernel.U_KEYS] + 1) > len(
                        self.slots)):
                self._room(pieces=1, keys=1, ids=len(ids))
            p = _kernel.table_add_piece_of(self.slots, self.kmeta, self.ipool, self.psol, self.porigin, self.pnext,
                                           self.pkey, self.rows, self.used, ids, j, sol.origin, np.array(other.row))
            self.index[other] = p
            self.pieces.append(other)
        return self.index[piece]

    def _record(self, sol: SupportSolution) -> int:
        """The record of ``sol``'s arrays (contiguous float64, as physics.contact makes them), added unless a record
        of the same arrays is there (a translated copy of a pattern's solution shares them: ``SupportSolution.at``);
        its index."""
        holding = sol._holding
        found = self.record_of.get(id(holding))
        if found is not None:
            return found
        m, r = sol.basis.shape
        floats = _kernel.record_floats(m, r, len(sol.hull_offsets), len(holding))
        used = self.used
        if (used[_kernel.U_FLOATS] + floats > len(self.fpool) or used[_kernel.U_RECORDS] >= len(self.srec)
                or used[_kernel.U_PIECES] >= len(self.psol)):
            self._room(pieces=1, records=1, floats=floats)
        j = _kernel.table_add_record(self.srec, self.fpool, self.used, float(sol.weight), sol.basis, sol.plane_lin,
                                     sol.plane_const, sol.hull_normals, sol.hull_offsets, sol.spring_lin,
                                     sol.spring_gradient, sol.points, sol.force_lin, sol.force_const, holding)
        self.records.append(sol)  # (which keeps holding, the key, alive)
        self.record_of[id(holding)] = j
        return j

    def learn_pattern(self, model: "ParcelModel", support: np.ndarray) -> None:
        """Add the solutions of the pattern of cells ``support`` in the model's shared store the table lacks."""
        if not self.drive or len(support) == 0:
            return
        _, _, rel = _kernel.pattern(model.cells.positions, support, _PATTERN_RESOLUTION * model.cells.pitch)
        self._learn_key(model, rel.tobytes())

    def _learn_key(self, model: "ParcelModel", gkey: bytes) -> None:
        """:meth:`learn_pattern` of the pattern whose key (its cells' integer offsets, int64 bytes) is ``gkey``: its
        shared solutions the table lacks, and whether the model holds solutions of it of its own."""
        solved = model._geometry.shared.get(gkey, ())
        own = gkey in model._geometry.own
        g, chained = self.patterns.get(gkey, (-1, 0))
        if chained == len(solved) and (not own or (g >= 0 and self.gmeta[g, 4])):
            return
        if g < 0:
            flat = np.frombuffer(gkey, np.int64).copy()
            self._room(patterns=1, ids=len(flat))
            g = _kernel.table_add_key(self.gslots, self.gmeta, self.ipool, self.used, _kernel.U_PATTERNS, flat)
        for sol in solved[chained:]:
            _kernel.table_chain_record(self.srec, self.gmeta, g, self._record(sol))
        if own:
            self.gmeta[g, 4] = 1
        self.patterns[gkey] = g, len(solved)

    def adopt_born(self, model: "ParcelModel", start: int, born: int) -> None:
        """Add the ``born`` pieces the loop made from patterns (indices from ``start``) to the model's cache as table
        entries (``model._unmade``: support key -> indices, in the order made), where :meth:`ParcelModel.piece_for` finds them as it
        would have found the pieces it made itself. Making each a :class:`Piece` at once was a third of the Python
        of an oscillating Coulomb parcel (367 pieces in 5 s, most of them never asked for)."""
        self.full |= born >= len(self.law_args[9])
        terms = self.law_args[9][:born].copy()  # the packed constants the law's compiled drive made, a row a piece
        ipool, records = self.ipool, self.records
        spans = self.kmeta[self.pkey[start:start + born], :2].tolist()  # (each piece's support set: its ids in ipool)
        for i, (off, n), j in zip(range(born), spans, self.psol[start:start + born].tolist()):
            skey = tuple(ipool[off:off + n].tolist())
            model._unmade.setdefault(skey, []).append(start + i)  # (a set met before on other contacts)
            self.unmade[start + i] = (skey, tuple(compress(skey, records[j].in_contact.tolist()))), terms[i]
            self.pieces.append(None)
        self.mirrored += born

    def key(self, p: int) -> tuple:
        """The :attr:`Piece.key` of piece ``p``, whether or not it has been made a :class:`Piece`."""
        piece = self.pieces[p]
        return piece.key if piece is not None else self.unmade[p][0]

    def piece(self, model: "ParcelModel", p: int) -> Piece:
        """Piece ``p`` of the table as a :class:`Piece`, made now if the loop made it (see :meth:`adopt_born`)."""
        piece = self.pieces[p]
        if piece is None:
            self.make(model, self.unmade[p][0][0])
            piece = self.pieces[p]
        return piece

    def make(self, model: "ParcelModel", skey: tuple) -> None:
        """Make the pieces the loop made for the support set ``skey`` :class:`Piece` objects, in the model's cache as
        :meth:`ParcelModel.piece_for` would have put them: after the set's pieces made before, in the order the loop
        made them (a set met again on other contacts has several; the first that holds is the one found)."""
        for p in model._unmade.pop(skey):
            key, k_terms = self.unmade.pop(p)
            sol = self.records[self.psol[p]].at(self.porigin[p].copy())
            k = affine.FrictionConstants(k_terms, self.damping, sol.weight)
            piece = Piece.of(np.array(skey, dtype=np.int64), sol, k, model.spec.mass, model.spec.inertia,
                             tuple(self.rows[p].tolist()), skey)
            model._pieces[key] = piece  # (piece.key: the same tuples, made from the same arrays)
            model._by_support.setdefault(skey, []).append(piece)
            self.index[piece] = p
            self.pieces[p] = piece

    def _room(self, keys: int = 0, ids: int = 0, pieces: int = 0, floats: int = 0, records: int = 0,
              patterns: int = 0) -> None:
        """Grow the arrays (doubling) until this much more fits."""
        n_pieces, n_keys, n_floats, n_ids, n_records, n_patterns = self.used.tolist()
        if n_pieces + pieces > len(self.psol):
            self.psol, self.porigin, self.pnext, self.pkey, self.rows = (
                _grown(a, n_pieces + pieces, n_pieces) for a in (self.psol, self.porigin, self.pnext, self.pkey,
                                                                 self.rows))
        if n_records + records > len(self.srec):
            self.srec = _grown(self.srec, n_records + records, n_records)
        if n_floats + floats > len(self.fpool):
            self.fpool = _grown(self.fpool, n_floats + floats, n_floats)
        if n_ids + ids > len(self.ipool):
            self.ipool = _grown(self.ipool, n_ids + ids, n_ids)
        if n_keys + keys > len(self.kmeta):
            self.kmeta = _grown(self.kmeta, n_keys + keys, n_keys)
        if n_patterns + patterns > len(self.gmeta):  # (zeros: a new pattern's flag column is read as written)
            self.gmeta = _grown(self.gmeta, n_patterns + patterns, n_patterns, zeros=True)
        for name, meta, n in (("slots", self.kmeta, n_keys + keys), ("gslots", self.gmeta, n_patterns + patterns)):
            slots = getattr(self, name)
            if 2 * n > len(slots):  # at most half full, so that probes stay short
                size = len(slots)
                while 2 * n > size:
                    size *= 2
                slots = np.full(size, -1, np.int64)
                _kernel.table_rehash(slots, meta, self.ipool, n_keys if name == "slots" else n_patterns)
                setattr(self, name, slots)


def _record_arrays(flat: np.ndarray, m: int, r: int, q: int) -> dict[str, np.ndarray]:
    """The arrays of a solution the compiled loop solved, by :class:`~virtual_vehicle.physics.contact.SupportSolution`
    attribute, as views of ``flat`` (its record's floats as :func:`~virtual_vehicle.engine._kernel.table_add_record`
    lays them: weight, basis, plane_lin, plane_const, hull_normals, hull_offsets, spring_lin, spring_gradient, points,
    force_lin, force_const, the holding test); unpacked only when the solution's arrays are read."""
    names = ("basis", "plane_lin", "plane_const", "hull_normals", "hull_offsets", "spring_lin", "spring_gradient",
             "points", "force_lin", "force_const")
    shapes = ((m, r), (r, 2), (r,), (q, 2), (q,), (m, 2), (m,), (m, 2), (m, 2), (m,))
    out, at = {}, 1
    for name, shape in zip(names, shapes):
        size = math.prod(shape)
        out[name] = flat[at:at + size].reshape(shape)
        at += size
    return out


def _readonly(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (no copy): the compiled loop then has one type for it whoever made the array (a
    writable and a read-only array are two types to numba, and each its own compilation)."""
    view = a.view()
    view.flags.writeable = False
    return view


def _grown(a: np.ndarray, need: int, used: int, zeros: bool = False) -> np.ndarray:
    """``a`` in a new array at least ``need`` rows long (its length doubled until it is), its first ``used`` rows
    copied; the rest is left as the allocator gives it unless ``zeros`` (the table writes a row before it reads it).
    Zeroing the room, most of which a call never reaches, touched every page of it: ~0.4 ms a growth of a fresh
    table's float pool, a tenth of a Coulomb parcel's 5 s."""
    size = len(a)
    while size < need:
        size *= 2
    out = (np.zeros if zeros else np.empty)((size, *a.shape[1:]), a.dtype)
    out[:used] = a[:used]
    return out


class ParcelModel:
    """One parcel on one cell array under constant wheel velocities and a friction law.

    Args:
        cells: the array.
        spec: the parcel.
        velocities: (n, 2) cell surface velocities, m/s.
        law: the friction law.
        gravity: m/s^2.
        shared_solutions: a store of solved supports to share with the models of other parcels of the same weight
            on the same array (see ``_GeometryCache``); None: this parcel's own.
    """

    def __init__(self, cells: CellArray, spec: ParcelSpec, velocities: np.ndarray, law: FrictionLaw,
                 gravity: float = 9.81, shared_solutions: dict | None = None):
        self.cells = cells
        self.spec = spec
        self.velocities = np.asarray(velocities, dtype=float)
        if self.velocities.shape != (cells.n, 2) or not np.all(np.isfinite(self.velocities)):
            raise ValueError(f"velocities must be finite with shape ({cells.n}, 2)")
        self.law = law
        law.supports(cells)
        if law.time_stepper is not None and law.time_stepper not in TIME_STEPPERS:
            raise ValueError(f"the {law.name} law asks for a time stepper {law.time_stepper!r} the engine does not "
                             f"have: one of {', '.join(map(repr, TIME_STEPPERS))}")
        self.weight = spec.weight(gravity)
        self._pieces: dict[tuple, Piece] = {}
        self._by_support: dict[tuple[int, ...], list[Piece]] = {}
        self._unmade: dict[tuple[int, ...], list[int]] = {}  # pieces the compiled loop made, not yet asked for
        """Support sets whose one piece the compiled loop made and no one has asked for yet: the index of that piece in
        the table (:meth:`_PieceTable.make` makes it a :class:`Piece`, into the two dicts above)."""
        self._geometry = _GeometryCache(shared_solutions)
        self._table: _PieceTable | None = None
        self._table_home: list[_PieceTable | None] = [None]
        """The table this model or one of its :meth:`with_velocities` copies (which share this list) made last:
        the next of them to need one takes it over (:meth:`_PieceTable.renew`) instead of building one."""
        self.present: np.ndarray | None = None
        """(n,) False for contacts of cells taken out of the array (reconfiguration): they carry nothing. None: all
        present. Set by the plant between integrate calls."""
        self.contact_memory: dict = {"lam": {}, "stuck": {}}
        """Stick-slip: each wheel's last impulse and whether it stuck, carried from one integrate call to the next
        (shared with :meth:`with_velocities` copies), so a run split into control ticks is the same run. Use a
        fresh model for an independent run."""
        self._line_dir = None
        if cells.is_line and cells.n > 1:
            self._line_dir = np.linalg.svd(cells.positions - cells.positions.mean(axis=0), full_matrices=False)[2][0]

    def margins_near(self, y, reach: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The cells present within ``reach`` (m) of the centre of mass at state (or pose) ``y`` (ids, sorted), their
        footprint margins (m, as the event values compute them) and the smallest ``|margin|`` (inf for none)."""
        y = np.ascontiguousarray(y, dtype=float)
        ids = self.cells.grid.within(y[0], y[1], reach, self.present)
        kind, _, half, normals, offsets, vertices = self.outline
        margins, nearest = _kernel.cell_margins(kind, half, normals, offsets, vertices, self.cells.positions[ids], y)
        return ids, margins, nearest

    def support_at(self, y) -> np.ndarray:
        """Ids of the cells under the footprint at state (or pose) ``y`` (those present)."""
        ids, margins, _ = self.margins_near(y, self.spec.radius * (1 + 1e-9) + 1e-12)
        return ids[margins > 0]

    def piece_at(self, y) -> Piece:
        """The piece valid at state ``y``. Raises TippingError when the supports cannot carry the parcel."""
        return self.piece_for(self.support_at(y), y)

    def with_velocities(self, velocities: np.ndarray) -> "ParcelModel":
        """The same parcel on the same array under other wheel velocities (m/s), sharing the solved support
        geometry (normal forces do not depend on the wheels), so a controller may change the field every tick."""
        velocities = np.asarray(velocities, dtype=float)
        if velocities.shape != (self.cells.n, 2) or not np.all(np.isfinite(velocities)):
            raise ValueError(f"velocities must be finite with shape ({self.cells.n}, 2)")
        return self.with_prechecked_velocities(velocities)

    def with_prechecked_velocities(self, velocities: np.ndarray) -> "ParcelModel":
        """:meth:`with_velocities` for ``velocities`` already checked ((n, 2) finite float array, m/s)."""
        self.outline  # made here once, so that every copy shares it
        other = ParcelModel.__new__(ParcelModel)
        other.__dict__.update(self.__dict__)
        other.velocities = velocities
        other._pieces = {}
        other._by_support = {}
        other._unmade = {}
        other._table = None
        return other

    @cached_property
    def outline(self) -> tuple:
        """The parcel's footprint as the compiled engine takes it (:func:`~virtual_vehicle.engine._kernel.outline`),
        made once a model and shared by its :meth:`with_velocities` copies."""
        return _kernel.outline(self.spec)

    @cached_property
    def segment_scales(self) -> tuple[float, float, float, float]:
        """What every :class:`_Segment` of this parcel takes: its radius, the candidates' search buffer (m) and the
        rounding noise of the lengths (m) and of the forces (N) among the event values, below which a sign is not to
        be trusted."""
        spec, cells = self.spec, self.cells
        return (spec.radius, max(cells.pitch, 0.25 * spec.radius), ROUNDING_NOISE * max(1.0, cells.extent, spec.radius),
                ROUNDING_NOISE * self.weight)

    @property
    def shared_solutions(self) -> dict:
        """The store of solved supports this model shares with the models of other parcels of its weight (the
        ``shared_solutions`` it was made with, or its own): a plant drops a store no parcel uses any more."""
        return self._geometry.shared

    @property
    def solves(self) -> int:
        """Normal-force problems solved so far (shared by models made with :meth:`with_velocities`)."""
        return self._geometry.solves

    def piece_for(self, support: np.ndarray, y) -> Piece:
        """The piece for the cells ``support`` at state ``y``.

        Two caches avoid solving a support set again: by the cells themselves, and by their geometric pattern
        (positions relative to the first cell), because on a regular lattice a parcel that has moved by whole cells
        rests on a translated copy of a pattern it has met before, whose local solution is the same. The friction
        constants of a new support set are recomputed from the solution (cheap).
        """
        X = np.asarray(y[:2], dtype=float)
        skey = tuple(support.tolist())
        if skey in self._unmade:
            self._table.make(self, skey)
        for piece in self._by_support.get(skey, ()):
            if piece.solution.holds(X - piece.solution.origin):
                return piece
        sol = self.solution_for(support, X)
        k, row = self.constants_and_row(support, sol, self.velocities[support])
        piece = Piece.of(support, sol, k, self.spec.mass, self.spec.inertia, row, skey)
        existing = self._pieces.get(piece.key)
        if existing is not None:
            return existing
        self._pieces[piece.key] = piece
        self._by_support.setdefault(skey, []).append(piece)
        return piece

    def adopt(self, support: np.ndarray, solution: SupportSolution, constants: FrictionConstants,
               row: tuple[float, ...]) -> None:
        """Cache the piece of the cells ``support`` made elsewhere from ``solution`` and ``constants`` for this
        model's wheels (a quiet stepper's anchor), unless a piece of those cells is cached already."""
        skey = tuple(support.tolist())
        if skey not in self._by_support and skey not in self._unmade:
            piece = Piece.of(support, solution, constants, self.spec.mass, self.spec.inertia, row, skey)
            self._pieces[piece.key] = piece
            self._by_support[skey] = [piece]

    def solution_for(self, support: np.ndarray, com) -> SupportSolution:
        """The solved normal forces of the cells ``support`` with the centre of mass at ``com`` (m), from the cache
        of geometric patterns (shared by all velocities, and by parcels of the same weight) or solved now. Raises
        TippingError when there is none."""
        return self.solution_and_first(support, com)[0]

    def solution_and_first(self, support: np.ndarray, com) -> tuple[SupportSolution, bool]:
        """:meth:`solution_for`, and whether it is the first of its pattern's shared solutions (which the lookup
        tries before any other: wherever it holds on these cells, it is the one found)."""
        X = np.asarray(com, dtype=float)
        if len(support) == 0:
            raise TippingError(f"no cell lies under the parcel at ({X[0]:.6g}, {X[1]:.6g}) m")
        unit = _PATTERN_RESOLUTION * self.cells.pitch
        pts, origin, rel = _kernel.pattern(self.cells.positions, support, unit)
        gkey = rel.tobytes()
        xi = X - origin
        geometry = self._geometry
        for store in (geometry.shared, geometry.own):
            found = next(((k, t) for k, t in enumerate(store.get(gkey, ())) if t.holds(xi)), None)
            if found is not None:
                return found[1].at(origin), found[0] == 0 and store is geometry.shared
        try:  # in the pattern's own coordinates (see _GeometryCache), its first cell at the local origin
            sol = solve_prechecked(rel * unit, X - pts[0], self.weight, self.cells.is_line, self._line_dir)
        except TippingError as exc:  # say where, in the array's coordinates
            try:
                solve_prechecked(pts, X, self.weight, self.cells.is_line, self._line_dir)
            except TippingError as world:
                raise world from None
            raise TippingError(f"the centre of mass at ({X[0]:.6g}, {X[1]:.6g}) m is on the edge of the hull of its "
                               f"{len(pts)} supporting cells, outside it to rounding: the parcel tips") from exc
        geometry.solves += 1
        store = geometry.own if sol.contact_collinear else geometry.shared
        solved = store.setdefault(gkey, [])
        solved.append(sol)
        return sol.at(origin), len(solved) == 1 and store is geometry.shared

    def constants_for(self, support: np.ndarray, sol: SupportSolution, velocities: np.ndarray) -> FrictionConstants:
        """The friction law's constants for the cells ``support`` solved as ``sol``, whose surfaces move at
        ``velocities`` ((len(support), 2), m/s)."""
        return self.law.constants(sol, velocities, self.cells.active_directions[support], self.spec.mu)

    def constants_and_row(self, support: np.ndarray, sol: SupportSolution,
                          velocities: np.ndarray) -> tuple[FrictionConstants, tuple[float, ...]]:
        """:meth:`constants_for` and the piece's constants row (:func:`constants_row`) in one compiled call."""
        spec = self.spec
        return self.law.constants_and_row(sol, velocities, self.cells.active_directions[support], spec.mu, spec.mass,
                                          spec.inertia)

    def _new_table(self, row_length: int) -> _PieceTable:
        """The compiled loop's table for this model, which has none: the one its copies made last, renewed for its
        wheels, or a new one."""
        table = self._table_home[0]
        if table is None or table.row_length != row_length:
            table = _PieceTable(self, row_length)
        table.renew(self)
        self._table = self._table_home[0] = table
        return table

    def drop_table(self) -> None:
        """Let go of the compiled loop's table and the pieces cached (the parcel is done with: it left the array). The
        table refers back to the model it serves, and so does every copy of the model to the table, so a released
        model and its copies were freed only at the next full garbage collection, which a long run holding its
        results makes rarer as it goes: on the junction's hour ~40 such tables of ~0.8 MB were waiting at a time, and
        the heap grew to hold them (most of the resident set's growth over the hour)."""
        table = self._table_home[0]
        if table is not None:
            table.owner = None
        self._table_home[0] = self._table = None
        self._pieces, self._by_support, self._unmade = {}, {}, {}

    @property
    def pieces_cached(self) -> int:
        """Number of distinct (support set, contact set) pieces solved so far."""
        return len(self._pieces) + sum(map(len, self._unmade.values()))

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """State derivative at ``y`` (looks the piece up; raises TippingError)."""
        return self.piece_at(y).rhs(t, y)


class _Segment:
    """Event functions of one piece started at state y0: an event is a sign change of any of them.

    The values are, in order: the footprint margin of every candidate cell near the parcel (m), the spring force
    of every supporting cell (N; its sign is contact), the slack of the centre of mass in the supports' hull (m),
    and the distance left before the candidate list must be refreshed (m). The compiled engine
    (:mod:`virtual_vehicle.engine._kernel`) evaluates them from :attr:`fields`.

    The candidates are the cells within the parcel's radius plus ``buffer`` of ``center``, where they were gathered:
    they cover the footprint while its centre stays within ``buffer`` of there. A segment that starts within half
    that of its predecessor's centre keeps its candidates (a KD-tree query a support change saved; at 0.2 m/s and
    100 changes a second a list lasts some 25 segments, and its refresh event costs one more).
    """

    def __init__(self, model: ParcelModel, piece: Piece, y0: np.ndarray, previous: "_Segment | None" = None):
        radius, buffer, noise_length, noise_force = model.segment_scales
        self.buffer = buffer
        x, y = y0[:2].tolist()
        if previous is not None and math.hypot(x - previous.xy[0], y - previous.xy[1]) <= buffer / 2:
            # still cover the footprint for buffer / 2 more
            self.ids, self.center, self.xy = previous.ids, previous.center, previous.xy
            self.candidates = previous.candidates
        else:
            self.center = np.array(y0[:2], dtype=float)
            self.xy = (x, y)
            self.ids = model.cells.grid.within(x, y, radius + buffer, model.present)
            self.candidates = model.cells.positions[self.ids]
        self._finish(model, piece)

    @classmethod
    def gathered(cls, model: ParcelModel, piece: Piece, ids: np.ndarray, candidates: np.ndarray,
                 center: np.ndarray) -> "_Segment":
        """The segment of ``piece`` whose candidates (cell ids and positions, m) a compiled event loop gathered
        about ``center`` (m), as :meth:`__init__` would have gathered them there."""
        seg = cls.__new__(cls)
        seg.buffer = model.segment_scales[1]
        seg.ids, seg.candidates, seg.center, seg.xy = ids, candidates, center, tuple(center.tolist())
        seg._finish(model, piece)
        return seg

    def _finish(self, model: ParcelModel, piece: Piece) -> None:
        radius, buffer, noise_length, noise_force = model.segment_scales
        sol = piece.solution
        nc, m, q = len(self.ids), len(sol.points), len(sol.hull_offsets)
        self.bounds = (0, nc, nc + m, nc + m + q, nc + m + q + 1)
        self.fields = _kernel.make_segment(model.outline, radius, self.candidates, sol, self.center, buffer,
                                           noise_length, noise_force, self.ids)

    @cached_property
    def arrays(self) -> _kernel.Segment:
        """:attr:`fields` named (what the compiled functions other than ``run_piece`` take)."""
        return _kernel.Segment(*self.fields)

    def support(self, g: np.ndarray | None) -> np.ndarray | None:
        """The cells under the footprint (as :meth:`ParcelModel.support_at` finds them) from event values ``g`` at
        one state, or None when they cannot tell: no values, or the parcel has gone beyond the candidates' reach."""
        if g is None or not g[-1] > 0:
            return None
        return self.ids[g[:self.bounds[1]] > 0]

    def values(self, y) -> np.ndarray:
        """Event values at state ``y`` ((6,) -> (n,)), or at many states ((k, 6) -> (k, n))."""
        Y = np.atleast_2d(np.asarray(y, dtype=float))
        out = np.empty((len(Y), self.bounds[-1]))
        for state, row in zip(Y, out):
            _kernel.values(self.arrays, np.ascontiguousarray(state), row)
        return out if np.ndim(y) == 2 else out[0]


ROUNDING_NOISE = 1e-11
"""Relative size below which an event value is treated as zero (rounding noise)."""

_CHATTER_EVENTS = 50
_CHATTER_SPAN = 1e-9
"""A run of ``_CHATTER_EVENTS`` support changes within ``_CHATTER_SPAN`` s (times max(1, |t|)) that goes back and
forth between at most ``_CHATTER_PIECES`` pieces is chattering: the parcel sits on a boundary between support sets
whose pieces each drive it back into the other (a sliding mode, as a parcel at rest with an edge exactly on a row
of cell centres under a field pushing both ways). Events there come one rounding step apart and would never reach
the end of the interval. (An edge sweeping a long row of cells at a grazing angle also makes many changes in a
short time, but each to a new piece.)"""
_CHATTER_PIECES = 4
_CHATTER_STEPS = 20
"""Fixed steps of ``dt`` taken across a chattering boundary before events are located again."""
_EVENT_COLUMNS = 256
"""Support changes the compiled event loop writes before it hands them to Python (which makes them events)."""
_PAUSE_STEPS = 64
"""With a progress callback, the compiled engine hands control back after this many steps within one piece, and the
event loop of a law without modes (``_kernel.run_events``) also after beginning this many pieces in one call (a
piece is often one step, and the loop hands back for little else: progress would be heard of a few times a run)."""
_NO_PAUSE = int(np.iinfo(np.int64).max)
"""Steps within one piece without a progress callback: no limit (worked out once: np.iinfo took ~5 us a call)."""


def integrate(model: ParcelModel, y0, t0: float, t1: float, *, mode: Mode = "event", rtol: float = 1e-10,
              atol: float = 1e-12, max_step: float = np.inf, dt: float = 1e-3, sample_dt: float | None = None,
              sample_times: np.ndarray | None = None, progress: Callable[[float], None] | None = None,
              max_segments: int = 1_000_000) -> Trajectory:
    """Integrate one parcel from state ``y0`` at ``t0`` to ``t1`` (s).

    Args:
        mode: ``"event"`` (piecewise, events located) or ``"fixed"`` (RK4 with step ``dt``, s). A law with modes
            (its ``modes``, e.g. stick-slip) runs exactly in event mode, mode by mode (each wheel sticking or
            slipping; mode events located as support events are), and in fixed mode with its time stepper (its
            ``time_stepper``: a complementarity problem per step at ``dt``). A law without modes but with a time
            stepper is always stepped at ``dt``.
        rtol, atol: tolerances of the adaptive integrator (event mode); atol in state units (m, rad, m/s, rad/s).
        max_step: largest step of the adaptive integrator, s.
        dt: fixed step (s) of fixed mode and of stick-slip. Event mode uses it only where support changes chatter
            (``_CHATTER_EVENTS`` of them within ``_CHATTER_SPAN`` s among a few pieces: a sliding mode on a boundary
            between support sets). It crosses ``_CHATTER_STEPS`` such steps as fixed mode would (RK4, the support
            read at every stage; first order across the boundary), counts them in ``stats["chatter_steps"]``, and
            then locates events again.
        sample_dt: spacing of the output samples, s (default: 100 samples over the run). Event mode samples the
            integrator's dense output; fixed mode interpolates linearly between its steps.
        sample_times: explicit increasing output times (s) within [t0, t1] instead of ``sample_dt``.
        progress: called with the simulated time now and then: where the compiled engine hands control back to
            Python, and at least every ``_PAUSE_STEPS`` steps or pieces (which makes it hand back that often).

    Returns:
        The :class:`Trajectory`. A parcel that tips ends with status ``"tipped"`` and a ``"tip"`` event.
    """
    y0 = np.asarray(y0, dtype=float)
    if y0.shape != (6,) or not np.all(np.isfinite(y0)):
        raise ValueError("y0 must be six finite numbers [x, y, theta, vx, vy, omega]")
    if not t1 > t0:
        raise ValueError(f"t1 must be after t0, got t0={t0}, t1={t1}")
    if sample_times is not None:
        sample_times = np.asarray(sample_times, dtype=float)
        if np.any(np.diff(sample_times) <= 0) or sample_times[0] < t0 or sample_times[-1] > t1:
            raise ValueError("sample_times must increase within [t0, t1]")
    else:
        if sample_dt is None:
            sample_dt = (t1 - t0) / 100
        if not sample_dt > 0:
            raise ValueError("sample_dt must be positive")
        sample_times = sample_grid(t0, t1, sample_dt)
    if mode not in MODES:
        raise ValueError(f"mode must be 'event' or 'fixed', got {mode!r}")
    return integrate_prechecked(model, y0, t0, t1, sample_times, mode=mode, rtol=rtol, atol=atol, max_step=max_step,
                                dt=dt, progress=progress, max_segments=max_segments)


def integrate_prechecked(model: ParcelModel, y0: np.ndarray, t0: float, t1: float, sample_times: np.ndarray, *,
                         mode: Mode, rtol: float, atol: float, max_step: float, dt: float,
                         progress: Callable[[float], None] | None = None, max_segments: int = 1_000_000,
                         support: np.ndarray | None = None) -> Trajectory:
    """:func:`integrate` for arguments known to be valid (``y0`` a finite (6,) float array, ``t1 > t0``,
    ``sample_times`` a float array increasing within [t0, t1], ``mode`` known): a plant's calls, whose checks took
    ~30 us of a ~250 us control tick with an event. ``support``: the cells under the parcel at ``y0`` when the caller
    has found them as :meth:`ParcelModel.support_at` does (event mode starts from them)."""
    # Flush values below 1e-100 (a velocity decaying for minutes under viscous damping reaches subnormal floats,
    # where the adaptive integrator's error norm underflows to 0/0).
    y0 = np.where(np.abs(y0) < 1e-100, 0.0, y0)
    law = model.law
    if mode == "event" and law.modes:
        return _run_modes(model, y0, t0, t1, sample_times, progress, max_segments, rtol=rtol, atol=atol,
                          max_step=max_step, dt=dt, support=support)
    if law.time_stepper is not None:
        return TIME_STEPPERS[law.time_stepper](model, y0, t0, t1, sample_times, progress, dt=dt)
    if mode == "event":
        return _run_event(model, y0, t0, t1, sample_times, progress, max_segments, rtol=rtol, atol=atol,
                          max_step=max_step, dt=dt, support=support)
    return _run_fixed(model, y0, t0, t1, sample_times, progress, max_segments, dt=dt)


class _Recorder:
    """Output samples at ``sample_times`` (filled in order, also by the compiled engine), then the last state."""

    def __init__(self, sample_times):
        self.sample_times = np.ascontiguousarray(sample_times, dtype=float)
        self.samples = np.empty((len(self.sample_times), 6))
        self.next = 0
        self.last: tuple[float, np.ndarray] | None = None

    def pending_until(self, t) -> np.ndarray:
        """Sample times not yet recorded that are <= t."""
        j = int(np.searchsorted(self.sample_times, t, side="right"))
        return self.sample_times[self.next:j]

    def add(self, ts, ys) -> None:
        self.samples[self.next:self.next + len(ts)] = np.reshape(ys, (-1, 6))
        self.next += len(ts)

    def final(self, t, y) -> None:
        if self.next == 0 or t > self.sample_times[self.next - 1]:
            self.last = float(t), np.array(y, dtype=float)

    def arrays(self):
        times, states = self.sample_times[:self.next], self.samples[:self.next]
        if self.last is None:
            return times.copy(), states.copy()
        return np.append(times, self.last[0]), np.vstack([states, self.last[1]])


def _check_outcome(outcome: int, t: float) -> None:
    """Raise IntegrationError for a compiled piece's or mode's failed outcome at time ``t`` (s)."""
    if outcome == _kernel.FAILED:
        raise IntegrationError(f"integrator failed at t={t:.9g} s")
    if outcome == _kernel.NOT_FINITE:
        raise IntegrationError(f"an event function is not finite at t={t:.9g} s")
    if outcome == _kernel.NO_CONVERGENCE:
        raise IntegrationError(f"locating an event near t={t:.9g} s did not converge")


def _grid_args(model: ParcelModel) -> tuple:
    """What the compiled event loop gathers candidates and finds the cells under the parcel with: the cells'
    ``PointGrid.within`` arguments, the ``present`` mask (empty: all) and the parcel's radius (m)."""
    cells_grid = model.cells.grid
    return (cells_grid.points, cells_grid.order, cells_grid.start, float(cells_grid.lo[0]), float(cells_grid.lo[1]),
            float(cells_grid.size), int(cells_grid.shape[0]), int(cells_grid.shape[1]),
            ALL_PRESENT if model.present is None else model.present, float(model.segment_scales[0]))


def _run_event(model, y0, t0, t1, sample_times, progress, max_segments, *, rtol, atol, max_step,
               dt, support=None) -> Trajectory:
    rec = _Recorder(sample_times)
    events: list[Event] = []
    t, y = float(t0), y0.copy()
    segments = nfev = chatter_steps = 0
    # First step: the whole interval, which the error control shrinks if it must (a few rejected trials for a long
    # run). Within a piece the motion is smooth, so a short interval, as a control tick, is often one step, where
    # the solver's own first-step guess took five.
    h = t1 - t0
    try:
        piece = model.piece_at(y) if support is None else model.piece_for(support, y)
    except TippingError as exc:
        rec.final(t, y)
        events.append(Event(t, "tip", tuple(map(float, y)), message=str(exc)))
        return Trajectory(*rec.arrays(), events, "tipped", t)
    status = "completed"
    y_probe = y
    seg = None
    max_steps = _PAUSE_STEPS if progress is not None else _NO_PAUSE
    ring_t, ring_p, ring = np.zeros(_CHATTER_EVENTS), np.zeros(_CHATTER_EVENTS, np.int64), np.zeros(2, np.int64)
    ev_t, ev_y, ev_p = np.empty(_EVENT_COLUMNS), np.empty((_EVENT_COLUMNS, 6)), np.empty((_EVENT_COLUMNS, 2), np.int64)
    begin = True  # a new piece whose candidates Python gathers (or keeps, as _Segment decides)
    begun = False  # a new piece the compiled loop begins (keeping the candidates) or hands back to begin here
    table, outcome = model._table, None
    grid = _grid_args(model)
    pending = table is None  # the first piece alone (kernel.run_piece), the table made only if an event ends it
    if pending:  # (most of a plant's control ticks have none: making the table took as long as the tick)
        segments += 1
        seg = _Segment(model, piece, y_probe, seg)
        base = y_probe
        first, h_abs = min(h, t1 - t), 0.0
        scratch = _kernel.search_scratch(0)  # (made to the piece's size in the call)
        while True:
            (outcome, t, y, h_abs, last, evals, rec.next, t_probe, y_probe, under,
             told) = _kernel.run_piece(piece.row, seg.fields, base, t, y, t1, h_abs, first, rtol, atol, max_step,
                                        max_steps, rec.sample_times, rec.next, rec.samples, scratch)
            nfev += evals
            first = 0.0
            if last:
                h = last
            _check_outcome(outcome, t)
            if progress is not None:
                progress(t)
            if outcome != _kernel.PAUSED:
                break
        if outcome == _kernel.EVENT:  # as the loop would have met it: the chatter test's first event, then a miss
            table = model._new_table(len(piece.row))
            table.sync(model, piece)
            ring_t[0], ring_p[0], ring[:] = t, table.index_of(model, piece), 1
            outcome = _kernel.LOOP_MISS
    while outcome != _kernel.REACHED:
        if pending:
            pending = False
        else:
            if begin:
                segments += 1
                if segments > max_segments:
                    raise IntegrationError(f"more than {max_segments} support changes: events accumulate near "
                                           f"t={t:.9g} s")
                seg = _Segment(model, piece, y_probe, seg)
                base = y_probe  # the event values' signs here are the piece's baseline
                first, h_abs = min(h, t1 - t), 0.0
            elif begun:
                base = y_probe
            begin = True
            if table.sync(model, piece):  # emptied (bounded memory): the chatter test starts again
                ring[:] = 0
            p = table.index_of(model, piece)  # after the sync: both may grow the table's arrays
            start = int(table.used[_kernel.U_PIECES])
            # DOP853 piece by piece (kernel.run_events) until a support set it cannot make or solve, a pause, ...
            (outcome, t, y, p, h, h_abs, evals, rec.next, segments, n_ev, born, y_probe, under, told, ids,
             candidates, center) = _kernel.run_events(
                table.arrays, seg.fields, p, begun, base, t, y, t1, h, h_abs, first, rtol, atol, max_step, max_steps,
                rec.sample_times, rec.next, rec.samples, segments, max_segments, ring_t, ring_p, ring, _CHATTER_SPAN,
                _CHATTER_PIECES, ev_t, ev_y, ev_p, table.law_args, grid)
            table.adopt_solved(model)  # before the pieces made from them
            if born:
                table.adopt_born(model, start, born)
            begun = False
            nfev += evals
            key = table.key
            for tj, yj, (a, b) in zip(ev_t[:n_ev].tolist(), ev_y[:n_ev].tolist(), ev_p[:n_ev].tolist()):
                events.append(Event.support_between(tj, tuple(yj), key(a), key(b)))
            piece = table.piece(model, p)
            if (center[0], center[1]) != seg.xy:  # gathered again in the loop (never where they were)
                seg = _Segment.gathered(model, piece, ids, candidates, center)
            _check_outcome(outcome, t)
            if progress is not None:
                progress(t)
            if outcome == _kernel.PAUSED:  # the same piece goes on
                base, first, begin = y_probe, 0.0, False
                continue
            if outcome in (_kernel.REACHED, _kernel.LOOP_DONE):
                break
            if outcome == _kernel.LOOP_TOO_MANY:
                raise IntegrationError(f"more than {max_segments} support changes: events accumulate near "
                                       f"t={t:.9g} s")
            if outcome == _kernel.LOOP_SEGMENT:
                continue
            if outcome == _kernel.LOOP_CHATTER:
                ring[:] = 0  # chattering: cross the boundary in fixed steps, then locate events again
                t_end = min(t1, t + _CHATTER_STEPS * dt)
                due = rec.pending_until(t_end)
                times, states, evs, status, t, n = fixed_steps(model, y, t, t_end, dt, due, progress,
                                                               _rk4(model))
                kept = int(np.count_nonzero(due <= t))  # all of them unless it tipped
                rec.add(times[:kept], states[:kept])
                events.extend(evs)
                chatter_steps += n
                y = y_probe = states[-1]
                if status == "tipped" or t >= t1:
                    break
                piece = model.piece_at(y)  # tipping would have ended the fixed steps
                continue
        try:  # LOOP_MISS: the cells under it are known from the probe's event values, when those tell
            new = model.piece_for(under, y_probe) if told else model.piece_at(y_probe)
        except TippingError as exc:
            events.append(Event(t, "tip", tuple(map(float, y)), message=str(exc)))
            status = "tipped"
            break
        table.learn(model, new)
        ev = diff_event(t, y, piece, new)
        if ev is not None:
            events.append(ev)
        piece = new
        if t >= t1:  # the event's restart point is the end of the interval
            break
        begin, begun = False, True
    rec.final(t, y)
    stats = {"pieces_cached": model.pieces_cached, "solves": model.solves}
    if chatter_steps:
        stats["chatter_steps"] = chatter_steps
    return Trajectory(*rec.arrays(), events, status, t, segments, nfev + 4 * chatter_steps, stats)


_MODE_CHATTER = 1000
"""Mode events in a row at one time (within 1e-12 s) after which a law with modes is said to chatter (a mode
decided that its own events end at once): the run stops with an IntegrationError instead of looping."""

_MODE_LOOP = True
"""Whether :func:`_run_modes` takes its events in one compiled call (:func:`~virtual_vehicle.engine._modeloop.
run_modes`) until it meets what only Python can do; False: every event in Python. The two runs are the same bit for
bit (the compiled loop calls the same compiled functions with the same arrays); the tests compare them."""

_LOG_ROWS = 256
"""Events the compiled mode loop logs in one call before it hands back to Python to read them."""


def _mode_tuple(wheels, mode, minv):
    """What the compiled engine takes for ``mode`` (as :func:`~virtual_vehicle.physics.stick_modes.decide_kernel`
    returns it) of the wheel arrays ``wheels``: the fields (:func:`~virtual_vehicle.engine._kernel.mode_fields`'
    order) and the number of mode event values. The sticking rows kept are a maximal independent subset (at most
    three), chosen in order; the others follow from them for the whole mode (their dependence does not change as
    the centre moves)."""
    state, rows, stick, rank, anchor, index = mode
    md = (*wheels, state, stick[rows], stick, rank, anchor, index, minv)
    return md, int(np.count_nonzero(np.abs(state) == 1)) + (len(index) if len(stick) else 0)


def _wheel_keys(model, piece) -> list:
    """(entry, wheel index) of each wheel of ``piece`` in the order of the law's wheel arrays."""
    return _support_wheel_keys(model, piece.key[0])


def _support_wheel_keys(model, support: tuple[int, ...]) -> list:
    """(entry, wheel index) of each wheel of the cells ``support`` (a piece's support key) in the order of the law's
    wheel arrays."""
    row, k = np.nonzero(model.cells.wheel_active[list(support)])
    return [(support[r], w) for r, w in zip(row.tolist(), k.tolist())]


def _mode_change_events(t, y, before, after, keys) -> list:
    """The run's events of one mode change at time ``t`` (s), state ``y``: a ``"stick"`` event naming the wheels that
    caught up with the parcel (slipping before, sticking after), a ``"slip"`` one those that broke away (sticking
    before, or slipping the other way), each as "entry:wheel" pairs in its message (``entered`` stays empty: it means
    cells entering the footprint); none for a side without wheels."""
    out = []
    for kind, moved in (("stick", [j for j, (a, b) in enumerate(zip(before, after)) if b == 0 and a in (1, -1)]),
                        ("slip", [j for j, (a, b) in enumerate(zip(before, after)) if b in (1, -1) and a != b
                                  and a != 2])):
        if moved:
            out.append(Event(t, kind, tuple(map(float, y)),
                             message=" ".join(f"{keys[j][0]}:{keys[j][1]}" for j in moved)))
    return out


def _replay(model, key, log_f, log_i, log_s, n_log, events, mode_events) -> None:
    """Add the run's events and mode records of the compiled mode loop's log (:mod:`~virtual_vehicle.engine.
    _modeloop`: ``n_log`` entries over the table's pieces, ``key(p)`` the p-th piece's :attr:`Piece.key`) as
    :func:`_run_modes`' Python makes them, from the pieces' keys alone: no :class:`Piece` is made for them."""
    for (t, *y), (kind, a, b, ob, oa, n, flag) in zip(log_f[:n_log].tolist(), log_i[:n_log].tolist()):
        before = tuple(log_s[ob:ob + n].tolist())
        after = None if oa < 0 else tuple(log_s[oa:oa + n].tolist())
        if kind == _modeloop.LOG_SUPPORT:
            old, new = key(a), key(b)
            if old != new and (frozenset(old[0]), frozenset(old[1])) != (frozenset(new[0]), frozenset(new[1])):
                events.append(Event.support_between(t, tuple(y[:6]), old, new))  # (as diff_event)
            if flag:  # a wheel staying under the parcel changed its mode here
                mode_events.append((t, "support", before, after))
                events.extend(_mode_change_events(t, y[6:], before, after, _support_wheel_keys(model, new[0])))
        else:
            mode_events.append((t, "stick" if kind == _modeloop.LOG_STICK else "slip", before, after))
            if after is not None:
                events.extend(_mode_change_events(t, y[6:], before, after, _support_wheel_keys(model, key(a)[0])))


_NO_CANDIDATES, _NO_CENTER = np.zeros((0, 2)), np.zeros(2)
"""What the compiled mode loop is passed for a segment it gathers itself (as it does where it finds its first
piece)."""


def _run_modes(model, y0, t0, t1, sample_times, progress, max_segments, *, rtol, atol, max_step, dt,
               support=None) -> Trajectory:
    """Event mode for a law with modes (stick-slip): on each piece (support set) the law's wheels
    (:meth:`~virtual_vehicle.physics.laws.base.FrictionLaw.wheel_contacts`) are in a mode (each sticks or slips with
    a known sign, :mod:`~virtual_vehicle.physics.stick_modes`); each mode is integrated by the compiled DOP853
    (:func:`~virtual_vehicle.engine._kernel.run_mode`) with its mode events and the piece's support events. At a
    mode event, and at a support event with the new piece's wheels, the next mode is decided by the complementarity
    rule (:func:`~virtual_vehicle.physics.stick_modes.decide_kernel`, the compiled form of
    :func:`~virtual_vehicle.physics.stick_modes.decide_mode`) and the twist projected onto its sticking wheels. Each
    mode change is also one or two of the run's events (:func:`_mode_change_events`: ``"stick"`` where wheels catch
    up with the parcel, ``"slip"`` where they break away). The stats hold the energy account (J) as the time stepper's do (its step dissipation 0: there is no
    step), ``mode_changes`` (how many events changed the mode) and ``mode_events`` (this call's): (time, kind, mode
    before, mode after) each, the kind naming what ended the mode: "slip" (a slipping wheel's slip reached zero),
    "stick" (a sticking wheel's force reached its bound) or "support" (a support change changed the mode of a wheel
    that stays in contact). The run's events are named by the outcome instead: "stick" where wheels caught up,
    "slip" where they broke away (:func:`_mode_change_events`). Where the rule cannot decide a mode, the run crosses a few fixed steps (:func:`_undecided_steps`),
    counted in ``stats["undecided_steps"]``."""
    law, spec = model.law, model.spec
    mass, inertia = spec.mass, spec.inertia
    minv = np.array([1.0 / mass, 1.0 / mass, 1.0 / inertia])
    rec = _Recorder(sample_times)
    events: list[Event] = []
    mode_events: list[tuple] = []
    t = float(t0)
    z = np.concatenate([y0, [0.0, 0.0, 0.0]])  # and the energy account: wheel work, friction, fixed steps' loss (J)
    kinetic_start = 0.5 * (mass * (y0[3] ** 2 + y0[4] ** 2) + inertia * y0[5] ** 2)
    segments = nfev = same_time = fallback_steps = chatter_steps = 0
    table = model._table if _MODE_LOOP else None
    if _MODE_LOOP and table is None and model._table_home[0] is not None:
        table = model._new_table(model._table_home[0].row_length)
    kept = None if table is None else table.loop_args
    if kept is not None and kept[0] is not model.present:  # (cells taken out since: gathered again)
        kept = None
    if kept is not None:  # the parcel's loop arguments, kept with its table
        _, grid, scales, wheel_cells, clock, same, log_f, log_i, log_s, ring_t, ring_h, ring = kept
        ring_t[:], ring_h[:], ring[:] = 0.0, 0, 0
    else:
        # the last support changes (time, the hash of the cells under the parcel), shared by the compiled loop
        ring_t, ring_h, ring = np.zeros(_CHATTER_EVENTS), np.zeros(_CHATTER_EVENTS, np.int64), np.zeros(2, np.int64)
    if _MODE_LOOP and kept is None:
        cells_grid, mu_static = model.cells.grid, spec.mu if spec.mu_static is None else spec.mu_static
        grid = (cells_grid.points, cells_grid.order, cells_grid.start, float(cells_grid.lo[0]),
                float(cells_grid.lo[1]), float(cells_grid.size), int(cells_grid.shape[0]), int(cells_grid.shape[1]),
                ALL_PRESENT if model.present is None else model.present, float(model.segment_scales[0]))
        radius, buffer, noise_length, noise_force = model.segment_scales
        scales = (float(buffer), float(radius + 2 * buffer), float(noise_length), float(noise_force))
        wheel_cells = (model.cells.wheel_active, model.cells.drive_directions, float(spec.mu), float(mu_static))
        clock, same = np.zeros(1), np.zeros(1, np.int64)
        log_f, log_i = np.empty((_LOG_ROWS, _modeloop.LOG_FLOATS)), np.empty((_LOG_ROWS, _modeloop.LOG_INTS), np.int64)
        log_s = np.empty(4096, np.int64)
    h = t1 - t0
    status = "completed"

    nobody = np.zeros(0, np.int64)

    def decide(wheels, t, z, breaking=nobody, signs=nobody):
        """The mode at (t, z) as :func:`decide_kernel` gives it (state, independent sticking rows, sticking wheels,
        facet choice), z's twist projected onto it; None where the rule cannot decide one."""
        ok, state, y, *mode = decide_kernel(*wheels, minv, t, z[:6], breaking, signs)
        if not ok:
            return None
        z[:6] = y
        return (state, *mode)

    def wheels_of(piece):
        return law.wheel_arrays(model.cells, piece.support, piece.solution, model.velocities, spec.mu,
                                spec.mu_static)

    def begin():
        """The first piece, its wheels and their mode (three None where the parcel tips)."""
        nonlocal status
        try:
            piece = model.piece_at(z[:6]) if support is None else model.piece_for(support, z[:6])
        except TippingError as exc:
            events.append(Event(t, "tip", tuple(map(float, y0)), message=str(exc)))
            status = "tipped"
            return None, None, None
        wheels = wheels_of(piece)
        return piece, wheels, decide(wheels, t, z)

    max_steps = _PAUSE_STEPS if progress is not None else _NO_PAUSE
    seg = None
    y_probe = z[:6].copy()
    base = y_probe
    # the compiled loop finds the first piece itself (from the support set, or the cells under the footprint), makes
    # its wheels and decides their mode, where its table can: no Piece, wheel arrays or decision made here for it
    starting = (_MODE_LOOP and table is not None and table.blank is not None
                and len(table.pieces) <= table.max_pieces)
    piece = wheels = mode = ended = None  # ended: the last piece's support key where the compiled loop ends the run
    if not starting:
        piece, wheels, mode = begin()
    new_piece = True
    while piece is not None or starting:
        segments += 1
        if segments > max_segments:
            raise IntegrationError(f"more than {max_segments} support and mode changes: events accumulate near "
                                   f"t={t:.9g} s")
        if mode is None and not starting:  # undecided: cross a few fixed steps of the law's stepper, then decide
            contacts = law.wheel_contacts(model.cells, piece.support, piece.solution, model.velocities, spec.mu,
                                          spec.mu_static)
            t, status, steps = _undecided_steps(model, contacts, z, t, t1, dt, rec, events, progress)
            fallback_steps += steps
            if status == "tipped" or t >= t1:
                break
            y_probe = z[:6].copy()
            piece = model.piece_at(y_probe)  # tipping would have ended the steps
            wheels = wheels_of(piece)
            mode = decide(wheels, t, z)
            new_piece = True
            continue
        if new_piece and not starting:
            seg = _Segment(model, piece, y_probe, seg)
            base = np.ascontiguousarray(y_probe, dtype=float)
        if _MODE_LOOP:  # events in one compiled call until Python must act
            if table is None or (not starting and table.row_length != len(piece.row)):
                table = model._new_table(len(piece.row))
            first, h_abs = min(h, t1 - t), 0.0
            while True:
                if starting:  # the loop's first piece, from the cells told or under the footprint
                    table.sync(model, None)
                    p = _modeloop.START_PROBE if support is None else _modeloop.START_TOLD
                    cells = nobody if support is None else np.ascontiguousarray(support, dtype=np.int64)
                    wheels, mode = table.blank
                    candidates, center, ids = _NO_CANDIDATES, _NO_CENTER, nobody
                else:
                    table.sync(model, piece)
                    p = table.index_of(model, piece)  # after the sync: both may grow the table's arrays
                    cells, candidates, center, ids = nobody, seg.candidates, seg.center, seg.ids
                start = int(table.used[_kernel.U_PIECES])
                if len(log_s) < 8 * len(mode[0]) + 256:
                    log_s = np.empty(2 * (8 * len(mode[0]) + 256), np.int64)
                clock[0], same[0] = (mode_events[-1][0] if mode_events else np.nan), same_time
                (outcome, t, z8, p, h, h_abs, evals, rec.next, segments, n_log, _, born, y_probe, under, told, ids,
                 candidates, center, base, mode, wheels, new_piece) = _modeloop.run_modes(
                    table.arrays, table.law_args, wheel_cells, model.outline, scales, grid, p, cells, wheels, mode,
                    minv, candidates, center, ids, base, t, z[:8].copy(), t1, h, h_abs, first, rtol, atol,
                    max_step, max_steps, rec.sample_times, rec.next, rec.samples, segments, max_segments, ring_t,
                    ring_h, ring, _CHATTER_SPAN, _CHATTER_PIECES, clock, same, _MODE_CHATTER, log_f, log_i, log_s)
                z[:8] = z8
                nfev += evals
                same_time = int(same[0])
                table.adopt_solved(model)  # before the pieces made from them
                if born:
                    table.adopt_born(model, start, born)
                if starting:
                    starting = False
                    if outcome == _modeloop.LOOP_START:  # the table cannot give it: found here, as before
                        break
                elif table.blank is None:
                    table.blank = wheels, mode
                _replay(model, table.key, log_f, log_i, log_s, n_log, events, mode_events)
                if outcome in (_kernel.REACHED, _kernel.LOOP_DONE):  # the window is done: its last piece is not
                    ended = table.key(p)[0]  # made a Piece (most windows of a plant's tick end on their first)
                else:
                    new = table.piece(model, p)  # (pieces the loop made are made when Python needs them)
                    if new is not piece or (center[0], center[1]) != seg.xy:  # (the loop's segment, as Python's)
                        seg = _Segment.gathered(model, new, ids, candidates, center)
                    piece = new
                _check_outcome(outcome, t)
                if progress is not None:
                    progress(t)
                if outcome != _kernel.PAUSED:
                    break
                first = 0.0
            if outcome == _modeloop.LOOP_START:
                piece, wheels, mode = begin()
                new_piece, segments = True, segments - 1  # (the loop's first iteration begins again)
                if piece is not None:  # its pattern's solutions, so that the next copy's loop finds it from them
                    table.learn_pattern(model, piece.support)
                continue
            if outcome in (_kernel.REACHED, _kernel.LOOP_DONE):
                break
            if outcome == _kernel.LOOP_TOO_MANY:
                raise IntegrationError(f"more than {max_segments} support and mode changes: events accumulate near "
                                       f"t={t:.9g} s")
            if outcome == _modeloop.LOOP_MODE_CHATTER:
                raise IntegrationError(f"stick-slip modes chatter at t={t:.9g} s")
            if outcome == _modeloop.LOOP_UNDECIDED:
                mode = None
                if t >= t1:
                    break
                continue
            if outcome == _kernel.LOOP_SEGMENT:
                continue
            # LOOP_MISS: a support event Python takes from the probe on
        else:
            md, n_ev = _mode_tuple(wheels, mode, minv)
            first, h_abs = min(h, t1 - t), 0.0
            while True:
                (outcome, t, z8, h_abs, last, evals, rec.next, t_probe, y_probe, under, told,
                 which) = _kernel.run_mode(md, n_ev, seg.fields, base, t, z[:8], t1, h_abs, first, rtol, atol,
                                           max_step, max_steps, rec.sample_times, rec.next, rec.samples)
                z[:8] = z8
                nfev += evals
                first = 0.0
                if last:
                    h = last
                _check_outcome(outcome, t)
                if progress is not None:
                    progress(t)
                if outcome != _kernel.PAUSED:
                    break
            if outcome == _kernel.REACHED:
                break
            if outcome == _kernel.MODE_EVENT:
                state, _, stick, rank, anchor, index = mode
                slipping = int(np.count_nonzero(np.abs(state) == 1))
                kind = "slip"
                if which >= slipping:
                    kind = "stick"
                    new_mode = decide(wheels, t, z, *breaking_kernel(*wheels, minv, t, z[:6], state, stick, rank,
                                                                     anchor, index, which - slipping))
                else:
                    new_mode = decide(wheels, t, z)
                same_time = same_time + 1 if mode_events and t - mode_events[-1][0] <= 1e-12 * max(1.0, t) else 0
                if same_time > _MODE_CHATTER:
                    raise IntegrationError(f"stick-slip modes chatter at t={t:.9g} s")
                before = tuple(state.tolist())
                after = None if new_mode is None else tuple(new_mode[0].tolist())
                mode_events.append((t, kind, before, after))
                if after is not None:
                    events.extend(_mode_change_events(t, z[:6], before, after, _wheel_keys(model, piece)))
                mode, new_piece = new_mode, False
                if t >= t1:
                    break
                continue
        try:
            new = model.piece_for(under, y_probe) if told else model.piece_at(y_probe)
        except TippingError as exc:
            events.append(Event(t, "tip", tuple(map(float, z[:6])), message=str(exc)))
            status = "tipped"
            break
        if table is not None:
            table.learn(model, new)  # so that the compiled loop finds it next time
        ev = diff_event(t, z[:6], piece, new)
        if ev is not None:
            events.append(ev)
        key = _modeloop.support_hash(np.ascontiguousarray(new.support, dtype=np.int64))
        if _modeloop.ring_event(ring_t, ring_h, ring, t, key, _CHATTER_SPAN, _CHATTER_PIECES, True):
            # support changes chatter (as in :func:`_run_event`: a parcel all but at rest with a footprint edge on a
            # cell's boundary, each piece's mode driving it back into the other, events a rounding step apart): cross
            # the boundary in fixed steps of the law's stepper, then locate events again
            ring[:] = 0
            contacts = law.wheel_contacts(model.cells, new.support, new.solution, model.velocities, spec.mu,
                                          spec.mu_static)
            t, status, steps = _undecided_steps(model, contacts, z, t, t1, dt, rec, events, progress)
            chatter_steps += steps
            if status == "tipped" or t >= t1:
                mode = None  # (the stepper keeps the wheels' grip itself)
                break
            y_probe = z[:6].copy()
            piece = model.piece_at(y_probe)
            wheels = wheels_of(piece)
            mode = decide(wheels, t, z)
            new_piece = True
            continue
        if new is not piece:
            held = {} if mode is None else dict(zip(_wheel_keys(model, piece), mode[0].tolist()))
            piece, wheels = new, wheels_of(new)
            mode = decide(wheels, t, z)
            if mode is not None and held:  # a wheel that stays under the parcel and changes mode here is an event too
                keys = _wheel_keys(model, piece)
                after = tuple(mode[0].tolist())
                before = tuple(a if held.get(key, 2) == 2 or a == 2 else held[key] for key, a in zip(keys, after))
                # (2: a wheel out of contact; lifting off or touching down is the support event itself)
                if before != after:
                    mode_events.append((t, "support", before, after))
                    events.extend(_mode_change_events(t, z[:6], before, after, keys))
        new_piece = True
        if t >= t1:
            break
    if table is not None:
        table.loop_args = (model.present, grid, scales, wheel_cells, clock, same, log_f, log_i, log_s, ring_t, ring_h,
                           ring)
    if ended is None and piece is not None:
        ended = piece.key[0]
    if ended is not None and mode is not None:  # the wheels' grip, for the time stepper should one take over next
        # (parcels pushing each other are stepped): updated in place, so the model this one was copied from has it
        memory, keys = model.contact_memory, _support_wheel_keys(model, ended)
        memory["lam"] = dict.fromkeys(keys, 0.0)  # (no warm start: the stick forces are not the stepper's impulses)
        memory["stuck"] = dict(zip(keys, (mode[0] == 0).tolist()))
    rec.final(t, z[:6])
    y = z[:6]
    stats = {"wheel_work": float(z[6]), "friction_dissipation": float(z[7]), "step_dissipation": 0.0,
             "contact_work": 0.0, "sweeps_max": 0, "unconverged_steps": 0, "kinetic_start": float(kinetic_start),
             "kinetic_end": 0.5 * float(mass * (y[3] ** 2 + y[4] ** 2) + inertia * y[5] ** 2),
             "mode_changes": sum(after != before for _, _, before, after in mode_events), "mode_events": mode_events, "pieces_cached": model.pieces_cached,
             "solves": model.solves}
    if fallback_steps or chatter_steps:
        stats["step_dissipation"] = float(z[8])
    if fallback_steps:
        stats["undecided_steps"] = fallback_steps
    if chatter_steps:
        stats["chatter_steps"] = chatter_steps
    return Trajectory(*rec.arrays(), events, status, t, segments, nfev + 4 * (fallback_steps + chatter_steps), stats)


def _undecided_steps(model, wheels, z, t, t1, dt, rec, events, progress):
    """Where the complementarity rule cannot decide a mode (its exact check fails: a tie its identification could
    not split, as among the many redundant omni wheels of hexagonal cells), cross ``_CHATTER_STEPS`` steps of
    ``dt`` with the law's time stepper, each wheel starting stuck where its slip is zero; the state ``z`` (with the
    energy account, a ninth entry for the steps' own dissipation) moves on in place. Returns (t, status, steps)."""
    law = model.law
    slips = wheels.slips(t, z[:6])
    speed = max(float(np.abs(wheels.surface(t)).max(initial=0.0)), 1e-3)
    memory = model.contact_memory  # in place: shared with the model this one was copied from
    memory["lam"] = dict.fromkeys(wheels.keys, 0.0)
    memory["stuck"] = dict(zip(wheels.keys, (np.abs(slips) <= 1e-9 * speed).tolist()))
    t_end = min(t1, t + _CHATTER_STEPS * dt)
    due = rec.pending_until(t_end)
    tr = TIME_STEPPERS[law.time_stepper](model, z[:6].copy(), t, t_end, due, progress, dt=dt)
    kept = int(np.count_nonzero(due <= tr.t_end))
    rec.add(tr.times[:kept], tr.states[:kept])
    events.extend(tr.events)
    z[:6] = tr.states[-1]
    z[6] += tr.stats["wheel_work"]
    z[7] += tr.stats["friction_dissipation"]
    z[8] += tr.stats["step_dissipation"]
    return tr.t_end, tr.status, tr.segments


def _rk4(model):
    """Classical RK4 for :func:`fixed_steps`; every stage looks its piece up."""
    def rk4(piece, t, y, h):
        k1 = model.rhs(t, y)
        k2 = model.rhs(t + h / 2, y + h / 2 * k1)
        k3 = model.rhs(t + h / 2, y + h / 2 * k2)
        k4 = model.rhs(t + h, y + h * k3)
        return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return rk4


def _run_fixed(model, y0, t0, t1, sample_times, progress, max_segments, *, dt) -> Trajectory:
    times, states, events, status, t, steps = fixed_steps(model, y0, t0, t1, dt, sample_times, progress,
                                                           _rk4(model))
    return Trajectory(times, states, events, status, t, steps, 4 * steps,
                      {"pieces_cached": model.pieces_cached, "solves": model.solves})


