"""Calibration and mounting for the hardware drivers.

* ``MOUNT_SCHEMA`` / :func:`mount_from_options`: every hardware driver takes its mounting (where
  the sensor sits on the vehicle) from the same config keys.
* :class:`Backoff`: the reconnect schedule every hardware driver uses.
* Stereo calibration from chessboard images (:func:`calibrate_stereo`), saved and loaded as JSON
  (:func:`save_stereo_calibration`, :func:`load_stereo_calibration`) and turned into rectification
  maps (:class:`Rectifier`). ``tools/calibrate_stereo.py`` is the command-line front end.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hal.errors import ConfigError
from hal.types import Mount, PinholeCalibration, StereoCalibration

MOUNT_SCHEMA = {"mount_x_m": float, "mount_y_m": float, "mount_z_m": float,
                "mount_roll_deg": float, "mount_pitch_deg": float, "mount_yaw_deg": float}


def mount_from_options(opts, default: Mount | None = None) -> Mount:
    """A Mount from ``mount_*`` option keys; keys not given keep ``default``'s values."""
    d = default or Mount()
    return Mount(x_m=float(opts.get("mount_x_m", d.x_m)), y_m=float(opts.get("mount_y_m", d.y_m)),
                 z_m=float(opts.get("mount_z_m", d.z_m)),
                 roll_deg=float(opts.get("mount_roll_deg", d.roll_deg)),
                 pitch_deg=float(opts.get("mount_pitch_deg", d.pitch_deg)),
                 yaw_deg=float(opts.get("mount_yaw_deg", d.yaw_deg)))


class Backoff:
    """Exponential reconnect back-off: first retry after ``first_s``, doubling up to ``max_s``;
    :meth:`reset` after a success. Uses the monotonic wall clock (device I/O happens in wall
    time whatever clock the loop uses)."""

    def __init__(self, first_s: float = 0.1, max_s: float = 2.0):
        self.first_s, self.max_s = float(first_s), float(max_s)
        self.delay_s = 0.0
        self.next_at = 0.0
        self.failures = 0

    def ready(self) -> bool:
        return time.monotonic() >= self.next_at

    def remaining_s(self) -> float:
        return max(0.0, self.next_at - time.monotonic())

    def failed(self) -> float:
        self.failures += 1
        self.delay_s = self.first_s if self.delay_s == 0 else min(self.max_s, self.delay_s * 2)
        self.next_at = time.monotonic() + self.delay_s
        return self.delay_s

    def reset(self) -> None:
        self.delay_s = 0.0
        self.next_at = 0.0
        self.failures = 0
