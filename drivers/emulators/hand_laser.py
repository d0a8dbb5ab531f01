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

    def put_obstacle(self, x_m, y_m=0.0, width_m=0.3):
        """Returns from an object ``width_m`` across (a post, a person: 0.3 m) centred on
        (x_m, y_m) in the vehicle frame: every beam whose direction crosses it (at least the
        one nearest its centre), each at the range to its centre. A real object is hit by
        every beam across it; one lone beam is what the pipeline's ``min_width_m`` takes for a
        stubble tuft's top."""
        dx, dy = x_m - self.geo.mount.x_m, y_m
        rng = float(np.hypot(dx, dy))
        ang = np.degrees(np.arctan2(dy, dx))
        half = np.degrees(np.arctan2(0.5 * width_m, rng))
        step = self.geo.angle_step_deg
        i0 = int(np.ceil((ang - half - self.geo.angle_min_deg) / step - 1e-9))
        i1 = int(np.floor((ang + half - self.geo.angle_min_deg) / step + 1e-9))
        ic = int(round((ang - self.geo.angle_min_deg) / step))
        idx = np.arange(min(i0, ic), max(i1, ic) + 1)
        idx = idx[(idx >= 0) & (idx < self.geo.beams)]
        self.ranges[idx] = rng

    def clear(self):
        self.ranges[:] = np.nan
