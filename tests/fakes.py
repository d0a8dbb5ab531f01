"""Test devices driven by hand (the loop's logic, not a device, is under test where these are
used). Real devices at the wire have their own tests."""
from __future__ import annotations

import threading

from appliance.perception.base import Detections, Pipeline
from drivers.emulators.hand_laser import HandLaser, laser_geometry  # noqa: F401 (tests use it)
from hal import GateOutput, VehicleLink, VehicleState


def geometry(beams=541):
    return laser_geometry(beams)


class HandLink(VehicleLink):
    def __init__(self, name, clock, timeout_s=0.25):
        super().__init__(name, clock, timeout_s)
        self.sent: list[GateOutput] = []
        self.speed = 0.0
        self.fail = False
        self.silent = False

    def service(self, now_ns):
        if not self.silent:
            self._publish(VehicleState(stamp_ns=now_ns, seq=len(self.sent),
                                       speed_mps=self.speed))

    def send(self, output):
        if self.fail:
            return False
        self.sent.append(output)
        return True


class HangPipeline(Pipeline):
    """Blocks inside process() while ``hang`` is set: a hung loop."""

    name = "hang-test"
    requires = ("laser",)
    release = threading.Event()
    hang = threading.Event()

    def process(self, inputs):
        if self.hang.is_set():
            self.release.wait(10)
        return Detections()
