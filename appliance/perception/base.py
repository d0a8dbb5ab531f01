from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from hal.types import DepthFrame, LaserScan, StereoFrame, VehicleState


@dataclass(frozen=True)
class SensorInputs:
    """The newest fresh sample of each sensor for one cycle (None = not available)."""

    stamp_ns: int
    stereo: StereoFrame | None = None
    rgbd: DepthFrame | None = None
    laser: LaserScan | None = None
    vehicle: VehicleState | None = None

    def has(self, sensor: str) -> bool:
        return getattr(self, sensor) is not None


@dataclass
class Detections:
    """Obstacle points in the vehicle frame (x forward, y left), metres."""

    points_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    debug: dict = field(default_factory=dict)     # pictures and figures for snapshot/status

    @staticmethod
    def empty() -> "Detections":
        return Detections()


class Pipeline(ABC):
    """A perception pipeline. ``requires`` names the SensorInputs fields it cannot run without."""

    name: str = "?"
    requires: tuple[str, ...] = ()
    config_class = None

    def __init__(self, options=None):
        self.options = options if options is not None else (
            self.config_class() if self.config_class else None)

    def missing(self, inputs: SensorInputs) -> list[str]:
        return [s for s in self.requires if not inputs.has(s)]

    @abstractmethod
    def process(self, inputs: SensorInputs) -> Detections:
        """Detect obstacles in one cycle's inputs. Raises on bad input (the loop catches it)."""

    def notes(self) -> dict:
        """What the status page should say about this pipeline beyond its name (e.g. an
        optional cue running without its model); {} when there is nothing to say."""
        return {}

    def close(self) -> None:
        """Stop background work (model updates)."""
