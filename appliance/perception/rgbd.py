"""The RGB-D pipeline (``rgbd``): the greenhouse paper (Nissimov, Goldberger, Alchanatis 2015).

Per frame, as the paper's Fig. 1:
1. slope of vertically neighbouring depth pixels (eq. 4) with the camera's real intrinsics and
   mount pitch; depth outside [min_range_m, max_range_m] ignored; slope > 40 deg = suspected
   obstacle pixel; 3x3 dilation (rgbd_slope);
2. suspected pixels get a colour class: nearest Mahalanobis distance (eq. 5) in the configured
   colour space, under a threshold, else undefined (rgbd_colour);
3. texture: LBP codes (eq. 6), 256-bin histograms over 20x20 windows (eq. 7), chi-square (eq. 8)
   under 0.5, else undefined -- by default only on frames where colour already found an obstacle
   (the paper), ``texture = "always"`` on every frame, ``"off"`` never (rgbd_texture);
4. a connected group of >= 30 suspected pixels, above and adjacent to surface pixels, of no
   traversable class, is an obstacle; colour OR texture (rgbd_decision).
Obstacle pixels with a valid depth go to 3-D (optical frame), through the mount into the vehicle
frame, and out as (x, y) points for the grid.

The defaults are the measured best on the simulated greenhouse (docs/rgbd.md), not the paper:
the surface an obstacle stands on is low ground (not any level patch: bush tops are level too),
ground-class pixels at ground height are traversable, texture judges only the pixels colour
called traversable and runs on every frame, a group must rise ``min_height_m`` above the
ground (and so must each 3-D cluster of its points: ``candidate_min_height``), and depth holes standing on the ground (shiny surfaces) are obstacles. ``PAPER_RULE``
holds the options of the paper's own decision; the decision itself is one function
(rgbd_decision.decide) with the cues as inputs.

The class model is a file (``model``), read once at construction by appliance.rgbd_model
(perception itself does no I/O); tests and tools may pass a model object instead.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.schema import _f

from .base import Detections, Pipeline, SensorInputs
from .candidates import cluster_candidates, low_clusters
from .cue import CueOptions, LearnedCue
from .rgbd_classes import RgbdClassModel
from .rgbd_colour import COLOUR_SPACES, ColourClassifier, colour_features
from .rgbd_decision import (NOT_CLASSIFIED, UNDEFINED, Rule, decide, not_traversable,
                            obstacle_groups, touching_ground)
from .rgbd_slope import height_map, slope_map, steep_map, suspected_from
from .rgbd_texture import classify_histograms, lbp_codes, to_grey, window_histograms, window_index
from .view import CameraView

log = logging.getLogger("fieldguard.perception.rgbd")

# the colour-model check: the share's running mean weighs each new frame by this, and a model
# found not to apply must be back above its minimum share by this margin before it is used again
COLOUR_CHECK_ALPHA = 0.3
COLOUR_CHECK_HYSTERESIS = 0.1
COLOUR_CHECK_MIN_PIXELS = 100      # sampled ground-height pixels a frame needs to count
COLOUR_CHECK_STRIDE = 4            # every 4th row and column of the frame is sampled
GEOMETRY_RISE_MEMORY = 1000        # geometry alone: the rises of the last 1000 groups seen


@dataclass(frozen=True)
class RgbdPipelineConfig(CueOptions):
    model: str = _f("", doc="class model file from `fieldguard train-classes`; "
                            "empty = the shipped greenhouse model (package data: "
                            "appliance/models/greenhouse-classes.npz)")
    colour_space: str = _f("rgb", choices=COLOUR_SPACES)
    min_range_m: float = _f(0.5, lo=0.0, hi=20.0, doc="depth below this is ignored")
    max_range_m: float = _f(5.0, lo=0.1, hi=50.0, doc="depth above this is ignored")
    camera_view: bool = _f(False, doc="hand the decision what this camera observes this frame "
                                      "(Detections.view: its image, the depth range used, its "
                                      "obstacle mask as the 'depth' cue): [grid] hold_blind then "
                                      "holds what the box stopped for once it is nearer than "
                                      "the sensor ranges or under its view, and [grid] "
                                      "laser_confirm_by can use it; false = no view (as before "
                                      "the thirty-fourth session: the greenhouse holds nothing)")
    slope_threshold_deg: float = _f(40.0, lo=1.0, hi=89.0)
    slope_step_px: int = _f(4, lo=1, hi=16, doc="rows between the two pixels of eq. 4 (paper: 1)")
    depth_median_px: int = _f(3, choices=(0, 3, 5), doc="median filter of the depth before "
                                                          "the slope (paper: 0 = none)")
    dilate_px: int = _f(3, lo=1, hi=15, doc="square dilation of the suspected map (3 = paper)")
    morphology: str = _f("dilate", choices=("dilate", "close"),
                         doc="dilate (paper) or close the suspected map")
    colour_threshold: float = _f(4.5, lo=0.1, hi=100.0, doc="Mahalanobis distance for a class "
                                                            "(the paper gives no value)")
    colour_lut_bits: int = _f(8, choices=(0, 6, 7, 8),
                              doc="classify colours through a lookup table of this many bits per "
                                  "channel (8 = exact, 16 MB, built once at start; 0 = "
                                  "Mahalanobis per pixel)")
    texture: str = _f("always", choices=("after-colour", "always", "off"),
                      doc="when the LBP texture classifier runs (paper: after-colour, only on "
                          "frames where colour found an obstacle)")
    texture_scope: str = _f("traversable-colour", choices=("suspected", "traversable-colour"),
                            doc="pixels texture may turn into obstacles: every suspected one "
                                "(paper) or only those colour called traversable")
    texture_undefined: bool = _f(False, doc="an undefined texture window is obstacle evidence "
                                            "(paper: true)")
    texture_window_px: int = _f(20, lo=3, hi=100)
    texture_threshold: float = _f(0.5, lo=0.0, hi=2.0, doc="chi-square distance for a class")
    min_pixels: int = _f(30, lo=1, hi=100000, doc="smallest obstacle group")
    texture_min_pixels: int = _f(401, lo=0, hi=100000,
                                 doc="smallest texture group (0 = min_pixels, the paper); "
                                     "texture decides per texture_window_px window, so more "
                                     "than a window's area (20x20 = 400) means at least two "
                                     "windows agree: one window's LBP verdict on a bush edge "
                                     "is not an obstacle")
    contact_px: int = _f(1, lo=1, hi=50, doc="surface within this many rows below a group "
                                             "(1 = the next row, the paper)")
    texture_contact_px: int = _f(20, lo=0, hi=100, doc="texture groups may touch the surface "
                                                       "this far below (0 = contact_px, paper)")
    ground_max_height_m: float = _f(0.25, lo=0.0, hi=5.0,
                                    doc="only surface lower than this counts as the ground a "
                                        "group must stand on (0 = any level surface, paper)")
    traversable: tuple = _f(("bush", "pepper"), doc="class names the vehicle may drive through")
    ground_classes: tuple = _f(("ground",), doc="class names that are traversable below "
                                                "ground_max_height_m (paper: none)")
    ground_class_contact: bool = _f(True, doc="a colour group may stand on the ground through "
                                              "the steep ground-class pixels at ground height "
                                              "below it (an obstacle of the ground's colour: its "
                                              "lower face is traversable by colour; paper: false)")
    bottom_grounded: bool = _f(True, doc="a group cut off by the image bottom stands on the "
                                         "ground the camera cannot see (paper: false)")
    min_height_m: float = _f(0.15, lo=0.0, hi=3.0, doc="a group must rise this high above the "
                                                       "ground plane (0 = any, paper)")
    candidate_min_height: bool = _f(True, doc="every obstacle object (a 3-D cluster of the "
                                              "projected points on 0.1 m cells, as the "
                                              "candidates) must itself reach min_height_m; "
                                              "lower clusters and their points are dropped (a "
                                              "group need reach it only somewhere: low leaves "
                                              "at a bush row's foot; paper: false, "
                                              "docs/rgbd.md)")
    raised_surfaces: bool = _f(True, doc="level surfaces of no traversable colour between "
                                          "min_height_m and raised_max_height_m above the "
                                          "ground are obstacles (a box top seen from close)")
    raised_max_height_m: float = _f(2.0, lo=0.0, hi=10.0)
    raised_bottom_only: bool = _f(True, doc="raised level surfaces count only where they reach "
                                             "the image bottom (a near box's top)")
    open_px: int = _f(0, lo=0, hi=15, doc="opening of the obstacle candidates before grouping "
                                          "(0 = none, the paper)")
    project_stride_px: int = _f(2, lo=1, hi=8, doc="project every n-th obstacle pixel in each "
                                                   "direction (2: 8 mm apart at 5 m, far below "
                                                   "the 0.1 m grid)")
    occlusion_filter: bool = _f(True, doc="do not project the far side of a depth edge that the "
                                          "slope pair and the dilation add to a group")
    holes: bool = _f(True, doc="depth holes standing on the ground are obstacles (paper: false)")
    hole_min_pixels: int = _f(150, lo=1, hi=100000)
    hole_min_width_px: int = _f(12, lo=1, hi=200, doc="narrower holes are depth shadows at "
                                                      "occlusion edges, not shiny objects")
    hole_max_range_m: float = _f(4.5, lo=0.0, hi=50.0,
                                 doc="a depth hole must stand on surface nearer than this (0 = "
                                     "max_range_m); at the range limit a hole is the far view")
    hole_ignore_classes: tuple = _f(("cover",), doc="colour classes a depth hole may have "
                                                    "without being an obstacle besides the "
                                                    "traversable ones (the greenhouse cover: "
                                                    "beyond the sensor's range)")
    use_vehicle_pitch: bool = _f(False, doc="add the vehicle's pitch to the mount pitch")
    colour_check: bool = _f(True, doc="judge on every frame whether the class model explains "
                                      "the ground in view: the share of level pixels at ground "
                                      "height (under ground_max_height_m, else 0.25 m) within "
                                      "colour_threshold of one of its classes. Below "
                                      "colour_check_min_share (running mean) the model was "
                                      "trained somewhere else (the greenhouse model on a stubble "
                                      "field) and the pipeline decides on geometry alone: slope "
                                      "and geometry_min_rise_m, no colour, texture or depth "
                                      "holes; it says so in the log and in status")
    colour_check_min_share: float = _f(0.8, lo=0.0, hi=1.0,
                                       doc="the share of ground-height pixels the class model "
                                           "must explain for its colour classes to be used")
    geometry_min_rise_m: float = _f(0.4, lo=0.0, hi=3.0,
                                    doc="geometry alone (the class model does not apply): a "
                                        "group must rise at least this far above its own foot "
                                        "(5th to 95th percentile of its pixels' heights, pixels "
                                        "with depth)")
    geometry_rise_factor: float = _f(1.6, lo=0.0, hi=10.0,
                                     doc="geometry alone: ... and this many times the 95th "
                                         "percentile of the rises of the last 1000 groups seen "
                                         "(the field's own crop residue; 0 = the minimum only)")
    geometry_max_rise_m: float = _f(0.8, lo=0.0, hi=5.0,
                                    doc="geometry alone: a group rising this far is an obstacle "
                                        "whatever the field's usual (0 = no cap): taller than "
                                        "crop residue, so where everything is that tall (bush "
                                        "rows) the box stops rather than sees nothing")
    cue_min_depth_valid: float = _f(0.5, lo=0.0, hi=1.0,
                                    doc="cue: a cell with less valid depth than this share "
                                        "is not used (a shiny object's cells hold only the "
                                        "depth around it; holes have their own rule)")
    cue_depth_span_m: float = _f(0.6, lo=0.0, hi=10.0,
                                 doc="cue: pixels of a cue group farther than its nearest "
                                     "tenth plus this are dropped (the cells on its outline "
                                     "hold the bush behind it); 0 = keep all")
    cue_erode_px: int = _f(8, lo=0, hi=32, doc="cue: its pixel mask shrunk by this much (the "
                                               "cells on an outline are partly background)")


# The paper's decision (section 3.5) on our slope step: give these to RgbdPipelineConfig (or put
# them in [perception.rgbd]) to run the faithful variant; the defaults above are the measured
# best (docs/rgbd.md). The paper-literal slope adds slope_step_px = 1, depth_median_px = 0,
# occlusion_filter = false.
PAPER_RULE = {
    # the paper gives no colour threshold: 3.5 was our first reproduction's, and it serves the
    # paper's rule better than our 4.5 (docs/rgbd.md)
    "colour_threshold": 3.5,
    "texture": "after-colour", "texture_scope": "suspected", "texture_undefined": True,
    "contact_px": 1, "texture_contact_px": 0, "ground_max_height_m": 0.0, "ground_classes": (),
    "bottom_grounded": False, "min_height_m": 0.0, "candidate_min_height": False,
    "holes": False,
    "ground_class_contact": False, "texture_min_pixels": 0,
    "raised_surfaces": False, "raised_bottom_only": False,
}


@dataclass
class RgbdResult:
    """Everything one frame produced (for tools and tests; process() keeps only the points)."""

    slope_deg: np.ndarray | None  # None from process() (the fast path thresholds without it)
    suspected: np.ndarray
    surface: np.ndarray
    colour_class: np.ndarray      # int16, NOT_CLASSIFIED outside suspected, -1 undefined
    texture_class: np.ndarray | None
    colour_obstacles: np.ndarray  # bool mask
    texture_obstacles: np.ndarray | None
    hole_obstacles: np.ndarray | None
    obstacles: np.ndarray         # bool mask (union)
    groups_colour: int
    groups_texture: int
    groups_holes: int
    points_xy: np.ndarray
    raised_obstacles: np.ndarray | None = None
    groups_raised: int = 0
    learned_obstacles: np.ndarray | None = None
    groups_learned: int = 0
    hole_points: int = 0          # the last ``hole_points`` of points_xy are the holes'
    projected: np.ndarray | None = None   # the obstacle pixels that went to 3-D
    geometry_only: bool = False   # the class model did not explain the scene: slope and height
    colour_share: float | None = None   # the frame's share of ground-height pixels it explained


class RgbdPipeline(Pipeline):
    name = "rgbd"
    requires = ("rgbd",)
    config_class = RgbdPipelineConfig
    cue_domain = "rgbd"                # the learned cue models this pipeline takes

    def __init__(self, options: RgbdPipelineConfig | None = None,
                 model: RgbdClassModel | None = None, cue_model=None):
        super().__init__(options)
        o: RgbdPipelineConfig = self.options
        self.cue = LearnedCue(o.cue, self.cue_domain, o.cue_model, o.cue_threshold, o.cue_threads,
                              model=cue_model)
        if o.max_range_m <= o.min_range_m:
            raise ValueError("perception.rgbd: max_range_m must exceed min_range_m")
        if model is None:
            from appliance import rgbd_model       # the file is read outside perception
            model = rgbd_model.load(o.model or None)
        self.model = model
        # the exact (8-bit) lookup table is built in a background thread; until it is there the
        # suspected pixels are classified one by one, with the same result
        self.colour = ColourClassifier(model.mixtures(o.colour_space), o.colour_threshold,
                                       o.colour_space, o.colour_lut_bits)
        self.traversable_idx = model.index(o.traversable)
        self.hole_ok_idx = sorted(set(self.traversable_idx) | set(model.index(o.hole_ignore_classes)))
        self.rule = Rule(tuple(self.traversable_idx), len(model.classes),
                         ground_classes=tuple(model.index(o.ground_classes)),
                         ground_max_height_m=o.ground_max_height_m,
                         texture_role="traversable-colour"
                         if o.texture_scope == "traversable-colour" else "or",
                         texture_undefined=o.texture_undefined,
                         min_pixels=o.min_pixels, contact_px=o.contact_px, open_px=o.open_px,
                         bottom_rows=(o.slope_step_px + o.dilate_px // 2 + o.contact_px)
                         if o.bottom_grounded else 0,
                         texture_contact_px=o.texture_contact_px, min_height_m=o.min_height_m,
                         raised_bottom_only=o.raised_bottom_only,
                         ground_class_contact=o.ground_class_contact,
                         texture_min_pixels=o.texture_min_pixels)
        # geometry alone (the class model does not explain the scene): every suspected pixel
        # is a candidate, no class is traversable (a group must also rise geometry_min_rise_m
        # above its own foot: _rising)
        self.geometry_rule = dataclasses.replace(
            self.rule, traversable=(), ground_classes=(),
            min_height_m=o.min_height_m)
        self.colour_share: float | None = None   # running mean of the explained share
        self.colour_applies = True
        self.geometry_frames = 0                 # frames decided on geometry alone
        self._rises = np.zeros(0, np.float32)    # geometry alone: recent groups' rises
        self.geometry_rise_m: float | None = None   # ... and the rise this frame asked for

    # ------------------------------------------------------------------------------------------
    def process(self, inputs: SensorInputs) -> Detections:
        o: RgbdPipelineConfig = self.options
        r = self.analyse(inputs, detail=False)
        geo = self._geometric_points(inputs, r)
        pts, n_low = r.points_xy, 0
        if o.candidate_min_height and o.min_height_m > 0 and len(geo[0]):
            # the geometric points are points_xy's first ones, in the same order (one helper,
            # _pixels_in_range, picks both); the holes' points follow and are not judged
            low = low_clusters(geo[0][:, :2], geo[0][:, 2], o.min_height_m, cell_m=0.1)
            n_low = int(low.sum())
            if n_low:
                n_geo = len(r.points_xy) - r.hole_points
                pts = np.concatenate([r.points_xy[:n_geo][~low], r.points_xy[n_geo:]])
                geo = (geo[0][~low], geo[1][~low], geo[2][~low])
        cands = self._candidates(inputs, r, geo)
        view = None
        if o.camera_view:
            fr = inputs.rgbd
            lo, hi = self._range(fr.calib)
            mask = r.obstacles.astype(np.uint8) * 255
            sx = mask.shape[1] / float(fr.calib.camera.width)
            sy = mask.shape[0] / float(fr.calib.camera.height)
            K = fr.calib.camera.matrix() * np.array([[sx], [sy], [1.0]])
            view = CameraView({"depth": mask}, K, fr.calib.mount.camera_to_vehicle(),
                              fr.calib.mount.position, hi, min_depth_m=lo)
        return Detections(points_xy=pts, candidates=cands, view=view, debug={
            "candidates": len(cands), "low_points_dropped": n_low,
            "suspected_px": int(r.suspected.sum()), "obstacle_px": int(r.obstacles.sum()),
            "groups_colour": r.groups_colour, "groups_texture": r.groups_texture,
            "groups_holes": r.groups_holes, "groups_raised": r.groups_raised,
            "groups_learned": r.groups_learned,
            "texture_ran": r.texture_class is not None,
            "colour_model": "geometry-only" if r.geometry_only else "applies",
            "colour_share": None if r.colour_share is None else round(r.colour_share, 3),
            "geometry_rise_m": None if not r.geometry_only or self.geometry_rise_m is None
            else round(self.geometry_rise_m, 3)})

    def notes(self) -> dict:
        out = dict(self.cue.notes())
        if not self.colour_applies:
            out["colour_model"] = self._not_applicable_text()
        return out

    def _not_applicable_text(self) -> str:
        o: RgbdPipelineConfig = self.options
        return (f"the class model explains {100 * (self.colour_share or 0.0):.0f} % of the "
                f"ground in view (needs {100 * o.colour_check_min_share:.0f} %): trained "
                f"elsewhere; deciding on geometry alone (slope, height >= "
                f"{self.geometry_rise_m or o.geometry_min_rise_m:.2f} m above its own foot, "
                f"{o.geometry_rise_factor:g} x the field's usual), no colour, texture or depth "
                f"holes")

    def _check_colour(self, color, depth, surface_all, height, cfull) -> float | None:
        """The colour-model check (``colour_check``): the share of this frame's level pixels at
        ground height (every COLOUR_CHECK_STRIDE-th row and column) that the model puts within
        ``colour_threshold`` of one of its classes; folded into a running mean that
        decides, with hysteresis, whether the colour classes are used. None: too few ground
        pixels in view (the state does not change)."""
        o: RgbdPipelineConfig = self.options
        st = COLOUR_CHECK_STRIDE
        gmax = o.ground_max_height_m if o.ground_max_height_m > 0 else 0.25
        g = surface_all[::st, ::st] & (depth[::st, ::st] > 0) & \
            (height[::st, ::st] < np.float32(gmax))
        if int(g.sum()) < COLOUR_CHECK_MIN_PIXELS:
            return None
        if cfull is not None:
            cls = cfull[::st, ::st][g]
        else:                    # the lookup table is not built yet: the same classes, per pixel
            cls = self.colour.classify(colour_features(color[::st, ::st][g], o.colour_space))
        share = float((cls >= 0).mean())          # UNDEFINED: no class near enough
        m = share if self.colour_share is None else \
            (1 - COLOUR_CHECK_ALPHA) * self.colour_share + COLOUR_CHECK_ALPHA * share
        self.colour_share = m
        was = self.colour_applies
        if was and m < o.colour_check_min_share:
            self.colour_applies = False
        elif not was and m >= min(1.0, o.colour_check_min_share + COLOUR_CHECK_HYSTERESIS):
            self.colour_applies = True
        if was and not self.colour_applies:
            log.warning("rgbd: %s", self._not_applicable_text())
        elif not was and self.colour_applies:
            log.warning("rgbd: the class model explains %.0f %% of the ground in view again: "
                        "colour, texture and depth holes back on", 100 * m)
        return share

    def _range(self, calib) -> tuple[float, float]:
        """The depth range used: the options' within the sensor's own."""
        o: RgbdPipelineConfig = self.options
        lo = max(o.min_range_m, calib.min_range_m) if calib.min_range_m else o.min_range_m
        hi = min(o.max_range_m, calib.max_range_m) if calib.max_range_m else o.max_range_m
        return lo, hi

    @staticmethod
    def _pixels_in_range(depth, mask, lo, hi, stride: int = 1):
        """(v, u, z) of the pixels of ``mask`` (every ``stride``-th row and column) whose
        depth is within [lo, hi], in row-major order: the points of points_xy and of the
        candidates are these, in this order."""
        if stride > 1:
            v, u = np.nonzero(mask[::stride, ::stride])
            v, u = v * stride, u * stride
        else:
            v, u = np.nonzero(mask)
        z = depth[v, u]
        ok = (z >= lo) & (z <= hi)
        return v[ok], u[ok], z[ok]

    def _geometric_points(self, inputs: SensorInputs, r: RgbdResult):
        """(points (N, 3) in the vehicle frame, their rows v, columns u): the obstacle pixels
        that went to points_xy (after the occlusion filter), the same ones in the same order
        as points_xy's first N (the holes' follow them there)."""
        o: RgbdPipelineConfig = self.options
        fr = inputs.rgbd
        cam, mount = fr.calib.camera, fr.calib.mount
        geo = r.projected if r.projected is not None else r.obstacles
        lo, hi = self._range(fr.calib)
        v, u, z = self._pixels_in_range(fr.depth_m, geo, lo, hi, max(1, o.project_stride_px))
        z = np.asarray(z, np.float32)
        x = (u - np.float32(cam.cx)) / np.float32(cam.fx) * z
        y = (v - np.float32(cam.cy)) / np.float32(cam.fy) * z
        p = np.stack([x, y, z], axis=1).astype(np.float64).reshape(-1, 3)
        return p @ mount.camera_to_vehicle().T + mount.position, v, u

    def _candidates(self, inputs: SensorInputs, r: RgbdResult, geo=None) -> tuple:
        """The frame's obstacle groups as candidates (issue #14): the obstacle pixels (every
        ``project_stride_px``-th) in 3-D (``geo``: :meth:`_geometric_points`, by default
        computed here), height above the ground plane under the mount (level ground), each
        point flagged with the cues whose mask holds it; depth holes (no 3-D but their
        contact line) are candidates of their own seen by colour. The pixels are those that
        went to points_xy (after the occlusion filter)."""
        o: RgbdPipelineConfig = self.options
        pv, v, u = self._geometric_points(inputs, r) if geo is None else geo
        out: tuple = ()
        if len(pv):
            flags = {}
            for name, m in (("colour", None if r.geometry_only else r.colour_obstacles),
                            ("texture", r.texture_obstacles),
                            ("cue", r.learned_obstacles), ("geometry", r.raised_obstacles)):
                if m is not None:
                    flags[name] = m[v, u]
            # every group stood out of the depth by its slope: geometry is the base source
            out = cluster_candidates(pv[:, :2], pv[:, 2], None, flags,
                                     base_sources=("geometry",), pipeline=self.name,
                                     cell_m=0.1, min_points=5, contact_m=0.3)
        if r.hole_obstacles is not None and r.groups_holes:
            # the hole points are the last ones added to points_xy (their contact line)
            n_geo = len(r.points_xy) - r.hole_points
            hp = r.points_xy[n_geo:]
            if len(hp):
                out = tuple(out) + cluster_candidates(hp, np.zeros(len(hp)), None,
                                                      base_sources=("colour",),
                                                      pipeline=self.name, cell_m=0.1,
                                                      min_points=2)
        return out

    def analyse(self, inputs: SensorInputs, detail: bool = True) -> RgbdResult:
        """One frame, every intermediate map in the result; ``detail=False`` (process()) skips
        the slope map in degrees, which the decision does not need."""
        o: RgbdPipelineConfig = self.options
        self.cue.check()                  # a required cue that cannot run: no decision at all
        fr = inputs.rgbd
        color, depth = fr.color, fr.depth_m
        if color.shape[:2] != depth.shape:
            raise ValueError(f"rgbd colour {color.shape[:2]} and depth {depth.shape} differ")
        cam, mount = fr.calib.camera, fr.calib.mount
        pitch = math.radians(mount.pitch_deg)
        if o.use_vehicle_pitch and inputs.vehicle is not None:
            pitch += inputs.vehicle.pitch_rad
        lo, hi = self._range(fr.calib)
        if o.depth_median_px:
            # Kinect-class depth is quantised and noisy; a 3x3 median keeps edges (holes stay 0)
            zf = np.asarray(depth, np.float32)
            depth_s = np.where(zf > 0, cv2.medianBlur(zf, o.depth_median_px), np.float32(0))
        else:
            depth_s = depth
        steep, level = steep_map(depth_s, cam.fy, cam.cy, pitch, lo, hi, o.slope_step_px,
                                 o.slope_threshold_deg)
        sus, surface = suspected_from(steep, level, o.dilate_px, o.morphology == "close")
        slope = slope_map(depth_s, cam.fy, cam.cy, pitch, lo, hi, o.slope_step_px) \
            if detail else None
        height = None
        if o.min_height_m > 0 or o.ground_max_height_m > 0 or o.raised_surfaces:
            height = height_map(depth_s, cam.fy, cam.cy, pitch, mount.z_m)
        if o.ground_max_height_m > 0:
            # our addition: bush tops are level too, but an obstacle stands on the ground
            surface &= height < np.float32(o.ground_max_height_m)

        # 2. colour classes (the whole frame through the lookup table: one gather per pixel is
        # cheaper than picking the suspected ones out)
        cfull = self.colour.classify_image(color) if self.colour.lut_ready() else None
        # does the class model explain the ground in view? (else: geometry alone)
        share = None
        if o.colour_check:
            if height is None:        # (the paper's rule does not need the height otherwise)
                height_c = height_map(depth_s, cam.fy, cam.cy, pitch, mount.z_m)
            else:
                height_c = height
            share = self._check_colour(color, depth_s, surface, height_c, cfull)
        geometry_only = not self.colour_applies

        # beyond the paper: the learned cue's obstacle-like cells (issue #8)
        learned = self.cue.mask(color, sus.shape, 0, o.cue_open_cells, o.cue_erode_px,
                                depth, o.cue_min_depth_valid) \
            if self.cue.enabled and sus.any() else None

        raised = None
        tmap = None
        if geometry_only:
            # geometry alone: every suspected pixel is a candidate (no class), standing on low
            # ground, min_height_m above it, and rising geometry_min_rise_m above its own foot,
            # judged on the pixels with depth (a pixel with no depth has no height)
            self.geometry_frames += 1
            cmap = np.where(sus, np.int16(UNDEFINED), np.int16(NOT_CLASSIFIED))
            hv = np.where(depth_s > 0, height_c, np.float32(np.nan))
            d = decide(sus, surface, cmap, None, self.geometry_rule, hv, None, learned)
            if d.n_colour:
                d.colour, d.n_colour = self._rising(d.colour, hv)
        else:
            if o.raised_surfaces:
                raised = level & ~sus & (height >= np.float32(max(o.min_height_m, 0.05))) & \
                    (height < np.float32(o.raised_max_height_m))
            want = sus if raised is None else sus | raised
            if cfull is not None:
                cmap = np.where(want, cfull, np.int16(NOT_CLASSIFIED))
            else:
                cmap = np.full(sus.shape, NOT_CLASSIFIED, np.int16)
                cmap[want] = self.colour.classify(colour_features(color[want], o.colour_space))
            # 3. texture, and 4. the decision
            if o.texture == "always":
                tmap = self._texture_map(color, sus)
                d = decide(sus, surface, cmap, tmap, self.rule, height, raised, learned)
            else:
                d = decide(sus, surface, cmap, None, self.rule, height, raised, learned)
                if o.texture == "after-colour" and d.n_colour > 0:
                    tmap = self._texture_map(color, sus)
                    d = decide(sus, surface, cmap, tmap, self.rule, height, raised, learned)
        col_obs, tex_obs, n_col, n_tex = d.colour, d.texture, d.n_colour, d.n_texture
        if d.learned is not None and d.n_learned and o.cue_depth_span_m > 0:
            d.learned = self._depth_trim(d.learned, depth, o.cue_depth_span_m)

        obs = d.obstacles
        proj = obs
        if o.occlusion_filter and obs.any():
            # eq. 4 marks the upper pixel of a pair, so at an occlusion edge (the top of a box)
            # the ground BEHIND is marked, and the dilation adds more background: keep only
            # pixels no farther than 10 % beyond the nearest depth around them
            zf = np.where(depth > 0, depth, np.float32(np.inf)).astype(np.float32)
            k = max(o.slope_step_px, 1) * 2 + 1
            zmin = cv2.erode(zf, np.ones((k, max(o.dilate_px, 3)), np.uint8))
            with np.errstate(over="ignore", invalid="ignore"):
                proj = obs & (zf <= zmin * np.float32(1.1))
        pts = self._points(depth, proj, cam, mount, lo, hi, o.project_stride_px)

        # our addition: shiny surfaces return no depth at all
        hole_obs = None
        n_holes = 0
        n_hole_pts = 0
        if o.holes and not geometry_only:
            # (a hole's rule needs colour: without it the far view and the sky are holes)
            hole_obs, n_holes, hpts = self._holes(color, depth, surface, cam, mount, pitch, lo, hi,
                                                  cfull)
            if len(hpts):
                pts = np.concatenate([pts, hpts])
                n_hole_pts = len(hpts)
            obs = obs | hole_obs
        return RgbdResult(slope, sus, surface, cmap, tmap, col_obs, tex_obs, hole_obs, obs,
                          n_col, n_tex, n_holes, pts, d.raised, d.n_raised, d.learned,
                          d.n_learned, n_hole_pts, proj, geometry_only, share)

    @staticmethod
    def _group_rises(mask: np.ndarray, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(labels of the connected groups of ``mask``, per label the rise of the group: the
        span of its pixels' heights (those not NaN, every 2nd row and column) from the 5th to
        the 95th percentile, NaN for a group with fewer than 5 such pixels and for label 0).
        The rise is above the group's own foot, wherever the ground under it is (the level
        ground plane under the mount is wrong by the field's undulation)."""
        n, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=8,
                                            ltype=cv2.CV_32S)
        rise = np.full(n, np.nan, np.float32)
        ls, hs = labels[::2, ::2], height[::2, ::2]
        sel = (ls > 0) & np.isfinite(hs)
        lv, hv = ls[sel], hs[sel]
        if len(lv):
            order = np.lexsort((hv, lv))
            lv, hv = lv[order], hv[order]
            starts = np.searchsorted(lv, np.arange(n))
            counts = np.bincount(lv, minlength=n)
            has = np.flatnonzero(counts >= 5)
            lo = hv[starts[has] + (counts[has] - 1) * 5 // 100]
            hi = hv[starts[has] + (counts[has] - 1) * 95 // 100]
            rise[has] = hi - lo
        rise[0] = np.nan
        return labels, rise

    def _rising(self, mask: np.ndarray, height: np.ndarray) -> tuple[np.ndarray, int]:
        """The groups of ``mask`` that rise more than the field's own crop residue: at least
        ``geometry_min_rise_m``, and ``geometry_rise_factor`` times the 95th percentile of the
        rises of the last GEOMETRY_RISE_MEMORY groups seen (this frame's included): the tufts
        of a tall stubble are ordinary there; an obstacle is a rare, taller group. A group
        rising ``geometry_max_rise_m`` always counts."""
        o: RgbdPipelineConfig = self.options
        labels, rise = self._group_rises(mask, height)
        seen = rise[np.isfinite(rise)]
        if len(seen):
            self._rises = np.concatenate([self._rises, seen])[-GEOMETRY_RISE_MEMORY:]
        thr = o.geometry_min_rise_m
        if len(self._rises):
            thr = max(thr, o.geometry_rise_factor * float(np.percentile(self._rises, 95)))
        if o.geometry_max_rise_m > 0:
            # however tall the field's usual groups, a group this tall is never the field's
            thr = min(thr, max(o.geometry_max_rise_m, o.geometry_min_rise_m))
        self.geometry_rise_m = thr
        with np.errstate(invalid="ignore"):
            keep = rise >= np.float32(thr)
        keep[0] = False
        return keep[labels], int(keep.sum())

    @staticmethod
    def _depth_trim(mask: np.ndarray, depth: np.ndarray, span_m: float) -> np.ndarray:
        """Each connected group of ``mask`` keeps the pixels no farther than its nearest tenth
        (10th percentile of its valid depth) plus ``span_m``."""
        n, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=8,
                                            ltype=cv2.CV_32S)
        if n <= 1:
            return mask
        lab = labels[mask]
        z = depth[mask]
        ok = z > 0
        near = np.full(n, np.inf, np.float32)      # a group with no sample keeps its pixels
        # the percentile from every 4th pixel each way (a group is >= 30 px; its nearest
        # tenth does not need all of them), the cut applied to every pixel
        sub = mask[::4, ::4]
        ls, zs = labels[::4, ::4][sub], depth[::4, ::4][sub]
        if (zs > 0).any():
            # per group: sort its valid depths once (by group, then depth), take the 10th
            # percentile by rank
            lv, zv = ls[zs > 0], zs[zs > 0]
            order = np.lexsort((zv, lv))
            lv, zv = lv[order], zv[order]
            starts = np.searchsorted(lv, np.arange(n))
            counts = np.bincount(lv, minlength=n)
            has = counts > 0
            idx = starts[has] + (counts[has] - 1) // 10
            near[has] = zv[idx] + np.float32(span_m)
        keep = ok & (z <= near[lab])
        out = np.zeros_like(mask)
        out[mask] = keep
        return out

    # ------------------------------------------------------------------------------------------
    def _texture_map(self, color: np.ndarray, sus: np.ndarray) -> np.ndarray:
        o: RgbdPipelineConfig = self.options
        if not sus.any():
            return np.full(sus.shape, NOT_CLASSIFIED, np.int16)
        win = o.texture_window_px
        h, w = sus.shape
        widx, ny, nx = window_index(sus.shape, win)
        nw = ny * nx
        if h % win == 0 and w % win == 0:
            # suspected pixels per window: an area resize of the mask (exact for whole windows)
            # (x255: one suspected pixel of 400 still rounds to a non-zero mean)
            frac = cv2.resize(sus.view(np.uint8) * np.uint8(255), (nx, ny),
                              interpolation=cv2.INTER_AREA)
            wanted = np.flatnonzero(frac.ravel() > 0)
        else:
            wanted = np.flatnonzero(np.bincount(widx[sus], minlength=nw))
        codes = lbp_codes(to_grey(color))
        hists = window_histograms(codes, win)       # every window: one bincount, the cheapest
        per_window = np.full(nw, NOT_CLASSIFIED, np.int16)
        per_window[wanted] = classify_histograms(hists[wanted], self.model.lbp,
                                                 o.texture_threshold)
        if h % win == 0 and w % win == 0:
            full = cv2.resize(per_window.reshape(ny, nx), (w, h), interpolation=cv2.INTER_NEAREST)
        else:
            full = per_window[widx]
        return np.where(sus, full, np.int16(NOT_CLASSIFIED))

    @staticmethod
    def _to_vehicle(u, v, z, cam, mount) -> np.ndarray:
        x = (u - np.float32(cam.cx)) / np.float32(cam.fx) * z
        y = (v - np.float32(cam.cy)) / np.float32(cam.fy) * z
        p = np.stack([x, y, z], axis=1).astype(np.float64)
        return (p @ mount.camera_to_vehicle().T + mount.position)[:, :2].astype(np.float32)

    def _points(self, depth, mask, cam, mount, lo, hi, stride: int = 1) -> np.ndarray:
        v, u, z = self._pixels_in_range(depth, mask, lo, hi, stride)
        if not len(z):
            return np.zeros((0, 2), np.float32)
        return self._to_vehicle(u.astype(np.float32), v.astype(np.float32), z, cam, mount)

    def _holes(self, color, depth, surface, cam, mount, pitch, lo, hi, cfull=None):
        """Depth holes standing on the ground: a connected region of no depth of at least
        ``hole_min_pixels``, with surface right below it, whose colour is of no traversable
        class. Its range comes from where its bottom pixels' rays meet the ground plane of the
        mount (flat ground assumed), clipped to the valid range."""
        o: RgbdPipelineConfig = self.options
        hole = depth <= 0
        if o.hole_max_range_m > 0:
            # ground at the range limit under a hole: that is the view beyond the range (the
            # far end of the path, the cover), not a shiny obstacle standing in range
            surface = surface & (depth < np.float32(o.hole_max_range_m))
        if cfull is not None:
            cmap = cfull                   # (only the holes' classes count: masked below)
        else:
            cmap = np.full(hole.shape, NOT_CLASSIFIED, np.int16)
            cmap[hole] = self.colour.classify(colour_features(color[hole], o.colour_space))
        cand = hole & not_traversable(cmap, self.hole_ok_idx)
        # holes are thin at depth edges: open the mask so only solid regions remain
        cand = cv2.morphologyEx(cand.view(np.uint8), cv2.MORPH_OPEN,
                                np.ones((5, max(5, o.hole_min_width_px)), np.uint8)) > 0
        mask, n = obstacle_groups(cand, surface, o.hole_min_pixels, max(o.contact_px, 3))
        if n == 0:
            return mask, 0, np.zeros((0, 2), np.float32)
        # bottom pixel of each column of the mask: its ray meets the ground at the contact --
        # only where that column stands on the (near) surface
        h = mask.shape[0]
        u = np.nonzero(mask.any(0))[0]
        v = h - 1 - np.argmax(mask[::-1, u], axis=0)
        foot = touching_ground(mask, surface, max(o.contact_px, 3))[v, u]
        cut = v >= h - (o.slope_step_px + o.dilate_px // 2 + max(o.contact_px, 3))
        # (a hole with a visible foot anywhere is placed by its feet; one grounded only beside
        # its bottom columns, cut off by the image bottom, where the lowest ray meets the
        # ground: it is at most that far. A hole with no surface next to it at all -- a blind
        # sensor, something nearer than the sensor's minimum range -- is not placed: the depth
        # camera's health and the other sensors deal with that)
        keep = foot if foot.any() else cut
        u, v = u[keep], v[keep]
        t = (v - cam.cy) / cam.fy
        ang = np.arctan(t) + pitch                              # below the horizontal
        with np.errstate(divide="ignore", invalid="ignore"):
            rng = mount.z_m / np.sin(ang)                       # range in the vertical plane
            z = (rng * np.cos(np.arctan(t))).astype(np.float32)
        far = min(hi, o.hole_max_range_m) if o.hole_max_range_m > 0 else hi
        ok = (ang > math.radians(0.5)) & (z >= lo) & (z <= far)
        if not ok.any():
            return mask, n, np.zeros((0, 2), np.float32)
        # a column of points up the face is not needed: the contact line is the obstacle's front
        pts = self._to_vehicle(u[ok].astype(np.float32), v[ok].astype(np.float32), z[ok], cam,
                               mount)
        return mask, n, pts
