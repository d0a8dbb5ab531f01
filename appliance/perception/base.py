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


@dataclass(frozen=True)
class Candidate:
    """One obstacle candidate of one frame, in the vehicle frame (metres): a cluster of points
    that stands above the ground, as a front end saw it. The tracker associates candidates
    across frames; the evidence model weighs them by ``sources``.

    ``sources`` names the cues that saw it: "geometry" (height above ground from stereo or
    depth), "novelty", "cue" (the learned cue), "colour" (RGB-D colour class), "texture",
    "laser". ``confidence`` is in [0, 1]: how sure the front end is that this is not noise
    (disparity consistency, point support), not whether it is an obstacle."""

    x_m: float                    # footprint centre
    y_m: float
    length_m: float               # footprint extent along x
    width_m: float                # footprint extent along y
    height_m: float               # top above the local ground
    points: int                   # supporting 3-D points (or cells for a cell cluster)
    confidence: float
    sources: tuple[str, ...]
    ground_contact: bool = True   # the cluster reaches down to the ground
    pipeline: str = "?"           # which pipeline produced it


@dataclass
class Detections:
    """Obstacle points in the vehicle frame (x forward, y left), metres; optionally the same
    evidence grouped into obstacle candidates (empty when a front end does not cluster: the
    tracker then clusters the points itself)."""

    points_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    debug: dict = field(default_factory=dict)     # pictures and figures for snapshot/status
    candidates: tuple[Candidate, ...] = ()
    # the points' heights in the vehicle frame, where the pipeline knows them (the laser: its
    # scan plane's height at each return) ...
    points_z: np.ndarray | None = None
    # ... and the ground this pipeline measured this frame (vehicle frame; an object with
    # ``z(x, y)`` and ``source``, perception/ground.py), for the other pipelines' points
    # (the laser's ``ground_min_m``, appliance/decision.py)
    ground: object = None
    # ... and what this camera saw where, for another pipeline's points this frame (an object
    # with ``look(xyz, names)``: appliance/perception/view.py; the laser's confirmation by a
    # camera, ``[grid] laser_confirm_by`` in appliance/decision.py)
    view: object = None

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
