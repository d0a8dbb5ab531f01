"""A laser driven by hand: the scene in front of the loop set from code (the link tests, the
link benchmark, the soak). Lock-step: it publishes in ``service()``."""
from __future__ import annotations

import numpy as np

from hal import LaserGeometry, LaserScan, Mount, SafetyLaser


def laser_geometry(beams=541):
    return LaserGeometry(-135.0, 0.5, beams, 50.0, Mount(x_m=1.3, z_m=0.7))


class HandLaser(SafetyLaser):
    """Publishes ``ranges`` every service() unless ``silent``; ``age_s`` ages the stamps."""

    def __init__(self, name, clock, timeout_s=0.25):
        super().__init__(name, clock, timeout_s)
        self.geo = laser_geometry()
        self.ranges = np.full(self.geo.beams, np.nan, np.float32)
        self.silent = False
        self.age_s = 0.0
        self.seq = 0
        self.raise_on_service = None

    def service(self, now_ns):
        if self.raise_on_service:
            raise self.raise_on_service
        if self.silent:
            return
        self.seq += 1
        self._publish(LaserScan(stamp_ns=now_ns - int(self.age_s * 1e9), seq=self.seq,
                                ranges_m=self.ranges.copy(), geometry=self.geo))

    def put_obstacle(self, x_m, y_m=0.0):
        """A return from a point (x_m, y_m) in the vehicle frame."""
        ang = np.degrees(np.arctan2(y_m, x_m - self.geo.mount.x_m))
        i = int(round((ang - self.geo.angle_min_deg) / self.geo.angle_step_deg))
        self.ranges[i] = np.hypot(x_m - self.geo.mount.x_m, y_m)

    def clear(self):
        self.ranges[:] = np.nan
