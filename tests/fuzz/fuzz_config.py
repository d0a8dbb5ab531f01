"""config: the bytes of /etc/fieldguard/fieldguard.toml.

What ``fieldguard config check`` and the daemon's start-up do with the file: ``load_config``
(read, TOML, validate into frozen dataclasses, cross-checks), the refusal of daemon-unsafe
matchers, and construction of every hardware device the file names through the driver
registry (``from_config``: option checks, no I/O; sim and replay devices are left out, they
build a whole simulated field). Refusals must be ConfigError (FieldguardError)."""
from __future__ import annotations

from appliance.config import load_config
from appliance.perception.stereo import check_daemon_matchers
from drivers.registry import create_device, driver_class
from hal.clock import ManualClock
from hal.errors import FieldguardError

from tests.fuzz.common import scratch_dir

_file = None
_HARDWARE = {"mavlink", "can-j1939", "sick-lms1xx", "serial", "log"}
for _kind, _type in (("link", "mavlink"), ("link", "can-j1939"), ("laser", "sick-lms1xx"),
                     ("trigger", "serial"), ("link", "log")):
    driver_class(_kind, _type)      # imported here, so the fuzzer's instrumentation sees them


def one_input(data: bytes) -> None:
    global _file
    if _file is None:
        _file = scratch_dir("config") / "fieldguard.toml"
    _file.write_bytes(data)
    try:
        cfg = load_config(_file)
        check_daemon_matchers(cfg)
    except FieldguardError:
        return
    for dc in cfg.devices:
        if dc.type not in _HARDWARE:
            continue
        try:
            create_device(dc, ManualClock(0), {"rate_hz": cfg.loop.rate_hz})
        except FieldguardError:
            pass
