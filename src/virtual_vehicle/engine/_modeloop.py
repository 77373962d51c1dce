"""One stick-slip parcel's event loop in one compiled call (issue 32, item 4).

Units: SI (m, s, kg, N, N m, J).

:func:`run_modes` is the compiled form of the Python loop of :func:`virtual_vehicle.engine.dynamics._run_modes`: it
integrates a mode (:func:`~virtual_vehicle.engine._kernel.run_mode`), decides the next mode at a mode event
(:func:`~virtual_vehicle.physics.stick_modes.breaking_kernel`, :func:`~virtual_vehicle.physics.stick_modes.
decide_kernel`), and at a support event looks the next piece up in the model's piece table
(:func:`~virtual_vehicle.engine._kernel.table_lookup`, or makes it from a solved pattern, as the Coulomb loop
:func:`~virtual_vehicle.engine._kernel.run_events` does), builds its wheels (``_wheel_arrays``) and decides their mode,
over as many events as it can. It calls the very compiled functions the Python loop calls, with the same arrays, so
a run is the same bit for bit whichever loop took an event. What it cannot do it hands back: a support set the table
cannot give (a solve it cannot make, tipping), a chatter test that would hold, an undecided mode,
a pause, a full log. What Python makes of the events (the run's :class:`~virtual_vehicle.engine.stepping.Event`
objects and the mode record) it writes into a log of plain arrays, read after the call.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from virtual_vehicle.engine._kernel import (
    EVENT,
    LOOP_DONE,
    LOOP_MISS,
    LOOP_SEGMENT,
    LOOP_TOO_MANY,
    MODE_EVENT,
    _gather,
    _ids_hash,
    _record_arrays,
    cells_under,
    piece_segment,
    run_mode,
    table_next_piece,
)
from virtual_vehicle.model.parcel import _within
from virtual_vehicle.physics.stick_modes import _wheel_arrays, breaking_kernel, decide_kernel

LOOP_UNDECIDED, LOOP_MODE_CHATTER, LOOP_START = 15, 16, 17
"""Outcomes of :func:`run_modes` besides run_events' ones: the mode rule could not decide a mode (the new mode is
none: Python crosses fixed steps), mode events chatter (Python raises), and the table cannot give the first piece
of a call started from the support set (Python finds it, as it finds a missed one, and calls again)."""

START_TOLD, START_PROBE = -1, -2
"""The piece :func:`run_modes` may start from instead of one of the table's: that of the cells ``start`` (told by
the caller: a quiet stepper's hand-over), or of the cells under the footprint at the probe state."""

LOG_SLIP, LOG_STICK, LOG_SUPPORT = 0, 1, 2
"""Kinds of a log entry: a mode event ended by a slipping wheel reaching zero slip, by the sticking wheels' required
wrench reaching a facet of their zonotope, and a support change to another piece."""

LOG_FLOATS, LOG_INTS = 13, 7
"""A log entry's floats (time, the state before the event's mode decision and after it) and integers (kind, piece
before, piece after, offset of the mode before and after in the state pool (-1: none), their length, and whether a
support change changed the mode of a wheel staying in contact)."""


@njit(cache=True)
def support_hash(support):
    """A 64-bit hash of the cell ids ``support`` (int64), what the chatter ring compares support sets by."""
    return np.int64(_ids_hash(support))


@njit(cache=True)
def ring_event(ring_t, ring_h, ring, t, key, span, pieces, push):
    """The support changes' chatter test over the latest ``ring_t.shape[0]`` changes (times ``ring_t``, support sets'
    hashes ``ring_h``, ``ring`` (2,) their count and next slot) with one at time ``t`` (s) onto support set ``key``
    added: whether the ring is full, its oldest change within ``span`` times max(1, |t|) of ``t`` and it holds at most
    ``pieces`` distinct support sets. With ``push`` the change is added (the oldest dropped), else only tested."""
    size, count, nxt = ring_t.shape[0], ring[0], ring[1]
    chatter = False
    if count + 1 >= size:
        oldest = (nxt + 1) % size
        if t - ring_t[oldest] <= span * max(1.0, abs(t)):
            seen = np.empty(pieces + 1, np.int64)
            distinct = 0
            for j in range(size):
                h = key if j == nxt else ring_h[j]
                known = False
                for i in range(distinct):
                    known = known or seen[i] == h
                if not known:
                    if distinct == pieces:
                        distinct += 1
                        break
                    seen[distinct] = h
                    distinct += 1
            chatter = distinct <= pieces
    if push:
        ring_t[nxt], ring_h[nxt] = t, key
        ring[1] = (nxt + 1) % size
        ring[0] = min(count + 1, size)
    return chatter


@njit(cache=True)
def _support_of(tab, p):
    """The cell ids (int64) of piece ``p``'s support set in table ``tab``."""
    kmeta, ipool, pkey = tab[1], tab[2], tab[6]
    k = pkey[p]
    return ipool[kmeta[k, 0]:kmeta[k, 0] + kmeta[k, 1]]


@njit(cache=True)
def _held_before(active, old_ids, old_state, new_ids, after):
    """The mode before a support change, wheel by wheel of the new support set: a wheel that stays in contact keeps
    its mode before the change (``old_state`` of the same cell and wheel), others (new wheels, wheels out of
    contact on either side) read as ``after`` (lifting off or touching down is the support event itself)."""
    before = after.copy()
    j = 0
    for r in range(new_ids.shape[0]):
        i = new_ids[r]
        for k in range(2):
            if not active[i, k]:
                continue
            held = 2
            a = 0
            for ro in range(old_ids.shape[0]):
                io = old_ids[ro]
                for ko in range(2):
                    if not active[io, ko]:
                        continue
                    if io == i and ko == k:
                        held = old_state[a]
                    a += 1
            if not (held == 2 or after[j] == 2):
                before[j] = held
            j += 1
    return before


@njit(cache=True)
def _log(log_f, log_i, log_s, n_log, n_s, kind, p, q, t, y_before, y_after, before, after, flag):
    """Write one log entry (``after`` empty with ``flag`` -1: no mode after); the state pool's new length."""
    log_f[n_log, 0] = t
    for e in range(6):
        log_f[n_log, 1 + e] = y_before[e]
        log_f[n_log, 7 + e] = y_after[e]
    n = before.shape[0]
    log_i[n_log, 0], log_i[n_log, 1], log_i[n_log, 2], log_i[n_log, 5] = kind, p, q, n
    log_i[n_log, 3] = n_s
    log_s[n_s:n_s + n] = before
    n_s += n
    if flag < 0:
        log_i[n_log, 4], log_i[n_log, 6] = -1, 0
    else:
        log_i[n_log, 4], log_i[n_log, 6] = n_s, flag
        log_s[n_s:n_s + n] = after
        n_s += n
    return n_s


@njit(cache=True)
def run_modes(tab, law, wheel_cells, footprint, scales, grid, p, start, wheels, mode, minv, candidates, center, ids, y_base,
              t, z, t_bound, h, h_abs, first_step, rtol, atol, max_step, max_steps, sample_times, next_sample, samples,
              segments, max_segments, ring_t, ring_h, ring, chatter_span, chatter_pieces, clock, same, same_limit,
              log_f, log_i, log_s):
    """One stick-slip parcel's event loop from piece ``p`` of table ``tab`` in ``mode`` (as
    :func:`~virtual_vehicle.physics.stick_modes.decide_kernel` gives it: state, independent sticking rows, sticking
    wheels, rank, anchor, facet index) of its ``wheels`` (the ten arrays of
    :func:`~virtual_vehicle.physics.stick_modes.wheel_arrays`), the 8-long state ``z`` (the parcel's six, wheel work
    and friction loss, J) at time ``t``, on the segment of candidates ``candidates``/``ids`` gathered about ``center``
    with probe ``y_base``; the first mode's first step ``first_step`` (0: resume with ``h_abs`` after a pause). Its
    loop as :func:`~virtual_vehicle.engine.dynamics._run_modes`', the iteration Python began counted in ``segments``.

    ``p`` :data:`START_TOLD` or :data:`START_PROBE` starts the call as Python's loop starts instead (its first piece
    found, its wheels built and their mode decided at ``y_base``, the candidates gathered about it): the piece of
    the cells ``start`` or of those under the footprint, looked up or made as at a support event; ``wheels``,
    ``mode``, ``candidates``, ``center`` and ``ids`` then only give their types. Where the table cannot give that
    piece the call returns :data:`LOOP_START` at once (nothing logged, nothing made).

    ``law`` is the table's ``law_args`` (:func:`~virtual_vehicle.engine._kernel.run_events`), ``wheel_cells`` (cells'
    wheel_active, drive directions, mu, mu_static), ``footprint`` the parcel's outline, ``scales`` (buffer, reach,
    noise length, noise force), ``grid`` as run_events takes it; ``ring_t``/``ring_h``/``ring`` the support chatter
    ring (:func:`ring_event`), ``clock`` (1,) the time of the last mode record (NaN: none), ``same`` (1,) the mode
    events in a row at one time (at most ``same_limit``); ``log_f``/``log_i``/``log_s`` the log (:data:`LOG_FLOATS`).

    Returns (outcome, t, z, piece, h, h_abs, evaluations, next_sample, segments, log entries, state pool used, pieces
    made, probe state, cells under the footprint at the probe, whether those tell, ids, candidates, centre, probe base,
    mode, wheels, whether the piece is new (Python begins its segment)). Outcomes: ``REACHED``, ``PAUSED`` (resume
    with ``first_step`` 0), a failure, ``LOOP_DONE`` (an event at t_bound), ``LOOP_MISS`` (a support event Python
    takes from the probe on: piece, mode and wheels are those before it), ``LOOP_SEGMENT`` (Python goes on at the
    top of its loop), ``LOOP_TOO_MANY``, :data:`LOOP_UNDECIDED`, :data:`LOOP_MODE_CHATTER`."""
    kind, convex, half, normals, offsets, vertices = footprint
    buffer, reach, noise_length, noise_force = scales
    (drive, positions, unit, velocities, directions, mu, damping, inv_mass, inv_inertia, born_terms, weight, solve_log,
     solve_origin) = law
    active, wheel_dirs, mu_k, mu_s = wheel_cells
    psol, porigin, srec, fpool = tab[3], tab[4], tab[8], tab[9]
    (g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, radius) = grid
    reuse2 = 0.25 * buffer * buffer * (1.0 - 1e-9)  # clearly within half the buffer (the edge is Python's to decide)
    gather2 = 0.25 * buffer * buffer * (1.0 + 1e-9)  # clearly beyond it: gathered again, as _Segment would
    P, U, w0, wa, t0, FL, FC, origin, mus, muk = wheels
    state, rows, stick, rank, anchor, index = mode
    capacity, pool = log_f.shape[0], log_s.shape[0]
    n_log = n_s = born = nfev = 0
    none = np.empty(0, np.int64)
    y_probe = y_base
    new_piece = False
    if p < 0:  # the first piece, as Python's piece_for (or piece_at) finds it before its loop
        under = start
        if p == START_PROBE:  # the cells under the footprint, as ParcelModel.support_at finds them
            under = cells_under(grid, positions, kind, half, normals, offsets, vertices, y_base)
        q = -1
        if under.shape[0]:
            q, born = table_next_piece(tab, under, y_base[0], y_base[1], positions, unit, velocities, directions,
                                       drive, mu, damping, inv_mass, inv_inertia, born_terms, born, weight,
                                       solve_log, solve_origin)
        if q < 0:
            return (LOOP_START, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, none,
                    False, ids, candidates, center, y_base, mode, wheels, new_piece)
        p = q
        _, _, _, _, _, _, _, _, _, force_lin, force_const, _ = _record_arrays(srec, fpool, psol[p])
        wheels = _wheel_arrays(active, wheel_dirs, positions, velocities, _support_of(tab, p), force_lin,
                               force_const, porigin[p], mu_k, mu_s)
        P, U, w0, wa, t0, FL, FC, origin, mus, muk = wheels
        if 8 * P.shape[0] + 256 > pool:  # no room for its mode's log: Python makes the pool larger
            return (LOOP_START, t, z, START_TOLD, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe,
                    none, False, ids, candidates, center, y_base, mode, wheels, new_piece)
        ids = _within(g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, y_base[0], y_base[1],
                      radius + buffer)  # the segment's candidates, as _Segment gathers them
        candidates = _gather(positions, ids)
        center = np.empty(2)
        center[0], center[1] = y_base[0], y_base[1]
        ok, new_state, y_new, new_rows, new_stick, new_rank, new_anchor, new_index = decide_kernel(
            P, U, w0, wa, t0, FL, FC, origin, mus, muk, minv, t, z[:6], none, none)
        if not ok:  # Python crosses fixed steps on this piece, in the iteration it began (counted again there)
            return (LOOP_UNDECIDED, t, z, p, h, h_abs, nfev, next_sample, segments - 1, n_log, n_s, born, y_probe,
                    none, False, ids, candidates, center, y_base, mode, wheels, True)
        z[:6] = y_new
        state, rows, stick, rank, anchor, index = new_state, new_rows, new_stick, new_rank, new_anchor, new_index
    while True:  # (the log has room for this mode's event: Python's first iteration starts it empty)
        m = state.shape[0]
        new_piece = False
        seg = piece_segment(srec, fpool, psol[p], porigin[p], kind, convex, half, normals, offsets, vertices,
                            candidates, center, buffer, reach, noise_length, noise_force, ids)
        md = (P, U, w0, wa, t0, FL, FC, origin, mus, muk, state, stick[rows], stick, rank, anchor, index, minv)
        slipping = 0
        for j in range(m):
            slipping += state[j] == 1 or state[j] == -1
        n_ev = slipping + (index.shape[0] if stick.shape[0] else 0)
        (outcome, t, z, h_abs, last, evals, next_sample, t_probe, y_probe, under,
         told, which) = run_mode(md, n_ev, seg, y_base, t, z, t_bound, h_abs, first_step, rtol, atol, max_step,
                                 max_steps, sample_times, next_sample, samples)
        nfev += evals
        if last:
            h = last
        if outcome != MODE_EVENT and outcome != EVENT:  # reached, paused or failed
            return (outcome, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, none, False,
                    ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index), wheels, new_piece)
        if outcome == MODE_EVENT:
            if which >= slipping:
                entry = LOG_STICK
                breaking, signs = breaking_kernel(P, U, w0, wa, t0, FL, FC, origin, mus, muk, minv, t, z[:6], state,
                                                  stick, rank, anchor, index, which - slipping)
            else:
                entry = LOG_SLIP
                breaking, signs = none, none
            y_before = z[:6].copy()
            ok, new_state, y_new, new_rows, new_stick, new_rank, new_anchor, new_index = decide_kernel(
                P, U, w0, wa, t0, FL, FC, origin, mus, muk, minv, t, z[:6], breaking, signs)
            if ok:
                z[:6] = y_new
            same[0] = same[0] + 1 if t - clock[0] <= 1e-12 * max(1.0, t) else 0
            if same[0] > same_limit:
                return (LOOP_MODE_CHATTER, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe,
                        none, False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index),
                        wheels, new_piece)
            clock[0] = t
            n_s = _log(log_f, log_i, log_s, n_log, n_s, entry, p, p, t, y_before, z, state, new_state,
                       1 if ok else -1)
            n_log += 1
            if not ok:
                return (LOOP_UNDECIDED, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe,
                        none, False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index),
                        wheels, new_piece)
            state, rows, stick, rank, anchor, index = new_state, new_rows, new_stick, new_rank, new_anchor, new_index
            if t >= t_bound:
                return (LOOP_DONE, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, none,
                        False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index), wheels,
                        new_piece)
            if n_log + 1 >= capacity or n_s + 4 * state.shape[0] > pool:  # Python goes on at its loop's top
                return (LOOP_SEGMENT, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe,
                        none, False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index),
                        wheels, new_piece)
            segments += 1
            if segments > max_segments:
                return (LOOP_TOO_MANY, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe,
                        none, False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index),
                        wheels, new_piece)
            first_step, h_abs = min(h, t_bound - t), 0.0
            continue
        # a support event: the next piece from the table (or made from a solved pattern), else Python's
        if not told:  # the cells under the footprint at the probe, as ParcelModel.support_at finds them
            under = cells_under(grid, positions, kind, half, normals, offsets, vertices, y_probe)
        q, born = table_next_piece(tab, under, y_probe[0], y_probe[1], positions, unit, velocities, directions, drive,
                                   mu, damping, inv_mass, inv_inertia, born_terms, born, weight, solve_log,
                                   solve_origin)
        miss = q < 0
        if not miss:
            new_ids = _support_of(tab, q)
            key = support_hash(new_ids)
            miss = (n_s + 4 * (m + 2 * new_ids.shape[0]) > pool
                    or ring_event(ring_t, ring_h, ring, t, key, chatter_span, chatter_pieces, False))
        if miss:  # (a chatter test that holds: Python takes the event, and crosses it in fixed steps)
            return (LOOP_MISS, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, under,
                    told, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index), wheels,
                    new_piece)
        ring_event(ring_t, ring_h, ring, t, key, chatter_span, chatter_pieces, True)
        if q != p:
            y_before = z[:6].copy()
            old_ids = _support_of(tab, p)
            _, _, _, _, _, _, _, _, _, force_lin, force_const, _ = _record_arrays(srec, fpool, psol[q])
            wheels = _wheel_arrays(active, wheel_dirs, positions, velocities, new_ids, force_lin, force_const,
                                   porigin[q], mu_k, mu_s)
            P, U, w0, wa, t0, FL, FC, origin, mus, muk = wheels
            ok, new_state, y_new, new_rows, new_stick, new_rank, new_anchor, new_index = decide_kernel(
                P, U, w0, wa, t0, FL, FC, origin, mus, muk, minv, t, z[:6], none, none)
            if not ok:
                n_s = _log(log_f, log_i, log_s, n_log, n_s, LOG_SUPPORT, p, q, t, y_before, z, none, none, -1)
                n_log += 1
                p = q
                return (LOOP_UNDECIDED, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe,
                        none, False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index),
                        wheels, True)
            z[:6] = y_new
            changed = 0
            before = new_state
            if m:  # a wheel that stays under the parcel and changes mode here is an event too
                before = _held_before(active, old_ids, state, new_ids, new_state)
                for j in range(new_state.shape[0]):
                    if before[j] != new_state[j]:
                        changed = 1
            if changed:
                clock[0] = t
            n_s = _log(log_f, log_i, log_s, n_log, n_s, LOG_SUPPORT, p, q, t, y_before, z, before, new_state,
                       changed)
            n_log += 1
            state, rows, stick, rank, anchor, index = new_state, new_rows, new_stick, new_rank, new_anchor, new_index
        p = q
        new_piece = True
        if t >= t_bound:
            return (LOOP_DONE, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, none,
                    False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index), wheels,
                    new_piece)
        # the top of the loop on a new piece: its candidates kept while clearly within half the buffer
        dx, dy = y_probe[0] - center[0], y_probe[1] - center[1]
        d2 = dx * dx + dy * dy
        if n_log + 1 >= capacity or n_s + 4 * state.shape[0] > pool or not (d2 < reuse2 or d2 > gather2):
            return (LOOP_SEGMENT, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, none,
                    False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index), wheels,
                    new_piece)
        segments += 1
        if segments > max_segments:
            return (LOOP_TOO_MANY, t, z, p, h, h_abs, nfev, next_sample, segments, n_log, n_s, born, y_probe, none,
                    False, ids, candidates, center, y_base, (state, rows, stick, rank, anchor, index), wheels,
                    new_piece)
        if not d2 < reuse2:  # the cells within the radius plus the buffer of the probe (PointGrid.within)
            ids = _within(g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, y_probe[0],
                          y_probe[1], radius + buffer)
            candidates = _gather(positions, ids)
            center = np.empty(2)
            center[0], center[1] = y_probe[0], y_probe[1]
        y_base = y_probe.copy()
        first_step, h_abs = min(h, t_bound - t), 0.0
