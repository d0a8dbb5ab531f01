"""Pipeline ``stereo-novelty``: the stereo paper's system (Ross et al., seed 000).

Per frame: stabilise (attitude or visual odometry, high-pass), descriptors of 32x32 cells in the
stabilised image, weighted Parzen density against the learnt model, novel = density < rho,
islanding and dilation, the mask back into the camera frame, dense stereo only in the novel
regions (plus the matcher's margin), reprojection, height band -> obstacle points. The frame's
cells, minus those near the obstacles just found, go to the background model update every
``update_every_frames`` frames (never updated inside :meth:`process`).

"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.config import _f

from .base import Detections, Pipeline, SensorInputs
from .novelty import NoveltyDetector, mask_to_camera, obstacle_cells
from .stereo import (StereoConfig, StereoPipeline, dedupe_cells, disparity_regions,
                     height_band, mask_boxes, points_from_disparity)

# the paper gives the 32x32 cells, the 40-frame update and the 3-sigma search; the other
# defaults were chosen on a tuning run (stubble-empty, seed 1), see docs/stereo-novelty.md
DEFAULT_SCALE = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)


@dataclass(frozen=True)
class StereoNoveltyConfig(StereoConfig):
    cell_px: int = _f(0, lo=0, hi=256, doc="cell size in px; 0 = image width / 40 (the paper's "
                                         "32 px, 40x32 cells at 1280x1024; 16 px at 640x512)")
    descriptor_scale: tuple = _f(DEFAULT_SCALE, doc="s of eq. 5: 8 factors for "
                                 "[Lmu amu bmu Lsd asd bsd u v]")
    sigma: float = _f(0.05, lo=1e-4, hi=10.0, doc="kernel width in scaled descriptor units")
    rho: float = _f(1.0, lo=1e-30, hi=1e30, doc="novel when density < rho (eq. 3 units)")
    forget: float = _f(0.1, lo=1e-4, hi=0.99, doc="lambda of eqs. 6, 7 (per update)")
    update_every_frames: int = _f(40, lo=1, hi=10000, doc="model update period (paper: 40)")
    weight_floor: float = _f(0.005, lo=0.0, hi=1.0,
                             doc="samples whose weight decays below this are dropped")
    max_neighbours: int = _f(64, lo=1, hi=4096, doc="neighbours summed per query (<= 3 sigma)")
    cutoff_sigmas: float = _f(3.0, lo=1.0, hi=10.0, doc="neighbour search radius (paper: 3)")
    island_min_neighbours: int = _f(1, lo=0, hi=8, doc="novel 8-neighbours a novel cell needs")
    dilate_cells: int = _f(1, lo=0, hi=10, doc="dilation of the novelty mask, in cells")
    obstacle_margin_px: float = _f(64.0, lo=0.0, hi=2000.0,
                                   doc="cells this close to a detected obstacle are never learnt")
    alpha: float = _f(0.1, lo=0.0, hi=1.0, doc="stabilisation high-pass: (1-alpha) per frame")
    stabilise: str = _f("auto", choices=("auto", "attitude", "vo", "off"),
                        doc="auto = vehicle attitude when present, else visual odometry")


class StereoNoveltyPipeline(Pipeline):
    name = "stereo-novelty"
    requires = ("stereo",)
    config_class = StereoNoveltyConfig

    def __init__(self, options=None, background: bool = True):
        super().__init__(options)
        self.novelty = NoveltyDetector(self.options, background=background)
        self._stereo = StereoPipeline(self.options)
        self.last = None                       # (NoveltyResult, camera mask) for tools/tests

    def process(self, inputs: SensorInputs) -> Detections:
        fr = inputs.stereo
        o: StereoNoveltyConfig = self.options
        cam = fr.calib.camera
        K = cam.matrix()
        M = fr.calib.mount.camera_to_vehicle()
        H, W = fr.left.shape[:2]
        t0 = time.perf_counter()
        res = self.novelty.detect(fr.left, K, M, inputs.vehicle)
        t1 = time.perf_counter()
        cam_mask = mask_to_camera(res.mask, res.affine, (W, H), res.cell_px)
        matcher = self._stereo.matcher_for(fr.calib)
        boxes = mask_boxes(cam_mask, 0)
        disp, work = disparity_regions(matcher, fr.left, fr.right, boxes)
        t2 = time.perf_counter()
        pts, px = points_from_disparity(disp, fr.calib, cam_mask, o.point_stride,
                                        inputs.vehicle, o.use_attitude)
        keep = height_band(pts, o.band_min_m, o.band_max_m, o.max_range_m)
        xy = dedupe_cells(pts[keep, :2])
        t3 = time.perf_counter()
        # obstacle-mask feedback: cells near what was just detected are never learnt
        exclude = obstacle_cells(px[keep], res.mask.shape, res.cell_px, o.obstacle_margin_px)
        self.novelty.learn(res, exclude)
        t4 = time.perf_counter()
        self.last = (res, cam_mask, exclude)
        rows, cols = res.mask.shape
        return Detections(points_xy=xy, debug={
            "novel_fraction": float(res.mask.mean()),
            "novel_cells_raw": int(res.raw.sum()),
            "model_samples": self.novelty.model.size,
            "model_updates": self.novelty.model.updates,
            "stereo_px_fraction": work / float(H * W),
            "boxes": len(boxes),
            "stabiliser": self.novelty.stabiliser.source,
            "grid": (rows, cols), "cell_px": res.cell_px,
            "ms": {"novelty": 1e3 * (t1 - t0), "stereo": 1e3 * (t2 - t1),
                   "points": 1e3 * (t3 - t2), "learn": 1e3 * (t4 - t3)}})

    def close(self) -> None:
        self.novelty.close()
