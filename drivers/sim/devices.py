"""HAL devices backed by the simulated field, in lock-step with the loop's clock.

All sim devices of one daemon share one :class:`SimHub` (one world, one vehicle). The first
device serviced at a new clock time steps the vehicle (with the last command the sim link
received: the simulated vehicle brakes when the box says STOP) and renders every sensor; each
device then publishes its part. Faults can be injected the way they happen in a field:
``unplugged`` (no data at all), ``latency_s`` (stamps older than the clock).
"""
from __future__ import annotations

import threading

from hal.clock import Clock
from hal.devices import DepthCamera, SafetyLaser, StereoCamera, VehicleLink
from hal.types import GateOutput, GateState, StereoCalibration


class SimHub:
    def __init__(self, scene: str, seed: int, sensors: tuple[str, ...], stereo_scale: float,
                 rate_hz: float = 10.0, path: str = "route", mission_wp_radius_m: float = 2.0):
        from drivers.sim.field import SimField
        self.field = SimField(scene=scene, seed=seed, sensors=tuple(sensors),
                              stereo_scale=stereo_scale, rate_hz=rate_hz, path=path,
                              mission_wp_radius_m=mission_wp_radius_m)
        self.command: GateState | None = GateState.STOP
        self._last_ns: int | None = None
        self._sample = None
        self._seq = 0
        self._lock = threading.Lock()

    def at(self, now_ns: int):
        with self._lock:
            if self._last_ns == now_ns and self._sample is not None:
                return self._sample
            if self._last_ns is not None:
                dt = (now_ns - self._last_ns) / 1e9
                if dt > 0:
                    self.field.step(dt, self.command)
            self._last_ns = now_ns
            self._seq += 1
            self._sample = self.field.render(now_ns, self._seq)
            return self._sample


def hub_from_shared(shared: dict) -> SimHub:
    hub = shared.get("sim_hub")
    if hub is None:
        sc = shared["sim_config"]
        sensors = tuple(shared.get("sim_sensors", ("laser",)))
        hub = SimHub(sc.scene, sc.seed, sensors, sc.stereo_scale, shared.get("rate_hz", 10.0),
                     path=sc.path, mission_wp_radius_m=sc.mission_wp_radius_m)
        shared["sim_hub"] = hub
    return hub


class _SimMixin:
    options_schema = {"latency_s": float}
    default_timeout_s = 0.25
    part = ""

    def _init_sim(self, hub: SimHub, latency_s: float = 0.0):
        self.hub = hub
        self.latency_ns = int(latency_s * 1e9)
        self.unplugged = False

    def service(self, now_ns: int) -> None:
        if self.unplugged:
            return
        sample = self.hub.at(now_ns)
        item = getattr(sample, self.part)
        if item is None:
            return
        if self.latency_ns:
            item = type(item)(**{**item.__dict__, "stamp_ns": item.stamp_ns - self.latency_ns})
        self._publish(item)

    @classmethod
    def from_config(cls, cfg, clock: Clock, shared: dict):
        hub = hub_from_shared(shared)
        return cls(cfg.name, clock, hub, timeout_s=cfg.timeout_s,
                   latency_s=cfg.options.get("latency_s", 0.0))


class SimLaser(_SimMixin, SafetyLaser):
    part = "laser"

    def __init__(self, name, clock, hub, timeout_s=0.25, latency_s=0.0):
        SafetyLaser.__init__(self, name, clock, timeout_s)
        self._init_sim(hub, latency_s)


class SimDepthCamera(_SimMixin, DepthCamera):
    part = "rgbd"

    def __init__(self, name, clock, hub, timeout_s=0.25, latency_s=0.0):
        DepthCamera.__init__(self, name, clock, timeout_s)
        self._init_sim(hub, latency_s)


class SimStereoCamera(_SimMixin, StereoCamera):
    part = "stereo"

    def __init__(self, name, clock, hub, timeout_s=0.25, latency_s=0.0):
        StereoCamera.__init__(self, name, clock, timeout_s)
        self._init_sim(hub, latency_s)

    @property
    def calibration(self) -> StereoCalibration:
        return self.hub.field.stereo_calibration


class SimVehicleLink(_SimMixin, VehicleLink):
    """The link to the simulated vehicle: what it is sent, it obeys (brakes on STOP)."""

    part = "vehicle"
    options_schema = {"latency_s": float, "fail_sends": bool}

    def __init__(self, name, clock, hub, timeout_s=0.25, latency_s=0.0, fail_sends=False):
        VehicleLink.__init__(self, name, clock, timeout_s)
        self._init_sim(hub, latency_s)
        self.fail_sends = fail_sends
        self.sent: list[GateOutput] = []
        self.keep_sent = 0          # >0: keep that many outputs (tests)

    @classmethod
    def from_config(cls, cfg, clock, shared):
        hub = hub_from_shared(shared)
        return cls(cfg.name, clock, hub, timeout_s=cfg.timeout_s,
                   latency_s=cfg.options.get("latency_s", 0.0),
                   fail_sends=cfg.options.get("fail_sends", False))

    def send(self, output: GateOutput) -> bool:
        if self.fail_sends or self.unplugged:
            return False
        self.hub.command = output.state
        if self.keep_sent:
            self.sent.append(output)
            del self.sent[:-self.keep_sent]
        return True

    def peers(self):
        return [{"peer": "simulated vehicle", **self.hub.field.stats()}]
