"""Registry adapters: build the replay twins (drivers/replay.py) from a DeviceConfig.

All replay devices of a daemon share one RunPlayer over ``shared["replay_path"]``; it runs in
lock-step with the loop's clock (deterministic). ``loop = true`` replays the run again and again.
"""
from __future__ import annotations

from hal.errors import ConfigError

from .replay import (ReplayDepthCamera, ReplayLaser, ReplayStereoCamera, ReplayVehicleLink,
                     RunPlayer)
from .runfolder import RunReader

_SCHEMA = {"loop": bool}


def _player(cfg, clock, shared) -> RunPlayer:
    p = shared.get("replay_player")
    if p is None:
        path = cfg.options.get("run") or shared.get("replay_path")
        if not path:
            raise ConfigError("a replay device needs a run folder: --replay RUN",
                              key=f"devices.{cfg.name}")
        p = RunPlayer(RunReader(path), clock, realtime=False,
                      loop=bool(cfg.options.get("loop", False)))
        shared["replay_player"] = p
    return p


def _factory(base):
    class Adapter(base):
        options_schema = {**_SCHEMA, "run": str}
        default_timeout_s = 0.25

        @classmethod
        def from_config(cls, cfg, clock, shared):
            return cls(_player(cfg, clock, shared), name=cfg.name, timeout_s=cfg.timeout_s)

    Adapter.__name__ = base.__name__ + "Device"
    return Adapter


ReplayStereoDevice = _factory(ReplayStereoCamera)
ReplayDepthDevice = _factory(ReplayDepthCamera)
ReplayLaserDevice = _factory(ReplayLaser)


class ReplayLinkDevice(_factory(ReplayVehicleLink)):
    """Keeps only the last 1000 outputs sent (a long replay must not grow without bound)."""

    def send(self, output):
        ok = super().send(output)
        del self.sent[:-1000]
        return ok
