"""The driver registry: a config ``type`` picks the backend class for a device kind.

Backends are imported lazily (as python-can does), so a box without Aravis or libfreenect
installed still starts with the drivers it has. Every entry is a factory
``f(cfg: DeviceConfig, clock: Clock, shared: dict) -> hal.Device``; the class behind it
declares ``options_schema`` (key -> type) for config validation.

``shared`` carries resources several devices use together (the simulated field, the replay
player); the daemon fills in ``shared["sim_config"]``, ``shared["replay_path"]``.
"""
from __future__ import annotations

import importlib

# (kind, type) -> "module:attribute"; the attribute is a class with from_config() and
# options_schema.
_REGISTRY: dict[tuple[str, str], str] = {
    ("laser", "sim"): "drivers.sim.devices:SimLaser",
    ("stereo", "sim"): "drivers.sim.devices:SimStereoCamera",
    ("rgbd", "sim"): "drivers.sim.devices:SimDepthCamera",
    ("link", "sim"): "drivers.sim.devices:SimVehicleLink",
    ("laser", "replay"): "drivers.replay_devices:ReplayLaserDevice",
    ("stereo", "replay"): "drivers.replay_devices:ReplayStereoDevice",
    ("rgbd", "replay"): "drivers.replay_devices:ReplayDepthDevice",
    ("link", "replay"): "drivers.replay_devices:ReplayLinkDevice",
    ("link", "log"): "drivers.loglink:LogVehicleLink",
    ("link", "mavlink"): "drivers.mavlink_link:MavlinkVehicleLink",
    ("link", "can-j1939"): "drivers.can_link:CanJ1939VehicleLink",
    ("laser", "sick-lms1xx"): "drivers.sick_lms1xx:SickLms1xxLaser",
    ("trigger", "serial"): "drivers.strobe_serial:StrobeSerialTrigger",
    ("stereo", "aravis"): "drivers.aravis_stereo:AravisStereoCamera",
    ("rgbd", "freenect"): "drivers.freenect_rgbd:FreenectDepthCamera",
}


def register(kind: str, type_: str, target: str) -> None:
    """Add a backend (for plug-ins and tests)."""
    _REGISTRY[(kind, type_)] = target


def known_types(kind: str) -> list[str]:
    return sorted(t for (k, t) in _REGISTRY if k == kind)


def driver_class(kind: str, type_: str):
    """The backend class for (kind, type). KeyError if unknown; ImportError propagates with the
    module's own message (a missing optional library)."""
    target = _REGISTRY[(kind, type_)]
    mod, _, attr = target.partition(":")
    return getattr(importlib.import_module(mod), attr)


def create_device(cfg, clock, shared: dict):
    cls = driver_class(cfg.kind, cfg.type)
    return cls.from_config(cfg, clock, shared)
