"""Compile (or load from numba's cache) every compiled kernel a run uses, at a time of the caller's choosing."""

from __future__ import annotations

import gc
import time

import numpy as np

from virtual_vehicle.cells.network.delivery import IdealRounds
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import CellInputs
from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.cells.sorting import Sorter
from virtual_vehicle.engine import _kernel
from virtual_vehicle.engine.batch import QuietStepper
from virtual_vehicle.engine.dynamics import ParcelModel, constants_row, integrate
from virtual_vehicle.engine.plant import Plant
from virtual_vehicle.model.fields import Uniform
from virtual_vehicle.model.layout import grid
from virtual_vehicle.model.parcel import covered_pairs, rectangle
from virtual_vehicle.physics.laws import LAWS


def warm_up(settle: bool = True) -> float:
    """Compile the event engine's inner loop (:mod:`virtual_vehicle.engine._kernel`), the support solve's compiled
    parts (:mod:`virtual_vehicle.physics.contact`, :mod:`virtual_vehicle.physics.laws`), the quiet step's checks and
    step (:mod:`virtual_vehicle.engine.batch`), the riding parcels' measure (:mod:`virtual_vehicle.engine.ride`) and
    the sorter's cell program (:mod:`virtual_vehicle.cells.sorting`; about a minute together, the first time on a
    machine) or load them from numba's cache (a fraction of a second), by integrating one parcel on a 4 x 4 array
    for 10 ms, looking its last piece up again, making its constants under the viscous law too, checking and
    stepping it as a quiet step would, letting a stick-slip parcel ride its wheels for six ticks and another catch
    up with them from rest (in closed form and by the exact mode loop), gathering the cells under it as sensing
    does, and stepping the sorter once and carrying its sentences. The first integration of a process does this
    anyway (but for the sorter and its sentences); call it to do it at a time of your choosing (the set-up of
    ``make`` does, so that no later run waits). Returns the seconds it took.

    With ``settle`` (the default) it then collects the garbage and freezes every object still alive
    (:func:`gc.freeze`): the libraries' and the loaded engine's ~140,000, which live as long as the process. The
    collector's full passes then skip them: one took ~55 ms over them, and a run of 200 parcels makes one in its
    first simulated second (a fifth of it). Frozen objects are still freed when nothing refers to them; only cycles
    among them are no longer collected, so call it once the libraries are loaded, not with a large state of your own
    alive that you mean to drop."""
    start = time.perf_counter()
    cells = grid(4, 4, 0.1)
    spec = rectangle(0.25, 0.22, 1.0, 0.5)
    model = ParcelModel(cells, spec, Uniform((0.1, 0.0)).velocities(cells), LAWS["coulomb"])
    end = integrate(model, np.array([0.15, 0.15, 0.0, 0.0, 0.0, 0.0]), 0.0, 0.01).states[-1]
    # long enough for support changes: the compiled event loop and its table (a call's first piece runs alone)
    integrate(model.with_velocities(model.velocities), np.array([0.15, 0.15, 0.0, 0.0, 0.0, 0.0]), 0.0, 0.3)
    piece = model.piece_at(end)  # found again: the cache's test of a solution
    LAWS["viscous"].constants_and_row(piece.solution, model.velocities[piece.support],
                                      cells.active_directions[piece.support], 0.5, spec.mass, spec.inertia)
    constants_row(piece.constants, piece.solution.origin, spec.mass, spec.inertia)  # as unpickling a piece does
    # the quiet step's compiled checks, with the argument types networked runs give them
    stepper = QuietStepper(cells, [spec], model.law, [spec.mu], model.weight / spec.mass, 1e-10, 1e-12)
    stepper.compile_checks(model, end)
    _kernel.quiet_steps(np.array([piece.row]), end[None], 0.01, 0.02, 1e-10, 1e-12,
                        np.array([0.01, 0.02]), np.empty((1, 2, 6)))
    # a stick-slip parcel riding its wheels, measured in Python, then again in the compiled call (engine.ride)
    # (its front edge 5 mm short of a wheel: the support change at the fifth tick fails the kept proof)
    riding = Plant(cells, [spec], LAWS["stick_slip"], model.weight / spec.mass)
    ys, active = [np.array([0.22, 0.15, 0.0, 0.1, 0.0, 0.0])], [True]
    for k in range(6):
        riding.advance(ys, active, model.velocities, 0.01 * k, 0.01 * (k + 1), 0.01)
    # and one from rest catching up with its wheels across support changes: in closed form (engine.glide), and by
    # the exact mode loop (engine._modeloop), which takes every window the closed form does not
    for closed_form in (True, False):
        catching = Plant(cells, [spec], LAWS["stick_slip"], model.weight / spec.mass)
        if not closed_form:
            catching._glide = None
        catching.advance([np.array([0.15, 0.15, 0.0, 0.0, 0.0, 0.0])], [True], model.velocities, 0.0, 0.2, 0.2)
    covered_pairs([spec], [end], cells.grid)  # as sensing and destination labels gather cells
    sorter = Sorter(0.3)  # the sorter's compiled cell program, and its sentences carried, as a networked run goes
    topology = from_layout(cells)
    inputs = CellInputs(0.0, np.zeros((cells.n, 5), bool), Mailbox.empty(sorter.schema, cells.n, 4),
                        topology.connected, {}, None)
    sent = sorter.step(sorter.init(cells.n, 4, {}), inputs)[1]
    rounds = IdealRounds(topology)
    for _ in range(2):  # the first carries everything, the second what changed
        rounds.exchange_changed(sent, np.ones(cells.n, bool), 0.0, 0.01)
    if settle:
        gc.collect()
        gc.freeze()
    return time.perf_counter() - start
