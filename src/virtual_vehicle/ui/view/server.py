"""The viewer's server (:class:`Viewer`): a Bokeh server on 127.0.0.1 (unless told otherwise) at a free port, one
signed session id as the access token, a live run (or a recorded one replayed) stepped on the server's own loop.

Why Bokeh: its wheel ships BokehJS (nothing is fetched from the internet at run time), it streams and patches
ColumnDataSources over one websocket in binary, it runs on Tornado, which Dask's distributed scheduler already
brings, and its signed session ids are the access token (Jupyter-style): a request without a valid one is refused
with 403.
"""

from __future__ import annotations

import math
import secrets
import socket
import time
from typing import TYPE_CHECKING

from virtual_vehicle.run.results import RunResult
from virtual_vehicle.ui.view.live import LiveRun

if TYPE_CHECKING:
    from virtual_vehicle.ui.view.replay import Replay

DEFLATE = 1
"""zlib level of the websocket's per-message compression (1: fastest; a frame's patches shrink about tenfold)."""
LOOPBACK = ("127.0.0.1", "localhost", "::1")
"""Addresses that serve the page to this machine alone."""

def _free_port(host: str) -> int:
    """A port free on ``host`` now (the server binds it right after)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class Viewer:
    """The page's server: a Bokeh server on ``host`` (default 127.0.0.1) at a free port, one signed session id as
    the access token, and the run stepped on the server's own loop (so the page's callbacks and the ticks never
    run at once). ``url`` is the address to open, token included; ``on_done`` is called once with the result when
    the run reaches its end. ``live``: a :class:`LiveRun` (the live page) or a
    :class:`~virtual_vehicle.ui.view.replay.Replay` (the replay page, whose time play moves on)."""

    def __init__(self, live: LiveRun | Replay, host: str = "127.0.0.1", port: int | None = None, on_done=None,
                 frame: float = 0.1):
        from bokeh.server.server import Server
        from bokeh.util.token import generate_session_id
        from tornado.ioloop import IOLoop, PeriodicCallback

        from virtual_vehicle.ui.view import page, replay

        self.live = live
        self.page = replay.build if isinstance(live, replay.Replay) else page.build
        self.playing = True
        self.speed = 1.0  # simulated s per real s; math.inf: as fast as it runs
        self.on_done = on_done
        self.result: RunResult | None = None
        self.message = ""
        self.frame = frame
        self._key = secrets.token_urlsafe(32)
        self.token = generate_session_id(secret_key=self._key.encode(), signed=True)
        self.loop = IOLoop.current()
        for attempt in range(5):
            self.port = _free_port(host) if port is None else port
            try:
                # on loopback the page's own origins only; exposed, the name others reach it by is not known
                # here, so any origin (the signed session token still guards every connection)
                name = f"[{host}]" if ":" in host else host  # an IPv6 address is bracketed in an origin
                origins = ([f"{name}:{self.port}", f"localhost:{self.port}"] if host in LOOPBACK else ["*"])
                self.server = Server({"/": self._page}, io_loop=self.loop, address=host, port=self.port,
                                     allow_websocket_origin=origins,
                                     sign_sessions=True, secret_key=self._key, generate_session_ids=False,
                                     session_token_expiration=24 * 3600,
                                     # frames deflated on the wire (the image patches are runs of equal pixels):
                                     # the fastest level takes most of it
                                     websocket_compression_level=DEFLATE, websocket_compression_mem_level=8)
                break
            except OSError:
                if port is not None or attempt == 4:
                    raise
        self.host = host
        self._last = time.perf_counter()
        self._stepper = PeriodicCallback(self._step, 1000 * frame / 2)

    @property
    def url(self) -> str:
        """The page's address with its access token."""
        shown = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{shown}:{self.port}/?bokeh-session-id={self.token}"

    def start(self) -> None:
        """Start serving and stepping (on the current IOLoop; run it with ``self.loop.start()``)."""
        self.server.start()
        self._stepper.start()

    def stop(self) -> None:
        """Stop stepping and serving."""
        self._stepper.stop()
        self.server.stop()

    def _step(self) -> None:
        now = time.perf_counter()
        elapsed, self._last = now - self._last, now
        if self.playing and not self.live.done:
            budget = 0.6 * self.frame
            self.live.advance(self.speed * min(elapsed, self.frame) if math.isfinite(self.speed) else math.inf,
                              budget)
        self._check_done()

    def _check_done(self) -> None:
        if isinstance(self.live, LiveRun) and self.live.done and self.result is None:
            self.result = self.live.result()
            if self.on_done is not None:
                self.message = self.on_done(self.result) or ""

    def step_once(self) -> None:
        """One tick, paused."""
        self.playing = False
        self.live.tick()
        self._check_done()

    def _page(self, doc) -> None:
        self.page(doc, self)

