"""The live views of the box: the read-only web console (``[console] listen``, on by default at
127.0.0.1:8080) and the Foxglove WebSocket server (``[foxglove] listen``, off by default). Both
are fed by one ``FrameTap`` on the loop (a bounded-rate, newest-only hand-over) and run in their
own threads. Neither can fail the box: a port that is taken is one log line, and the loop runs
on without that view (docs/console.md)."""
from __future__ import annotations

import logging

from appliance.config import parse_listen
from appliance.console.server import Console
from appliance.console.tap import FrameTap, View

log = logging.getLogger("fieldguard.console")

__all__ = ["Console", "ConsoleService", "FrameTap", "View"]


class ConsoleService:
    """What the daemon starts and stops: the tap, the console and the live Foxglove server,
    each only when configured. ``start()`` never raises."""

    def __init__(self, daemon):
        self.d = daemon
        cfg = daemon.cfg
        self.listen = parse_listen(cfg.console.listen, "console.listen", cfg.source)
        self.fox_listen = parse_listen(cfg.foxglove.listen, "foxglove.listen", cfg.source)
        self.tap: FrameTap | None = None
        self.console: Console | None = None
        self.foxglove = None
        self.errors: list[str] = []

    def _tracks(self, res):
        t = getattr(res, "tracks", None)
        if t is None:
            t = self.d.status().get("tracks")
        return t

    def start(self) -> None:
        if self.listen is None and self.fox_listen is None:
            return
        d = self.d
        try:
            self.tap = FrameTap(d.cfg, lambda: d.loop.grid.evidence, self._tracks,
                                rate_hz=d.cfg.console.rate_hz)
            if self.listen is not None:
                c = Console(*self.listen, self.tap, d.status, d.cfg,
                            d.cfg.status.incident_dir,
                            lambda: list(d.recorder.incidents) if d.recorder else [])
                if c.start():
                    self.console = c
                else:
                    self.errors.append(f"console: {c.error}")
            if self.fox_listen is not None:
                from appliance.foxglove_out import LiveFoxglove
                fx = LiveFoxglove(*self.fox_listen, d.cfg)
                if fx.start():
                    self.foxglove = fx
                    self.tap.consumers.append(fx.on_view)
                else:
                    self.errors.append(f"foxglove: {fx.error}")
            if self.console is None and self.foxglove is None:
                self.tap = None
                return
            self.tap.start()
            d.loop.on_cycle.append(self.tap.on_cycle)
        except Exception as exc:          # a view must never stop the box
            log.exception("console: could not start")
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def stop(self) -> None:
        for part in (self.console, self.foxglove, self.tap):
            if part is not None:
                try:
                    part.stop()
                except Exception:
                    log.exception("console: stopping %s", type(part).__name__)

    def info(self) -> dict:
        out = {"console": self.console.info() if self.console else None,
               "foxglove": self.foxglove.info() if self.foxglove else None}
        if self.errors:
            out["errors"] = list(self.errors)
        return out
