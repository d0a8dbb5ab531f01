"""What a camera pipeline saw where, this frame, for the points of another pipeline.

A planar laser cannot tell the top of a stubble tuft its plane grazes from a post: both are a
return at the plane's height (docs/proving-ground.md, "Tuft tops", "A second scan plane"). The
camera beside it can say whether anything other than the field is there: its novelty or learned
cue raised that place in the image, or its own obstacle points lie there.
``CameraView.look`` answers that for points in the vehicle frame; ``[grid] laser_confirm_by``
(appliance/decision.py) uses it.
"""
from __future__ import annotations

import numpy as np

# the camera evidence a point can be confirmed by: its masks at the point's place in the image
MASK_NAMES = ("novelty", "learned", "depth")
# ... or its obstacle points (the pipeline's Detections.points_xy) near the point
CONFIRM_NAMES = MASK_NAMES + ("points",)


def pixels_of(pts: np.ndarray, fx: float, fy: float, cx: float, cy: float, R: np.ndarray,
              t: np.ndarray, min_depth_m: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, in_front) of vehicle-frame points ``pts`` (N, 3) in a pinhole camera whose
    optical frame is at ``t`` with ``R`` (optical -> vehicle): in front where the point lies
    more than ``min_depth_m`` along the optical axis (u, v there are meaningless elsewhere).
    The one projection the snapshot, the console and the camera view share."""
    p = np.asarray(pts, np.float64).reshape(-1, 3)
    c = (p - np.asarray(t, np.float64).reshape(3)) @ R   # vehicle -> optical: R^T (p - t)
    z = c[:, 2]
    front = z > min_depth_m
    zs = np.where(front, z, 1.0)
    return fx * c[:, 0] / zs + cx, fy * c[:, 1] / zs + cy, front


class CameraView:
    """One frame's masks of one camera (uint8, 255 = raised, all of one size), the pinhole
    ``K`` of that size, the camera's pose on the vehicle (``R`` optical -> vehicle, position
    ``t``), and the range within which it vouches for what it sees."""

    def __init__(self, masks: dict, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                 max_range_m: float, slack_px: int = 0, min_depth_m: float = 0.0,
                 stereo_look=None):
        self.masks = {k: m for k, m in masks.items() if k in MASK_NAMES and m is not None}
        shapes = {m.shape[:2] for m in self.masks.values()}
        if len(shapes) > 1:
            raise ValueError(f"camera view masks of different sizes: {sorted(shapes)}")
        self.shape = shapes.pop() if shapes else None
        self.K = np.asarray(K, np.float64)
        self.R = np.asarray(R, np.float64)
        self.t = np.asarray(t, np.float64).reshape(3)
        self.max_range_m = float(max_range_m)
        self.slack_px = int(slack_px)
        # nearer than this along the optical axis the camera's pipeline cannot range a thing
        # (stereo: the disparity search's near end, min_depth_m)
        self.min_depth_m = float(min_depth_m)
        # the frame's pair kept to look again at a place nearer than that (a StereoLook:
        # appliance/perception/look.py; [grid] hold_blind_look_frames), or None
        self.stereo_look = stereo_look

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, inside) of vehicle-frame points: pixel coordinates in the masks' size and
        whether the point is in front of the camera, within its range and in the image."""
        p = np.asarray(xyz, np.float64).reshape(-1, 3)
        K = self.K
        u, v, front = pixels_of(p, K[0, 0], K[1, 1], K[0, 2], K[1, 2], self.R, self.t, 0.05)
        rng = np.hypot(p[:, 0] - self.t[0], p[:, 1] - self.t[1])
        inside = front & (rng <= self.max_range_m)
        if self.shape is None:
            return u, v, np.zeros(len(p), bool)
        h, w = self.shape
        inside &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        return u, v, inside

    def observes(self, xyz: np.ndarray) -> np.ndarray:
        """Per vehicle-frame point: could this camera's pipeline have put an obstacle point
        there this frame? In its image and range (:meth:`project`) and no nearer along the
        optical axis than ``min_depth_m``. What it does not observe it cannot vouch for
        (``[grid] hold_blind``)."""
        p = np.asarray(xyz, np.float64).reshape(-1, 3)
        _u, _v, inside = self.project(p)
        if self.min_depth_m > 0 and inside.any():
            depth = (p - self.t) @ self.R[:, 2]      # along the optical axis
            inside &= depth >= self.min_depth_m
        return inside

    def look(self, xyz: np.ndarray, names) -> tuple[np.ndarray, np.ndarray]:
        """(inside, raised) per vehicle-frame point: in this camera's view (see ``project``),
        and, of those, whether one of the masks ``names`` is raised at the point's pixel or
        within ``slack_px`` above or below it (a laser's point is where its plane is assumed
        to be; the vehicle's pitch moves the true hit up or down the image)."""
        u, v, inside = self.project(xyz)
        raised = np.zeros(len(u), bool)
        if not inside.any():
            return inside, raised
        h, w = self.shape
        ui = np.clip(u[inside].astype(np.intp), 0, w - 1)
        vi = v[inside].astype(np.intp)
        got = np.zeros(len(ui), bool)
        for name in names:
            m = self.masks.get(name)
            if m is None:
                continue
            for dv in ((0,) if self.slack_px <= 0 else (-self.slack_px, 0, self.slack_px)):
                got |= m[np.clip(vi + dv, 0, h - 1), ui] > 0
        raised[inside] = got
        return inside, raised
