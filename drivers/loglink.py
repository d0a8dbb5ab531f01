"""A vehicle link that only writes what it would send to the log: for bench tests with no
vehicle. It reports a fixed assumed speed (``assume_speed_mps``) as the vehicle's state, so the
stop zone can be checked on the bench; never use it on a vehicle."""
from __future__ import annotations

import logging

from hal.devices import VehicleLink
from hal.types import GateOutput, VehicleState

log = logging.getLogger("fieldguard.link.log")


class LogVehicleLink(VehicleLink):
    options_schema = {"assume_speed_mps": float}
    default_timeout_s = 0.5

    def __init__(self, name, clock, timeout_s=0.5, assume_speed_mps=0.0):
        super().__init__(name, clock, timeout_s)
        self.assume_speed_mps = assume_speed_mps
        self._last_state = None
        self.count = 0

    @classmethod
    def from_config(cls, cfg, clock, shared):
        return cls(cfg.name, clock, cfg.timeout_s, cfg.options.get("assume_speed_mps", 0.0))

    def service(self, now_ns: int) -> None:
        self._publish(VehicleState(stamp_ns=now_ns, seq=self.count,
                                   speed_mps=self.assume_speed_mps))

    def send(self, output: GateOutput) -> bool:
        self.count += 1
        if output.state is not self._last_state:
            log.info("link %s: %s (%s)", self.name, output.state.value, output.reason)
            self._last_state = output.state
        return True

    def peers(self):
        return [{"peer": "log only (bench)", "messages": self.count}]
