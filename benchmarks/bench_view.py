"""Live viewer benchmark (issue 34, item 2): what one frame of the page costs on a 100 x 100 hall (10^4 cells,
pitch 0.1 m, the distributed sorter at 100 Hz, bench_scale's hall with ``--parcels`` parcels).

One live run is stepped ``--seconds`` of simulated time per frame; after each step two pages of it are drawn: one
that replaces every source each frame (as the page did before: the whole cell image every frame) and one that sends
only what changed (the image patched where cells changed colour, the other sources only when they differ). For
each it prints the bytes the server would send per frame (the PATCH-DOC message Bokeh builds from the frame's
changes: header, JSON and binary buffers, uncompressed and deflated as the viewer's websocket sends them) and the
time the server spends drawing a frame (s, the
fastest and the median over the frames). Asserts nothing about time.

Run: ``python benchmarks/bench_view.py`` (``--colour "program state"`` etc. for another colouring).
"""

from __future__ import annotations

import argparse
import platform
import time
import zlib

import numpy as np

from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.ui.view import COLOUR_BY, LiveRun, page
from virtual_vehicle.ui.view.server import DEFLATE

import bench_scale  # (run as a script: its folder is on the path)


class _Viewer:
    """What the page reads off its server: the run, paused (the benchmark steps it)."""

    def __init__(self, live):
        self.live, self.playing, self.speed, self.frame, self.message = live, False, 1.0, 0.1, ""

    def step_once(self):
        self.live.tick()


def message_bytes(events, level: int | None = None) -> int:
    """Bytes of the PATCH-DOC message a Bokeh server sends for ``events`` (0 when there are none); with ``level``,
    deflated at that zlib level as the viewer's websocket sends it (each part a websocket message)."""
    from bokeh.protocol import Protocol

    if not events:
        return 0
    msg = Protocol().create("PATCH-DOC", events)
    parts = [msg.header_json.encode(), msg.metadata_json.encode(), msg.content_json.encode(),
             *(b.to_bytes() for b in msg.buffers)]
    if level is None:
        return sum(len(p) for p in parts)
    return sum(len(zlib.compress(p, level)) for p in parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parcels", type=int, default=20)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--seconds", type=float, default=0.1, help="simulated s between frames")
    parser.add_argument("--colour", default="traffic", choices=COLOUR_BY)
    args = parser.parse_args()
    from bokeh.document import Document

    sc = parse_scenario(bench_scale.scenario(100, args.parcels, args.frames * args.seconds + 1.0))
    live = LiveRun(sc)
    pages = {}
    for mode, send_all in (("before: every source replaced", True), ("after: only what changed", False)):
        doc, sent = Document(), []
        refresh = page.build(doc, _Viewer(live), send_all=send_all)
        doc.get_model_by_name("colour").value = args.colour
        doc.callbacks.on_change(lambda event, sent=sent: sent.append(event))
        pages[mode] = (refresh, sent, [], [], [])
    for _ in range(args.frames):
        live.advance(args.seconds, budget=float("inf"))
        for refresh, sent, sizes, deflated, times in pages.values():
            sent.clear()
            start = time.perf_counter()
            refresh()
            times.append(time.perf_counter() - start)
            sizes.append(message_bytes(list(sent)))
            deflated.append(message_bytes(list(sent), DEFLATE))
    print(f"100 x 100 hall, {args.parcels} parcels, cells coloured by {args.colour}, {args.frames} frames "
          f"{args.seconds:g} s apart (t = {live.t:.2f} s); {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}")
    print(f"{'page':32s} {'bytes/frame (median)':>21s} {'max':>10s} {'deflated (median)':>18s} {'max':>10s} "
          f"{'frame s (best)':>15s} {'(median)':>9s}")
    for mode, (_, _, sizes, deflated, times) in pages.items():
        print(f"{mode:32s} {np.median(sizes):21,.0f} {max(sizes):10,d} {np.median(deflated):18,.0f} "
              f"{max(deflated):10,d} {min(times):15.4f} {np.median(times):9.4f}")


if __name__ == "__main__":
    main()
