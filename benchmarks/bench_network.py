"""Network benchmark (issue: cell network). Prints figures; asserts nothing about time.

Sentences per second of wall time handled by each delivery model on a 100 x 100 array, every cell broadcasting its
gradient distance on its four ports every tick (the Routing program), and what the wire-level hardware achieves in
simulated time (delivered fraction, latency).

Run: ``make bench`` (or ``python benchmarks/bench_network.py``).
"""

from __future__ import annotations

import time

import numpy as np

from virtual_vehicle.cells.network.delivery import IdealRounds
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import CellInputs, Routing
from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.cells.network.wire import WireLevel
from virtual_vehicle.model import layout


def measure(delivery, topo, ticks: int, period: float):
    n, P = topo.n, topo.ports
    exits = np.zeros(n, bool)
    exits[0] = True
    config = {"exit": exits}
    prog = Routing(max_age=10)
    state = prog.init(n, P, config)
    inbox = Mailbox.empty(prog.schema, n, P)
    sent = received = 0
    lat = []
    exchange_time = 0.0
    for k in range(ticks):
        state, out, _ = prog.step(state, CellInputs(k * period, np.zeros((n, 1), bool), inbox, topo.connected, config))
        t = time.perf_counter()
        inbox, stats = delivery.exchange(out, k * period, period)
        exchange_time += time.perf_counter() - t
        sent += int(stats.sent.sum())
        received += int(stats.received.sum())
        lat.append(stats.latencies)
    lat = np.concatenate(lat)
    return sent, received, exchange_time, lat


def main() -> None:
    topo = from_layout(layout.grid(100, 100, 0.1))
    print("# Network delivery on a 100 x 100 array (10^4 cells, 4 ports), gradient broadcast every tick")
    print(f"{'model':<26}{'ticks':>6}{'sent':>10}{'delivered':>11}{'wall (s)':>10}{'sentences/s':>14}"
          f"{'latency mean (ms)':>19}")
    for name, delivery, ticks, period in (("ideal rounds", IdealRounds(topo), 50, 0.01),
                                          ("wire level, 9600 baud", WireLevel(topo), 4, 0.05)):
        sent, received, wall, lat = measure(delivery, topo, ticks, period)
        print(f"{name:<26}{ticks:>6}{sent:>10}{received:>11}{wall:>10.2f}{received / wall:>14.0f}"
              f"{lat.mean() * 1e3:>19.2f}")


if __name__ == "__main__":
    main()
