"""Wire-level delivery: the paper's cell network hardware (Section 2.3), simulated event by event.

Each cell has one serial port (UART) multiplexed between its neighbours, and one handshake line to each neighbour.

- A cell with nothing in progress *polls*: it checks the incoming handshake line of one port every ``poll_time``
  seconds, port after port. A cell with sentences queued tries to send after each full sweep of its ports.
- To send on port q the cell selects q, raises its handshake line toward that neighbour and waits until the
  neighbour's polling reaches that line (the transfer starts) or ``cts_timeout`` passes (by default as long as the
  longest sentence holds a line: a neighbour busy with one transfer is waited for) (it lowers the line, waits a
  random backoff in [0, ``backoff_max``] while polling, and tries again; after ``max_attempts`` tries the sentence
  is dropped). While it waits it goes on polling its neighbours' handshake lines (the paper's processor "polls
  through all four neighbor's handshaking lines"): a neighbour waiting to send to it is answered, its own line
  lowered (that try is not counted), and it tries again after the transfer. So two cells that want to send to each
  other at once, or a ring of them, do not wait each other out: the first to poll the other's line receives.
- A transfer takes ``select_time`` plus the sentence's bytes at ``bits_per_byte`` bits each at ``baud`` bits/s;
  both cells are busy for that time. Bit errors flip data bits independently at ``bit_error_rate``; the receiver
  decodes the bytes and drops a sentence that fails (counted as corrupted), or, if the checksum misses, delivers the
  misread sentence (counted as undetected). ``loss_rate`` loses whole sentences after transfer (e.g. an overrun).
- Ports with no neighbour are known to be empty and their sentences dropped at once; a dead link or dead neighbour
  simply never answers, which the sender finds out by timing out.
- Per port at most ``queue_limit`` sentences wait; a newer one replaces the oldest waiting one (state-sharing
  programs want the latest value), and the tries the port's handshake has made still count, so that a silent
  neighbour is given up on after ``max_attempts`` tries however often the sender has news for it.

Latency, queueing and lost opportunities therefore emerge from the model. Polling of idle cells is not simulated
poll by poll: a polling cell's position in its sweep is a function of time, so only interactions cost events.
Units: s, bits/s, bytes.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from virtual_vehicle.cells.network.delivery import TickStats
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.sentence import MAX_PAYLOAD, OVERHEAD, SentenceError
from virtual_vehicle.cells.network.topology import Topology
from virtual_vehicle.model import state_data

POLL, WAIT, XFER, DEAD = range(4)


@dataclass(frozen=True)
class WireParams:
    """Hardware parameters (defaults: a 68HC11-class controller at 9600 baud)."""

    baud: float = 9600.0
    bits_per_byte: int = 10
    poll_time: float = 50e-6
    select_time: float = 20e-6
    cts_timeout: float | None = None
    """How long a sender waits for the neighbour to answer its handshake line (s); None: as long as the longest
    sentence holds a line at this baud (64 bytes, :data:`~virtual_vehicle.cells.network.sentence.MAX_PAYLOAD` plus
    its frame, and the select time), at least 2 ms, so that a neighbour busy with one transfer is waited for and not
    given up on (:meth:`longest_transfer`)."""
    backoff_max: float = 1e-3
    max_attempts: int = 5
    queue_limit: int = 1
    bit_error_rate: float = 0.0
    loss_rate: float = 0.0

    def __post_init__(self):
        for name in ("baud", "poll_time"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        for name in ("select_time", "backoff_max"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be non-negative")
        if self.max_attempts < 1 or self.queue_limit < 1 or self.bits_per_byte < 8:
            raise ValueError("max_attempts and queue_limit must be >= 1 and bits_per_byte >= 8")
        for name in ("bit_error_rate", "loss_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1]")
        if self.cts_timeout is None:  # (from the line's numbers, checked above)
            object.__setattr__(self, "cts_timeout", max(2e-3, self.longest_transfer()))
        if not self.cts_timeout > 0:
            raise ValueError("cts_timeout must be positive")

    def longest_transfer(self) -> float:
        """The time the longest sentence (64 bytes) holds a line: the select time and its bytes at the baud (s)."""
        return self.select_time + (MAX_PAYLOAD + OVERHEAD) * self.bits_per_byte / self.baud


class _Sentence:
    __slots__ = ("data", "t_sent", "attempts")

    def __init__(self, data: bytes, t_sent: float):
        self.data = data
        self.t_sent = t_sent
        self.attempts = 0


class WireLevel:
    """The wire-level delivery model; state (queues, modes, time) persists from one exchange to the next."""

    def __init__(self, topology: Topology, params: WireParams = WireParams(), seed: int | None = 0):
        self.topology = topology
        self.p = params
        self.rng = np.random.default_rng(seed)
        n, P = topology.n, topology.ports
        self.mode = np.where(topology.alive, POLL, DEAD)
        self.epoch = np.zeros(n, dtype=np.int64)
        self.t0 = np.zeros(n)  # polling phase: at t0 the cell polls port p0, then one port per poll_time
        self.p0 = np.zeros(n, dtype=np.int64)
        self.target = np.full(n, -1, dtype=np.int64)  # port being sent on (WAIT / XFER as sender)
        self.next_port = np.zeros(n, dtype=np.int64)  # round-robin pointer for choosing what to send
        self.queues = [[deque() for _ in range(P)] for _ in range(n)]
        self.events: list = []
        self.seq = 0
        self.now = 0.0
        self._reset_tick(n, P)

    # ------------------------------------------------------------------ public
    def exchange(self, outbox: Mailbox, t: float, period: float) -> tuple[Mailbox, TickStats]:
        """Serialise, frame and checksum every sentence at the link's baud rate and deliver what is complete by the
        tick's end (corrupted frames are counted and dropped); see
        :class:`~virtual_vehicle.cells.network.delivery.Delivery`."""
        if t < self.now - 1e-12:
            raise ValueError("exchange times must not go backwards")
        topo = self.topology
        n, P = topo.n, topo.ports
        self._reset_tick(n, P)
        self.schema = outbox.schema
        self._advance(t)  # finish whatever was due before this tick
        self.inbox = Mailbox.empty(outbox.schema, n, P)
        partial = outbox.words is not None  # sentences carry only the words the program marked
        if partial:
            self.inbox.words = np.zeros((n, P), dtype=np.int64)
        cells, ports = np.nonzero(outbox.present & topo.alive[:, None])
        for i, q in zip(cells.tolist(), ports.tolist()):
            if topo.neighbor[i, q] < 0:
                self.unaddressed += 1  # nobody there: the cell knows the port is empty
                continue
            values = {k: v[i, q] for k, v in outbox.values.items()}
            words = int(outbox.words[i, q]) if partial else None
            queue = self.queues[i][q]
            waiting = len(queue) - (1 if (self.mode[i] == XFER and self.target[i] == q) else 0)
            tries = 0
            if waiting >= self.p.queue_limit:
                # replace the oldest waiting sentence (not the one on the wire)
                idx = 1 if len(queue) > waiting else 0
                if partial:  # the words it carried and the new one does not still go (the port's latest words)
                    values, words = self._merged(queue[idx].data, values, words)
                tries = queue[idx].attempts if idx == 0 else 0
                del queue[idx]
                self.superseded += 1
            data = outbox.schema.to_bytes(values, words)
            queue.append(_Sentence(data, t))
            if tries:  # the port's handshake goes on: the tries it made count for the sentence now at its head
                queue[0].attempts = max(queue[0].attempts, tries)
            self.sent[i] += 1
            self.bytes_sent[i] += len(data)
        for i in range(n):
            if self.mode[i] == POLL and self._has_queue(i):
                self._push(self._next_sweep_end(i, t), "try", i)
        self._advance(t + period)
        stats = TickStats(self.sent, self.received, self.bytes_sent, self.bytes_received,
                          np.array(self.latencies), lost=self.lost, corrupted=self.corrupted,
                          undetected=self.undetected, dropped=self.dropped, unaddressed=self.unaddressed,
                          extra={"timeouts": self.timeouts, "superseded": self.superseded,
                                 "queued": sum(len(q) for qs in self.queues for q in qs)})
        return self.inbox, stats

    def set_topology(self, topology: Topology) -> None:
        """Cells died, were taken out or snapped in, links were cut (see
        :class:`~virtual_vehicle.cells.network.delivery.Delivery`), now. A cell that goes loses what it had queued
        (counted as dropped) and any transfer it was part of is broken off (the sender keeps its sentence and tries
        again); a transfer over a link that is cut likewise; a cell that comes starts polling with empty queues.
        Sentences queued for a port whose link is gone time out and are dropped as for any silent neighbour."""
        old, t = self.topology, self.now
        self.topology = topology
        P = topology.ports
        going = np.flatnonzero(old.alive & ~topology.alive)
        coming = np.flatnonzero(~old.alive & topology.alive)
        broken = set()
        for i in np.flatnonzero(self.mode == XFER):
            q = self.target[i]
            if q < 0:
                continue  # a receiver: found from its sender
            j = old.neighbor[i, q]
            if not (topology.alive[i] and topology.alive[j] and topology.link_up[i, q]):
                broken.update((int(i), int(j)))
        for i in going:
            self.dropped += sum(len(queue) for queue in self.queues[i])
            self.queues[i] = [deque() for _ in range(P)]
            self.target[i] = -1
            self._set_mode(i, DEAD, t)
        for i in sorted(broken - set(going.tolist())):
            self.target[i] = -1
            self._start_polling(i, t, self.p0[i])
        for i in coming:
            self.queues[i] = [deque() for _ in range(P)]
            self.target[i] = -1
            self._start_polling(i, t, 0)

    _KINDS = ("try", "connect", "done", "timeout")
    """The kinds of the pending events, in the order their codes in :meth:`to_data` number them."""

    def to_data(self) -> dict:
        """Everything that carries on from one exchange to the next, as data: the random generator (``rng``), per
        cell ``mode``, ``epoch``, polling phase ``t0`` (s) and ``p0``, ``target`` and ``next_port`` (n,), the clock
        ``now`` (s), the event counter ``seq``, the pending events as columns in heap order (``events``: time s,
        number, kind code of :attr:`_KINDS`, cells ``a``, ``b`` and their epochs) and the queued sentences as
        columns (``sentences``: cell, port, time sent s, attempts, length in bytes, in queue order, and their bytes
        one after another in ``data``). The tick's traffic counts start afresh at every exchange; the topology and
        parameters are the setup's and the run's."""
        ev = self.events
        kinds = {k: c for c, k in enumerate(self._KINDS)}
        queued = [(i, q, s) for i, ports in enumerate(self.queues) for q, queue in enumerate(ports) for s in queue]
        return {
            "rng": state_data.rng_to_data(self.rng),
            **{k: getattr(self, k).astype(np.float64 if k == "t0" else np.int64) for k in self._PER_CELL},
            "now": float(self.now), "seq": int(self.seq),
            "events": {"t": np.array([e[0] for e in ev], dtype=np.float64),
                       **{k: np.array([e[c] if c != 2 else kinds[e[2]] for e in ev], dtype=np.int64)
                          for c, k in ((1, "seq"), (2, "kind"), (3, "a"), (4, "b"), (5, "epoch_a"), (6, "epoch_b"))}},
            "sentences": {"cell": np.array([i for i, _, _ in queued], dtype=np.int64),
                          "port": np.array([q for _, q, _ in queued], dtype=np.int64),
                          "t_sent": np.array([s.t_sent for _, _, s in queued], dtype=np.float64),
                          "attempts": np.array([s.attempts for _, _, s in queued], dtype=np.int64),
                          "length": np.array([len(s.data) for _, _, s in queued], dtype=np.int64),
                          "data": np.frombuffer(b"".join(s.data for _, _, s in queued), dtype=np.uint8).copy()},
        }

    _PER_CELL = ("mode", "epoch", "t0", "p0", "target", "next_port")

    def load_data(self, d, inbox: Mailbox | None = None) -> None:
        """Go on from what :meth:`to_data` wrote, on a wire made from the same setup and over the run's topology now.
        ``inbox``: the mailbox the last exchange returned, which the run kept (a transfer that ends in the sliver
        between one tick's end and the next one's start is received into it, as in the run that wrote the data; its
        schema decodes them). Raises ValueError for data that is not such a wire's."""
        where = "delivery"
        d = state_data.fields(d, ("rng", *self._PER_CELL, "now", "seq", "events", "sentences"), where)
        n, P = self.topology.n, self.topology.ports
        per_cell = {k: state_data.array(d, k, "f" if k == "t0" else "i", (n,), where) for k in self._PER_CELL}
        if not (np.isin(per_cell["mode"], (POLL, WAIT, XFER, DEAD)).all() and (per_cell["target"] >= -1).all()
                and (per_cell["target"] < P).all() and (per_cell["p0"] >= 0).all() and (per_cell["p0"] < P).all()
                and (per_cell["next_port"] >= 0).all() and (per_cell["next_port"] < P).all()):
            raise ValueError(f"{where}: a cell's mode or port out of range")
        at = f"{where}.events"
        ev = state_data.fields(d["events"], ("t", "seq", "kind", "a", "b", "epoch_a", "epoch_b"), at)
        t = state_data.array(ev, "t", "f", (None,), at)
        cols = {k: state_data.array(ev, k, "i", (len(t),), at) for k in ("seq", "kind", "a", "b", "epoch_a",
                                                                          "epoch_b")}
        if not (((cols["kind"] >= 0) & (cols["kind"] < len(self._KINDS)) & (cols["a"] >= 0) & (cols["a"] < n)
                 & (cols["b"] >= -1) & (cols["b"] < n)).all()):
            raise ValueError(f"{at}: a kind or cell out of range")
        child = np.arange(1, len(t))
        parent = (child - 1) // 2
        if ((t[parent] > t[child]) | ((t[parent] == t[child]) & (cols["seq"][parent] >= cols["seq"][child]))).any():
            raise ValueError(f"{at}: not a heap of distinct events in time order")
        at = f"{where}.sentences"
        sd = state_data.fields(d["sentences"], ("cell", "port", "t_sent", "attempts", "length", "data"), at)
        cell = state_data.array(sd, "cell", "i", (None,), at)
        port, t_sent, attempts, length = (state_data.array(sd, k, "f" if k == "t_sent" else "i", (len(cell),), at)
                                          for k in ("port", "t_sent", "attempts", "length"))
        data = state_data.array(sd, "data", "u1", (None,), at)
        if not (((cell >= 0) & (cell < n) & (port >= 0) & (port < P) & (length >= 0)).all()
                and int(length.sum()) == len(data)):
            raise ValueError(f"{at}: a cell or port out of range, or lengths that do not add up to its bytes")
        self.rng = state_data.rng_from_data(d["rng"], f"{where}.rng")
        for k, a in per_cell.items():
            setattr(self, k, a)
        self.now, self.seq = state_data.number(d, "now", where), state_data.integer(d, "seq", where)
        kinds = [self._KINDS[c] for c in cols["kind"].tolist()]
        self.events = list(zip(t.tolist(), cols["seq"].tolist(), kinds, cols["a"].tolist(), cols["b"].tolist(),
                               cols["epoch_a"].tolist(), cols["epoch_b"].tolist()))
        self.queues = [[deque() for _ in range(P)] for _ in range(n)]
        raw = data.tobytes()
        ends = np.cumsum(length).tolist()
        for i, q, ts, tries, size, end in zip(cell.tolist(), port.tolist(), t_sent.tolist(), attempts.tolist(),
                                              length.tolist(), ends):
            s = _Sentence(raw[end - size:end], ts)
            s.attempts = tries
            self.queues[i][q].append(s)
        self._reset_tick(n, P)
        if inbox is not None:
            self.schema, self.inbox = inbox.schema, inbox

    # ------------------------------------------------------------------ internals
    def _merged(self, older: bytes, values: dict, words: int) -> tuple[dict, int]:
        """The sentence that replaces a waiting partial sentence ``older`` and a newer one (``values``, every word of
        the port now, and the bit mask ``words`` of those it carries): the words of both, each at its value now. A
        word the older one carried goes at the port's value now, not at the older value: a word that changed back
        since (a stop gone back to go, a word at its rest value that a sentence may leave unsaid) would otherwise
        reach the neighbour as the older value and stay there until the word changed again."""
        said = self.schema.from_bytes(older, partial=True)
        mask = words
        for k, f in enumerate(self.schema.fields):
            if f.name in said:
                mask |= 1 << k
        return {f.name: values[f.name] for f in self.schema.fields}, mask

    def _reset_tick(self, n, P):
        self.sent = np.zeros(n, dtype=np.int64)
        self.received = np.zeros(n, dtype=np.int64)
        self.bytes_sent = np.zeros(n, dtype=np.int64)
        self.bytes_received = np.zeros(n, dtype=np.int64)
        self.latencies: list[float] = []
        self.lost = self.corrupted = self.undetected = self.dropped = self.unaddressed = 0
        self.timeouts = self.superseded = 0

    def _push(self, t, kind, a, b=-1):
        self.seq += 1
        heapq.heappush(self.events, (t, self.seq, kind, a, b, self.epoch[a], self.epoch[b] if b >= 0 else 0))

    def _advance(self, t_end):
        ev = self.events
        while ev and ev[0][0] <= t_end:
            t, _, kind, a, b, ea, eb = heapq.heappop(ev)
            self.now = t
            if self.epoch[a] != ea or (b >= 0 and self.epoch[b] != eb):
                continue  # the cell changed mode since: stale
            getattr(self, "_on_" + kind)(t, a, b)
        self.now = max(self.now, t_end)

    def _has_queue(self, i) -> bool:
        return any(self.queues[i])

    def _set_mode(self, i, mode, t):
        self.mode[i] = mode
        self.epoch[i] += 1
        if mode == POLL:
            self.t0[i] = t

    def _next_sweep_end(self, i, t) -> float:
        sweep = self.topology.ports * self.p.poll_time
        k = math.ceil((t - self.t0[i]) / sweep - 1e-9)
        return self.t0[i] + max(k, 0) * sweep

    def _poll_time_of(self, j, port, t) -> float:
        """When polling cell j next checks the handshake line of ``port`` at or after t."""
        tau, P = self.p.poll_time, self.topology.ports
        k = max(0, math.ceil((t - self.t0[j]) / tau - 1e-9))
        k += (port - self.p0[j] - k) % P
        return self.t0[j] + k * tau

    def _start_polling(self, i, t, first_port, retry_at=None):
        """Poll from ``first_port`` on; answer neighbours already waiting on us in the order the sweep reaches
        them; if sentences are queued, try to send again at ``retry_at`` (default: after one full sweep)."""
        self._set_mode(i, POLL, t)
        self.p0[i] = first_port % self.topology.ports
        self._listen(i, t)
        if self._has_queue(i):
            self._push(t + self.topology.ports * self.p.poll_time if retry_at is None else retry_at, "try", i)

    def _listen(self, i, t):
        """Answer the neighbours already waiting to send to polling cell i, in the order its sweep reaches their
        lines (from the epoch of i's mode now: a new mode, a new listen)."""
        topo = self.topology
        for q in range(topo.ports):
            j = topo.neighbor[i, q]
            if j >= 0 and topo.link_up[i, q] and self.mode[j] == WAIT and self.target[j] == topo.back_port[i, q]:
                self._push(self._poll_time_of(i, q, t), "connect", i, j)

    def _on_try(self, t, i, _):
        if self.mode[i] != POLL or not self._has_queue(i):
            return
        P = self.topology.ports
        for k in range(P):
            q = (self.next_port[i] + k) % P
            if self.queues[i][q]:
                break
        self.next_port[i] = (q + 1) % P
        self.target[i] = q
        self._set_mode(i, WAIT, t)  # (t0 kept: waiting, it polls on in the same sweep)
        self._push(t + self.p.cts_timeout, "timeout", i)
        self._listen(i, t)  # (its mode's epoch is new: the neighbours waiting on it are answered anew)
        topo = self.topology
        j = topo.neighbor[i, q]
        if topo.link_up[i, q] and topo.alive[j] and self.mode[j] in (POLL, WAIT):
            self._push(self._poll_time_of(j, topo.back_port[i, q], t), "connect", j, i)

    def _on_connect(self, t, j, i):
        # j (polling, or waiting to send and polling meanwhile) sees i's handshake line on the port that leads to i;
        # i is waiting to send to j. A waiting j lowers its own line: that try is not counted, it tries again later
        if self.mode[j] not in (POLL, WAIT) or self.mode[i] != WAIT:
            return
        self.target[j] = -1  # j receives
        q = self.target[i]
        head = self.queues[i][q][0]
        duration = self.p.select_time + len(head.data) * self.p.bits_per_byte / self.p.baud
        self._set_mode(i, XFER, t)
        self._set_mode(j, XFER, t)
        self._push(t + duration, "done", i, j)

    def _on_done(self, t, i, j):
        topo = self.topology
        q = self.target[i]
        s = self.queues[i][q].popleft()
        port = topo.back_port[i, q]
        self._receive(j, port, s, t)
        self.target[i] = -1
        self._start_polling(i, t, q + 1)
        self._start_polling(j, t, port + 1)

    def _receive(self, j, port, s: _Sentence, t):
        data = s.data
        if self.p.bit_error_rate > 0:
            nbits = 8 * len(data)
            k = self.rng.binomial(nbits, self.p.bit_error_rate)
            if k:
                buf = bytearray(data)
                for b in self.rng.choice(nbits, k, replace=False).tolist():
                    buf[b // 8] ^= 1 << (b % 8)
                data = bytes(buf)
        if self.p.loss_rate > 0 and self.rng.random() < self.p.loss_rate:
            self.lost += 1
            return
        partial = self.inbox.words is not None
        try:
            values = self.schema.from_bytes(data, partial=partial)
        except SentenceError:
            self.corrupted += 1
            return
        if data != s.data:
            self.undetected += 1
        for k, v in values.items():
            self.inbox.values[k][j, port] = v
        if partial:  # two sentences may arrive in one tick: the inbox holds the words of both
            self.inbox.words[j, port] |= sum(1 << k for k, f in enumerate(self.schema.fields) if f.name in values)
        self.inbox.present[j, port] = True
        self.received[j] += 1
        self.bytes_received[j] += len(data)
        self.latencies.append(t - s.t_sent)

    def _on_timeout(self, t, i, _):
        if self.mode[i] != WAIT:
            return
        self.timeouts += 1
        q = self.target[i]
        head = self.queues[i][q][0]
        head.attempts += 1
        if head.attempts >= self.p.max_attempts:
            self.queues[i][q].popleft()
            self.dropped += 1
        self.target[i] = -1
        # back off: poll for a random while before trying again
        self._start_polling(i, t, self.p0[i], retry_at=t + self.rng.uniform(0.0, self.p.backoff_max))
