"""The planar-laser pipeline: the stereo paper's baseline.

Every return in range becomes an obstacle point in the vehicle frame, with the scan plane
assumed parallel to the ground (as the paper mounted its SICK LMS151 at 0.7 m). On bouncing
ground over stubble that assumption fails and stubble returns become obstacles: the paper's
finding, and why this pipeline is a baseline. ``use_attitude`` (our addition) projects each hit
with the mount and the vehicle's roll and pitch and drops hits lower than ``min_height_m``.
``min_width_m`` (our addition) drops what the scan sees narrower than that: the returns are cut
into segments of neighbouring beams at about the same range, and a segment's width is the
distance across its ends plus one beam's footprint (docs/proving-ground.md, "Tuft tops").
"""
from __future__ import annotations

import numpy as np

from dataclasses import dataclass

from appliance.schema import _f
from hal.types import rotation_rpy

from .base import Detections, Pipeline, SensorInputs
from .candidates import cluster_candidates


@dataclass(frozen=True)
class LaserPipelineConfig:
    min_range_m: float = _f(0.3, lo=0.0)
    max_range_m: float = _f(30.0, lo=0.1)
    use_attitude: bool = _f(False, doc="project hits with the vehicle's roll/pitch (not in the paper)")
    min_height_m: float = _f(-100.0, doc="with use_attitude: drop hits lower than this")
    min_width_m: float = _f(0.05, lo=0.0, hi=2.0,
                            doc="drop returns whose segment (neighbouring beams at about the "
                                "same range) is narrower than this across: the tops of stubble "
                                "tufts the plane grazes; 0 = keep every return (the paper)")
    ground_min_m: float = _f(0.0, lo=0.0, hi=2.0,
                             doc="with a camera pipeline's ground this cycle (stereo-novelty's "
                                 "ground_for_laser): drop returns where the scan plane runs "
                                 "lower than this above that ground (a tuft's top where the "
                                 "ground ahead rises or the vehicle pitches); 0 = off. Applied "
                                 "where the pipelines meet (appliance/decision.py)")
    segment_jump_m: float = _f(0.15, lo=0.01, hi=5.0,
                               doc="min_width_m: neighbouring beams whose ranges differ by more "
                                   "than this (or 3 beam footprints, if larger) start a new "
                                   "segment")


def segment_widths(r: np.ndarray, ok: np.ndarray, step_rad: float, jump_m: float) -> np.ndarray:
    """Per beam, the width across of the segment it belongs to (0 where ``ok`` is false).

    A segment is a run of neighbouring ``ok`` beams whose ranges differ by less than
    max(jump_m, 3 x r x step_rad) from one beam to the next; its width is the chord from its
    first to its last beam plus one beam's footprint at the segment's mean range."""
    n = len(r)
    out = np.zeros(n, dtype=np.float64)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return out
    ri = r[idx]
    tol = np.maximum(jump_m, 3.0 * np.minimum(ri[1:], ri[:-1]) * step_rad)
    brk = (np.diff(idx) != 1) | (np.abs(np.diff(ri)) >= tol)
    starts = np.concatenate([[0], np.flatnonzero(brk) + 1])
    last = np.concatenate([starts[1:], [len(idx)]]) - 1
    r0, r1 = ri[starts], ri[last]
    dth = (idx[last] - idx[starts]) * step_rad
    chord = np.sqrt(np.maximum(r0 * r0 + r1 * r1 - 2.0 * r0 * r1 * np.cos(dth), 0.0))
    mean_r = np.add.reduceat(ri, starts) / (last - starts + 1)
    out[idx] = np.repeat(chord + mean_r * step_rad, last - starts + 1)
    return out


def plane_points(local: np.ndarray, mount) -> tuple[np.ndarray, np.ndarray]:
    """The paper's assumption for scanner-frame returns ``local`` (N, 3; z = 0): (their x, y in
    the vehicle frame with the mount's position and yaw only, the scan plane parallel to the
    ground; where the plane is in the vehicle frame, the height the mount's pitch and roll give
    it at each return -- what a camera's ground or view is measured against)."""
    c, s = np.cos(np.radians(mount.yaw_deg)), np.sin(np.radians(mount.yaw_deg))
    xy = np.stack([mount.x_m + c * local[:, 0] - s * local[:, 1],
                   mount.y_m + s * local[:, 0] + c * local[:, 1]], axis=1)
    return xy, (local @ mount.rotation().T)[:, 2] + mount.z_m


class LaserPipeline(Pipeline):
    name = "laser"
    requires = ("laser",)
    config_class = LaserPipelineConfig

    def process(self, inputs: SensorInputs) -> Detections:
        scan = inputs.laser
        o: LaserPipelineConfig = self.options
        r = np.asarray(scan.ranges_m, dtype=np.float64)
        geo = scan.geometry
        if r.shape != (geo.beams,):
            raise ValueError(f"laser scan has {r.shape} ranges, geometry says {geo.beams} beams")
        ang = geo.angles_rad()
        ok = np.isfinite(r) & (r >= o.min_range_m) & (r <= min(o.max_range_m, geo.range_max_m))
        n_in_range = int(ok.sum())
        if o.min_width_m > 0:
            ok &= segment_widths(r, ok, abs(np.radians(geo.angle_step_deg)),
                                 o.segment_jump_m) >= o.min_width_m
        r, ang = r[ok], ang[ok]
        local = np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros_like(r)], axis=1)
        m = geo.mount
        if o.use_attitude and inputs.vehicle is not None:
            v = inputs.vehicle
            rot = rotation_rpy(v.roll_rad, v.pitch_rad, 0.0) @ m.rotation()
            pts = local @ rot.T + m.position
            keep = pts[:, 2] >= o.min_height_m
            pts = pts[keep]
            z = pts[:, 2]
            plane_z = None                  # a gravity frame, not the vehicle's
        else:
            # the paper's assumption: the scan plane is parallel to the ground (mount yaw only);
            # where the plane is in the vehicle frame (a mount tilted in pitch or roll: not at
            # the mount's height everywhere), for a camera's ground or view to be measured against
            pts, plane_z = plane_points(local, m)
            z = np.full(len(pts), m.z_m)
        # a planar scan sees one height (the hit's, or the mount's): no contact claim beyond it
        cands = cluster_candidates(pts[:, :2], z, None, base_sources=("laser",),
                                   pipeline=self.name, min_points=2, contact_m=np.inf)
        return Detections(points_xy=pts[:, :2].astype(np.float32), candidates=cands,
                          points_z=None if plane_z is None else plane_z.astype(np.float32),
                          debug={"returns": n_in_range, "kept": int(ok.sum()),
                                 "beams": geo.beams,
                                 "candidates": len(cands)})
