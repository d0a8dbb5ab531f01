"""Pipeline ``stereo-novelty``: the stereo paper's system (Ross et al., seed 000).

Per frame: stabilise (attitude or visual odometry, high-pass), descriptors of 32x32 cells in the
stabilised image, weighted Parzen density against the learnt model, novel = density < rho,
islanding and dilation, the mask back into the camera frame, dense stereo only in the novel
regions (plus the matcher's margin), reprojection, height band -> obstacle points. The frame's
cells, minus those near the obstacles just found, go to the background model update every
``update_every_frames`` frames (never updated inside :meth:`process`).

"""
from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, replace

import cv2
import numpy as np

from appliance.schema import _f

from hal.types import move_with_vehicle

from .base import Detections, Pipeline, SensorInputs
from .cue import CueOptions, LearnedCue
from .candidates import cluster_candidates, on_footprints, stalk_points
from .ground import GroundModel
from .novelty import NoveltyDetector, dilate_cells, mask_to_camera, obstacle_cells
from .look import StereoLook
from .view import CameraView, pixels_of
from .stereo import (StereoConfig, StereoPipeline, band_mask, check_matcher, dedupe_cells, drop_dark,
                     disparity_regions, downscale, local_heights, make_matcher, mask_boxes,
                     match_correlation, match_factor, merge_strips, point_confidence,
                     points_from_disparity,
                     scaled_calibration, strip_boxes, vertical_support, local_ground_of,
                     heights_above)

log = logging.getLogger(__name__)

# the paper gives the 32x32 cells, the 40-frame update and the 3-sigma search; the other
# defaults were chosen on a tuning run (stubble-empty, seed 1), see docs/stereo-novelty.md
DEFAULT_SCALE = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)


@dataclass(frozen=True)
class StereoNoveltyConfig(StereoConfig, CueOptions):
    cell_px: int = _f(0, lo=0, hi=256, doc="cell size in px; 0 = image width / 40 (the paper's "
                                         "32 px, 40x32 cells at 1280x1024; 16 px at 640x512)")
    descriptor_scale: tuple = _f(DEFAULT_SCALE, doc="s of eq. 5: 8 factors for "
                                 "[Lmu amu bmu Lsd asd bsd u v]")
    sigma: float = _f(0.05, lo=1e-4, hi=10.0, doc="kernel width in scaled descriptor units")
    rho: float = _f(1.0, lo=1e-30, hi=1e30, doc="novel when density < rho (eq. 3 units)")
    novelty_gate: str = _f("on", choices=("on", "off", "all"),
                           doc="what the novelty mask does (an ablation switch; the model is "
                               "learnt as always): on = its cells are matched densely (the "
                               "paper); off = novelty gates nothing (only the depth cue and "
                               "the learned cue choose cells; no point counts as novelty's); "
                               "all = every cell is matched (full-frame dense stereo, "
                               "novelty still credited where it fires). rho cannot switch "
                               "novelty off (docs/front-end.md known limits)")
    forget: float = _f(0.1, lo=1e-4, hi=0.99, doc="lambda of eqs. 6, 7 (per update)")
    update_every_frames: int = _f(40, lo=1, hi=10000, doc="model update period (paper: 40)")
    # Off by default (twenty-seventh and twenty-eighth sessions): fewer boot-time false stops
    # in closed loop (training and acceptance), but its updates learn what stands in view at
    # boot where the frame's points miss it, and keeping the boot check's cells out of them
    # takes the gain away (docs/front-end.md "The field's canopy, and the boot")
    warmup_updates: int = _f(0, lo=0, hi=1000,
                             doc="beyond the paper: the model's first this many updates come "
                                 "every warmup_every_frames frames instead of "
                                 "update_every_frames (a model of one frame calls the field's "
                                 "own stubble novel for the 4 s until its second update; a "
                                 "model loaded from the state directory is no young one); 0 = "
                                 "off (the paper)")
    warmup_every_frames: int = _f(2, lo=1, hi=10000, doc="warmup_updates: their period")
    weight_floor: float = _f(0.005, lo=0.0, hi=1.0,
                             doc="samples whose weight decays below this are dropped")
    max_neighbours: int = _f(64, lo=1, hi=4096, doc="neighbours summed per query (<= 3 sigma)")
    cutoff_sigmas: float = _f(3.0, lo=1.0, hi=10.0, doc="neighbour search radius (paper: 3)")
    island_min_neighbours: int = _f(1, lo=0, hi=8, doc="novel 8-neighbours a novel cell needs")
    dilate_cells: int = _f(1, lo=0, hi=10, doc="dilation of the novelty mask, in cells")
    obstacle_margin_px: float = _f(64.0, lo=0.0, hi=2000.0,
                                   doc="cells this close to a detected obstacle are never learnt "
                                       "(in pixels: of the camera's image, or see "
                                       "obstacle_margin_ref_px)")
    obstacle_margin_ref_px: int = _f(0, lo=0, hi=16384,
                                     doc="obstacle_margin_px is in pixels of an image this wide "
                                         "(1280, the paper's: the same margin in novelty cells, "
                                         "2 each way, whatever the camera's resolution); 0 = "
                                         "in pixels of the camera's own image (4 cells each way "
                                         "at 640 px; docs/front-end.md 'The feedback margin')")
    alpha: float = _f(0.1, lo=0.0, hi=1.0, doc="stabilisation high-pass: (1-alpha) per frame")
    stabilise: str = _f("auto", choices=("auto", "attitude", "vo", "off"),
                        doc="auto = vehicle attitude when present, else visual odometry")
    descriptor_width_px: int = _f(640, lo=0, hi=16384,
                                  doc="cell descriptors of the image area-averaged to at most "
                                      "this wide (1280 -> 640, cells scaled with it: the same "
                                      "grid); 0 = native resolution")
    match_width_px: int = _f(640, lo=0, hi=16384,
                             doc="dense matching on images at most this wide (1280 -> 640); "
                                 "0 = native resolution")
    ground_range: bool = _f(True, doc="per-strip disparity range: nothing farther than the "
                                      "ground plane (with the slacks below)")
    ground_slack_m: float = _f(0.3, lo=0.0, hi=10.0,
                               doc="ground_range: the ground may be this much lower")
    pitch_slack_deg: float = _f(3.0, lo=0.0, hi=45.0,
                                doc="ground_range: the vehicle may pitch this much nose-up")
    strip_rows: int = _f(64, lo=0, hi=4096,
                         doc="ground_range: rows per strip, at matching resolution (0 = whole box)")
    band_cols: int = _f(32, lo=0, hi=4096,
                        doc="ground_range: a region's box is cut into column bands this wide (at "
                            "matching resolution), each trimmed to its masked rows and searched "
                            "from its own foot (0 = whole box)")
    merge_bands: bool = _f(False, doc="ground_range: neighbouring bands' strips whose rows "
                                       "overlap are matched as one box over their union when "
                                       "SGBM's fitted crop cost says that is cheaper (each "
                                       "band keeps only its own rows and range). Off: -10 % "
                                       "matching time with merge_max_cols = 0, recall the "
                                       "same, but +16 % false-positive frames by day and +23 % "
                                       "false cells at night on acceptance seed 1001 "
                                       "(docs/front-end.md, Speed)")
    merge_max_cols: int = _f(64, lo=0, hi=16384,
                             doc="merge_bands: no merged box wider than this (matching "
                                 "resolution px; 0 = no limit)")
    depth_cue: str = _f("bm", choices=("off", "bm", "sgbm"),
                        doc="beyond the paper: coarse full-frame stereo with this matcher at "
                            "depth_cue_width_px; cells where enough coarse points lie in the "
                            "height band are matched densely too, novel or not (catches an "
                            "obstacle coloured like the field)")
    depth_cue_width_px: int = _f(320, lo=32, hi=16384,
                                 doc="depth_cue: coarse matching at most this wide")
    depth_cue_min_fraction: float = _f(0.25, lo=0.0, hi=1.0,
                                       doc="depth_cue: share of a cell's coarse pixels that "
                                           "must be in the height band")
    depth_cue_dilate_cells: int = _f(1, lo=0, hi=10, doc="depth_cue: dilation of its cells")
    depth_cue_max_range_m: float = _f(15.0, lo=0.5, hi=200.0,
                                      doc="depth_cue: coarse points farther ahead are ignored "
                                          "(coarse depth is poor far away; novelty still covers "
                                          "the far field)")
    depth_cue_block: int = _f(11, lo=0, hi=51, doc="depth_cue: matcher block (odd; 0 = the "
                                                   "matcher's default)")
    depth_cue_speckle_px: int = _f(60, lo=0, hi=10000,
                                   doc="depth_cue: speckle filter window of the coarse matcher "
                                       "(0 = off): drops small blobs of mismatches")
    near_from_foot: bool = _f(True, doc="ground_range, with depth_cue on: a region's obstacle "
                                         "stands on the ground inside it, so it is no nearer "
                                         "than the ground at the region's last row, or than "
                                         "the nearest coarse depth seen in it (without the "
                                         "coarse pass this check is off: full near range)")
    cue_dilate_cells: int = _f(0, lo=0, hi=10, doc="cue: dilation of its cells")
    # Off by default: open loop it passed its rule on the acceptance seeds, but closed loop on
    # training drives it had one collision more and more first differences for the worse
    # (docs/front-end.md "The near search")
    near_min_depth_m: float = _f(0.0, lo=0.0, hi=100.0,
                                 doc="near_from_foot: a strip whose own last row sees "
                                     "ground nearer than min_depth_m searches down to this "
                                     "z-depth (more disparities than num_disparities, only "
                                     "there), so what stands in the stop zone's near part is "
                                     "ranged; 0 = off (the search ends at min_depth_m)")
    # Off: closed loop it let go of the held phantoms and of a 0.48-m crate the hold had
    # kept, one collision more (docs/tracking.md "The view as near as the near search")
    near_view: bool = _f(False, doc="near_min_depth_m: the camera's view (what [grid] "
                                    "hold_blind asks: could the pipeline have put a point "
                                    "there?) reaches down to near_min_depth_m instead of "
                                    "min_depth_m, so a cell held out of sight that the near "
                                    "search can range is looked at again, and let go if "
                                    "nothing is found there; needs near_min_depth_m > 0")
    near_boot: bool = _f(False, doc="near_min_depth_m: the boot guard's full-frame pass "
                                    "searches that near too (measured with an earlier "
                                    "version: the empty field's false frames 5 -> 12 of 80, "
                                    "most likely far mismatches kept out of the first update, "
                                    "a lock-in)")
    near_margin: float = _f(1.15, lo=1.0, hi=4.0,
                            doc="near_from_foot: the coarse disparity seen is scaled by this "
                                "(coarse depth is rough) before it bounds the search")
    ground_local_cue: bool = _f(False, doc="ground_local: the depth cue's coarse points too "
                                           "are judged above the local ground (false: above "
                                           "the level plane or the fit; the dense points "
                                           "always above the local ground)")
    ground_local_dense: bool = _f(True, doc="ground_local: the frame's dense points carry the "
                                             "local ground too (with the depth cue's coarse "
                                             "points); false: the coarse points alone")
    ground_for_laser: bool = _f(False, doc="fit the frame's ground to the coarse pass's "
                                           "points (as ground_fit does) and hand it to the "
                                           "laser's returns ([perception.laser] ground_min_m); "
                                           "this pipeline's own heights are unchanged")
    boot_guard: bool = _f(True, doc="beyond the paper (issue #14): until the novelty model's "
                                     "first update, every frame also gets full-frame dense "
                                     "stereo; what stands above the ground there (candidates of "
                                     "boot_min_points or more) and the learned cue's cells are "
                                     "obstacles of that frame and are kept out of the first "
                                     "update (paper: the first frame is learnt whole)")
    # issue #14's stages of StereoConfig, on for the product (measured in docs/front-end.md;
    # PRE_ISSUE_14 below gives the values that reproduce the earlier tables)
    uniqueness: int = _f(15, lo=0, hi=100, doc="matcher uniqueness ratio (also the depth "
                                               "cue's coarse BM; before issue #14: 10)")
    pad_left: bool = _f(True, doc="match the image's leftmost columns too (see "
                                  "[perception.stereo]; before issue #14: false)")
    support_min: float = _f(0.5, lo=0.0, hi=1.0, doc="vertical support of obstacle points "
                                                     "(see [perception.stereo]; before issue "
                                                     "#14: 0 = off)")
    support_known_min: float = _f(0.5, lo=0.0, hi=1.0,
                                  doc="vertical support: the share of the samples below an "
                                      "obstacle point that must have a disparity at all (see "
                                      "[perception.stereo]; a mismatch floating over an "
                                      "unmatched column, the false stops' signature, has none; "
                                      "before the false-stop work: 0 = off)")
    # Off by default: built and measured in the forty-first session (docs/front-end.md "The
    # match's own correlation")
    match_ncc_min: float = _f(0.0, lo=0.0, hi=1.0,
                              doc="an obstacle point whose left and right windows (7 x 11 "
                                  "pixels at 640 wide, grey, at its disparity) correlate "
                                  "(zero-mean, normalised) below this is dropped; a window "
                                  "too flat to say (grey std < 2) or off the image keeps its "
                                  "point. 0 = off")
    match_ncc_from_m: float = _f(0.0, lo=0.0, hi=100.0,
                                 doc="match_ncc_min: only points at least this far along the "
                                     "camera's axis are tested (nearer ones, at the search's "
                                     "near edge, are how an obstacle nearer than the search "
                                     "shows at all). 0 = every point")
    dark_level: float = _f(8.0, lo=0.0, hi=255.0, doc="no disparity where the 7x7 mean grey "
                                                      "level is below this (before issue #14: "
                                                      "0 = off)")
    model_state: str = _f("auto", doc="where the novelty model persists across restarts: "
                                      "auto = $STATE_DIRECTORY/novelty-<pipeline>.npz when "
                                      "the service has a state directory (systemd), off = "
                                      "never, else a file path (appliance/novelty_store.py)")
    model_save_s: float = _f(300.0, lo=0.0, hi=86400.0,
                             doc="while running, the model is saved to model_state every this "
                                 "many seconds (a vehicle whose power is cut at key-off never "
                                 "shuts the box down: it would boot with an empty model, or "
                                 "that of its last clean shutdown); 0 = only at shutdown")
    boot_min_points: int = _f(30, lo=1, hi=100000,
                              doc="boot_guard: points a candidate needs to be kept out of the "
                                  "first update (fewer: stereo noise, learnt as field)")
    boot_horizon_cells: int = _f(1, lo=-100, hi=100,
                                 doc="boot_guard: only cells whose top is at least this many "
                                     "cells below the horizon row are kept out of the first "
                                     "update (the sky and the skyline are learnt)")
    # On by default since the thirty-ninth session (docs/front-end.md "The person at boot,
    # driven": the person's cells novel after the boot 53.9 -> 76.4 % training, 32.2 -> 57.7 %
    # acceptance; the eval runs' false positives +2 frames of 60 on training, none on
    # acceptance)
    boot_above_horizon: bool = _f(True, doc="boot_guard: above the horizon, the cells that "
                                              "hold points of the boot check's candidates "
                                              "(grounded, supported, boot_min_points; no "
                                              "margin) are kept out of the first update too: a "
                                              "standing person's head and shoulders, which the "
                                              "horizon rule lets the first update learn")
    boot_above_horizon_half_width_m: float = _f(2.0, lo=0.0, hi=100.0,
                                                doc="boot_above_horizon: only candidates "
                                                    "whose footprint comes within this of "
                                                    "the vehicle's centre line (what it may "
                                                    "drive into: without it, the far course's "
                                                    "poles and tanks stay novel above the "
                                                    "horizon and their matching adds false "
                                                    "cells); 0 = every boot candidate")
    boot_support_min: float = _f(0.5, lo=0.0, hi=1.0,
                                 doc="boot_guard: the vertical support (support_min) its "
                                     "points need, whatever support_min is")
    # Off by default (the lead's call, seventh session): the rule drops thin, short things
    # within stalk_max_range_m that only the geometry saw — a stubble tuft, but also a stake,
    # a small child side-on, a dog facing the vehicle — and the simulator has no such obstacle
    # to measure that cost against the tufts it removes (docs/front-end.md "Stalks")
    stalk_max_width_m: float = _f(0.0, lo=0.0, hi=2.0,
                                  doc="obstacle points whose neighbourhood (0.2 m along, 0.3 m "
                                      "across) holds band points spanning at most this across, "
                                      "stalk_max_length_m along, none higher than "
                                      "stalk_max_height_m, and raised by geometry alone (under "
                                      "20 % by novelty or the learned cue) are a stalk (a "
                                      "stubble tuft above the band's floor), not an obstacle; "
                                      "0 = off (appliance/perception/candidates.py "
                                      "stalk_points; docs/front-end.md 'Stalks'; 0.22 removed "
                                      "the training night drives' tuft stops)")
    stalk_max_length_m: float = _f(0.3, lo=0.0, hi=2.0, doc="see stalk_max_width_m")
    stalk_max_height_m: float = _f(1.0, lo=0.0, hi=5.0, doc="see stalk_max_width_m")
    stalk_max_range_m: float = _f(8.0, lo=0.0, hi=200.0,
                                  doc="stalk_max_width_m judges only points at most this far "
                                      "ahead (vehicle x): farther, a thing 0.2 m across is a "
                                      "few pixels wide and its points too sparse for a width")
    # Off by default: measured on training drives it held five of seven low obstacles the
    # defaults ran over, but added false stops by day (real stubble 0.2-0.45 m in novel cells)
    # and kept one night drive standing (docs/front-end.md "Low obstacles"). Eleventh session:
    # with low_band_max_novel_share it halved the training collisions (12 -> 6) for 4 more
    # false stops, but on the acceptance seeds it made 73 false stops against 40 (night
    # drives locked in) and no fewer collisions: off again. Fifteenth session, by day only
    # (low_band_night = false): training two dogs held for no more false stops, acceptance
    # the same four dogs hit and 22 -> 24 false stops (docs/proving-ground.md "Paired"): off
    low_band_min_m: float = _f(0.0, lo=0.0, hi=10.0,
                               doc="issue #14 (lying people, dogs): obstacle points from this "
                                   "height up to band_min_m count too when novelty or the "
                                   "learned cue (not the depth cue: geometry alone) put their "
                                   "pixel into matching; the depth cue still raises cells by "
                                   "band_min_m. 0 = off (docs/front-end.md 'Low obstacles')")
    low_band_max_novel_share: float = _f(0.1, lo=0.0, hi=1.0,
                                         doc="low_band_min_m: a low point raised by novelty "
                                             "counts only where its novel region (connected, "
                                             "in the image) covers at most this share of the "
                                             "image: a lying person is a compact region, a "
                                             "patch of soil of a new colour with its stubble a "
                                             "large one (the low band's lock-in, "
                                             "docs/front-end.md 'Low obstacles'; with the low "
                                             "band on, training: 63 -> 35 false stops, the "
                                             "same collisions); 0 = any")
    low_band_night: bool = _f(True, doc="low_band_min_m: at night (strobe) too; false: by day "
                                        "only (at night the novelty mask is the strobe's lit "
                                        "region, where the low band locked drives in on the "
                                        "acceptance seeds)")
    low_band_min_updates: int = _f(2, lo=0, hi=1000,
                                   doc="low_band_min_m: counts only once the novelty model "
                                       "holds this many updates (a model that has learnt one "
                                       "frame calls much of the field novel: at start-up the "
                                       "low band stopped a training drive for its stubble at "
                                       "2.7 s); 0 = from the first frame")
    # Off (thirty-eighth session, docs/front-end.md "Looking again where something was"): a
    # head-on dog, never novel, was matched in 19 of the 92 cycles of its approach (when the
    # depth cue raised it); recalled, in 72, but the recall holds stubble as firmly: training
    # 4 -> 13 false stops (4 with the width filter, more false-stop seconds), acceptance
    # 19 -> 40 with the filter
    recall_frames: int = _f(0, lo=0, hi=100,
                            doc="the obstacle points of the last this many frames, carried "
                                "with the vehicle's motion (speed, yaw rate) and projected "
                                "into the camera, raise their novelty cells for matching "
                                "(cue \"recent\"): what was found once is looked at again in "
                                "the next frames, whatever raised it then. 0 = off")
    recall_dilate_cells: int = _f(1, lo=0, hi=10,
                                  doc="recall_frames: dilation of the recalled cells")
    recall_min_width_m: float = _f(0.0, lo=0.0, hi=10.0,
                                   doc="recall_frames: only the points of the frame's "
                                       "candidates at least this wide across (y) are "
                                       "recalled (a stubble tuft is 9-17 cm across, a dog "
                                       "head-on 26-35 cm); 0 = every obstacle point")
    recall_min_updates: int = _f(0, lo=0, hi=1000,
                                 doc="recall_frames: nothing is recalled before the novelty "
                                     "model holds this many updates (the boot's first frames "
                                     "call much of the field novel)")
    low_band_feedback: bool = _f(True, doc="low_band_min_m: its points keep their cells out of "
                                            "the novelty model's update like any obstacle point "
                                            "(false: they are learnt, so low stubble in a novel "
                                            "cell cannot hold that cell novel)")
    # Off by default (twenty-seventh session): the camera box's stubble false stops on training
    # drives were tuft tops 0.5-0.75 m high raised by the depth cue alone; it removed 8 and 7 of
    # them (training, acceptance) but lost a head-on dog's stop on the acceptance seeds
    # (docs/front-end.md "The field's canopy, and the boot")
    canopy_floor: bool = _f(False, doc="with the depth cue: obstacle points that only the depth "
                                       "cue put into matching (neither novelty nor the learned "
                                       "cue) count only above the field's canopy: the "
                                       "median over the last canopy_frames frames of the "
                                       "canopy_quantile of the heights of each frame's coarse "
                                       "points on the field (in no novel or learned-cue cell, "
                                       "at most canopy_max_range_m ahead, canopy_min_m to "
                                       "canopy_max_m high) + canopy_margin_m, at most "
                                       "canopy_max_m; off: the band's floor for every point")
    canopy_quantile: float = _f(0.99, lo=0.5, hi=1.0, doc="canopy_floor: the quantile")
    canopy_margin_m: float = _f(0.2, lo=0.0, hi=2.0,
                                doc="canopy_floor: above the canopy by this (a tuft's dense points "
                                    "stand up to ~0.2 m over the coarse pass's quantile)")
    canopy_frames: int = _f(10, lo=1, hi=1000,
                            doc="canopy_floor: the median of this many frames' canopies (one "
                                "frame's quantile moves by 0.1-0.3 m; the field's does not)")
    canopy_max_m: float = _f(1.0, lo=0.0, hi=5.0,
                             doc="canopy_floor: the floor is never higher (what stands taller "
                                 "counts by geometry alone, whatever the field)")
    canopy_min_m: float = _f(0.1, lo=0.0, hi=2.0,
                             doc="canopy_floor: coarse points lower than this are the soil, "
                                 "not the canopy, and are left out of the quantile")
    canopy_max_range_m: float = _f(12.0, lo=1.0, hi=200.0,
                                   doc="canopy_floor: coarse points at most this far ahead")
    canopy_min_points: int = _f(200, lo=1, hi=10 ** 7,
                                doc="canopy_floor: fewer field points above canopy_min_m: no "
                                    "canopy this frame (the band's floor for every point)")


# The values of issue #14's new stages that give the pipeline as it was before them (the
# Figure-5 / reproduction tables of docs/stereo-novelty.md: tools/experiments_stereo.py pins
# them in its rows)
PRE_ISSUE_14 = {"boot_guard": False, "pad_left": False, "support_min": 0.0, "uniqueness": 10,
                "dark_level": 0.0, "support_known_min": 0.0, "stalk_max_width_m": 0.0,
                "near_min_depth_m": 0.0}


def canopy_height(h: np.ndarray, pts: np.ndarray, cued: np.ndarray, o) -> float | None:
    """The field's canopy (``canopy_floor``): the ``o.canopy_quantile`` of the heights ``h``
    of the coarse points ``pts`` (vehicle frame) that lie on the field (``cued`` False: in no
    novel or learned-cue cell), 0 < x <= ``canopy_max_range_m``, ``canopy_min_m`` <= h <=
    ``canopy_max_m``; None when fewer than ``canopy_min_points`` are left."""
    sel = ((~cued) & (h >= o.canopy_min_m) & (h <= o.canopy_max_m) & (pts[:, 0] > 0)
           & (pts[:, 0] <= o.canopy_max_range_m))
    if np.count_nonzero(sel) < o.canopy_min_points:
        return None
    return float(np.quantile(h[sel], o.canopy_quantile))


def rescale_mask(mask: np.ndarray, f: int, k: int, out_hw: tuple[int, int]) -> np.ndarray:
    """A uint8 mask made at 1/``f`` of the camera's resolution, at 1/``k`` (``f``, ``k`` powers
    of two) and of size ``out_hw``: nearest-neighbour up, or 'any pixel set' down (what
    area-averaging a nearest-upsampled full-resolution mask and testing > 0 gives)."""
    h, w = out_hw
    if k == f:
        out = mask
    elif k < f:
        r = f // k
        out = np.repeat(np.repeat(mask, r, axis=0), r, axis=1)
    else:
        r = k // f
        mh, mw = mask.shape[0] // r * r, mask.shape[1] // r * r
        out = (cv2.resize(mask[:mh, :mw], (mw // r, mh // r), interpolation=cv2.INTER_AREA)
               > 0).astype(np.uint8) * 255
    if out.shape[:2] == (h, w):
        return out
    full = np.zeros((h, w), np.uint8)
    hh, ww = min(h, out.shape[0]), min(w, out.shape[1])
    full[:hh, :ww] = out[:hh, :ww]
    return full


def coarse_mask(mask: np.ndarray, f: int, g: int, out_hw: tuple[int, int]) -> np.ndarray:
    """Boolean (h, w) = ``out_hw`` mask at 1/``g`` of the camera's resolution: a coarse pixel
    is set when any camera pixel under it is set in ``mask`` (made at 1/``f``)."""
    h, w = out_hw
    if g % f:                                       # not a whole number of mask pixels
        return rescale_mask(rescale_mask(mask, f, 1, (mask.shape[0] * f, mask.shape[1] * f)),
                            1, g, out_hw) > 0
    r = g // f
    sub = np.zeros((h * r, w * r), np.uint8)
    hh, ww = min(h * r, mask.shape[0]), min(w * r, mask.shape[1])
    sub[:hh, :ww] = mask[:hh, :ww]
    if r == 1:
        return sub > 0
    return cv2.resize(sub, (w, h), interpolation=cv2.INTER_AREA) > 0


class StereoNoveltyPipeline(Pipeline):
    name = "stereo-novelty"
    requires = ("stereo",)
    config_class = StereoNoveltyConfig
    cue_domain = "stereo"              # the learned cue models this pipeline takes

    def __init__(self, options=None, background: bool = True, cue_model=None):
        super().__init__(options)
        o = self.options
        check_matcher(o.matcher, f"perception.{self.name}")
        self.cue = LearnedCue(o.cue, self.cue_domain, o.cue_model, o.cue_threshold, o.cue_threads,
                              model=cue_model)
        self.novelty = NoveltyDetector(self.options, background=background)
        self._stereo = StereoPipeline(self.options)
        self.last = None                       # (NoveltyResult, camera mask, exclude) for tools
        self._cue_matcher, self._cue_key = None, None
        self._pyramid: dict = {}
        self._coarse = None                    # (disparity, factor) of this frame's depth cue
        self._ground = GroundModel.level()     # this frame's ground (ground_fit)
        self._laser_ground = None              # this frame's fit for the laser (ground_for_laser)
        self._source_masks: dict = {}          # cue name -> camera mask (1/kd) of this frame
        self._canopy_src = None                # (points, pixels, factor) of the coarse pass
        self._canopies: deque = deque(maxlen=self.options.canopy_frames)   # canopy_floor
        # recall_frames: per recent frame its obstacle points (vehicle frame, x y z), moved
        # with the vehicle each frame; the stamp of the last move
        self._recall: deque = deque(maxlen=max(1, self.options.recall_frames))
        self._recall_ns: int | None = None

    # ---- the regions that get dense stereo -------------------------------------------------
    def _cells_to_match(self, res, size_wh: tuple[int, int], extra: dict) -> np.ndarray:
        """THE place where the mask of what is matched is formed: camera-frame uint8 (H, W),
        255 = match. The novelty mask (stabilised cells, back through the inverse transform)
        OR every extra cue in ``extra`` (name -> camera-frame cell mask (rows, cols) bool on the
        ``res.cell_px`` grid, or an (H, W) pixel mask). A new cue is one more entry there."""
        W, H = size_wh
        mask = mask_to_camera(res.mask, res.affine, (W, H), res.cell_px)
        gate = self.options.novelty_gate
        if gate == "off":
            mask = np.zeros_like(mask)
        self._source_masks = {"novelty": mask}
        if gate == "all":
            mask = np.full_like(mask, 255)
        for name, cue in extra.items():
            if cue is None or not np.any(cue):
                continue
            if cue.shape != (H, W):
                up = cv2.resize(cue.astype(np.uint8) * 255,
                                (cue.shape[1] * res.cell_px, cue.shape[0] * res.cell_px),
                                interpolation=cv2.INTER_NEAREST)[:H, :W]
                cue = np.zeros((H, W), np.uint8)
                cue[:up.shape[0], :up.shape[1]] = up
            cm = (cue > 0).astype(np.uint8) * 255
            self._source_masks[name] = cm
            mask = cv2.bitwise_or(mask, cm)
        return mask

    def _pair(self, fr, k: int):
        """The frame's left/right images downscaled by ``k`` (a power of two), each level made
        from the one above it and kept for the rest of this frame."""
        cache = self._pyramid
        if cache.get("frame") is not fr:
            cache.clear()
            cache["frame"] = fr
            cache[1] = (fr.left, fr.right)
        if k not in cache:
            up = self._pair(fr, k // 2)
            cache[k] = (downscale(up[0], 2), downscale(up[1], 2))
        return cache[k]

    def _pair_for(self, fr, k: int, matcher):
        """:meth:`_pair` as ``matcher`` takes it: grey (converted once per frame and level)
        when the matcher matches grey."""
        return self._grey_pair(fr, k) if matcher.grey_input else self._pair(fr, k)

    def _grey_pair(self, fr, k: int):
        """The pair at 1/``k``, grey (converted once per frame and level, shared with a grey
        matcher's :meth:`_pair_for`)."""
        cache = self._pyramid
        key = ("grey", k)
        if cache.get("frame") is not fr or key not in cache:
            left, right = self._pair(fr, k)
            cache[key] = tuple(x if x.ndim == 2 else cv2.cvtColor(x, cv2.COLOR_BGR2GRAY)
                               for x in (left, right))
        return cache[key]

    def _extra_cues(self, fr, vehicle, res, kd: int) -> dict:
        """Cues beyond novelty (none in the paper), each a camera-frame cell mask on the
        novelty grid (``res.cell_px`` cells of the image at 1/``kd``)."""
        o: StereoNoveltyConfig = self.options
        cues = {}
        if o.depth_cue != "off":
            cues["depth"] = self._depth_cue(fr, vehicle, res, kd)
        if o.recall_frames > 0:
            cues["recent"] = self._recall_cue(fr, vehicle, res, kd)
        if self.cue.enabled:
            # on the camera-frame image the novelty grid was computed on (1/kd); a pixel mask
            # of that size (the model's cells need not be the novelty grid's)
            img = self._pair(fr, kd)[0]
            cues["learned"] = self.cue.mask(img, img.shape[:2], o.cue_dilate_cells,
                                            o.cue_open_cells)
        return cues

    def notes(self) -> dict:
        return self.cue.notes()

    def _recall_cue(self, fr, vehicle, res, kd: int) -> np.ndarray | None:
        """``recall_frames``: the novelty cells (camera frame, 1/``kd``) where the obstacle
        points of the last frames lie now, the vehicle's motion since taken into account
        (a point fixed in the world); None when there are none."""
        o: StereoNoveltyConfig = self.options
        dt = 0.0 if self._recall_ns is None else (fr.stamp_ns - self._recall_ns) * 1e-9
        self._recall_ns = fr.stamp_ns
        if dt < 0 or dt > 2.0:                 # a clock step or a gap: the past means nothing
            self._recall.clear()
        elif dt > 0 and vehicle is not None:
            for i, p in enumerate(self._recall):
                if len(p):
                    q = p.copy()
                    q[:, :2] = move_with_vehicle(p[:, :2], dt, vehicle)
                    self._recall[i] = q
        pts = [p for p in self._recall if len(p)]
        if not pts:
            return None
        p = np.concatenate(pts)
        cal = scaled_calibration(fr.calib, kd)
        cam = cal.camera
        u, v, ahead = pixels_of(p, cam.fx, cam.fy, cam.cx, cam.cy,
                                cal.mount.camera_to_vehicle(), cal.mount.position)
        if not ahead.any():
            return None
        u, v = u[ahead], v[ahead]
        rows, cols = res.mask.shape
        ci, cj = np.floor(v / res.cell_px), np.floor(u / res.cell_px)
        ok = (ci >= 0) & (ci < rows) & (cj >= 0) & (cj < cols)
        out = np.zeros((rows, cols), bool)
        out[ci[ok].astype(np.int64), cj[ok].astype(np.int64)] = True
        return dilate_cells(out, o.recall_dilate_cells) if out.any() else None

    def _remember(self, pts: np.ndarray, cands=()) -> None:
        """``recall_frames``: keep this frame's obstacle points (one per 0.1 m cube: a tall
        thing keeps its height, whose cells are one above the other); with
        ``recall_min_width_m`` only those on a candidate that wide, and nothing before the
        novelty model holds ``recall_min_updates`` updates."""
        o: StereoNoveltyConfig = self.options
        if o.recall_frames <= 0:
            return
        if self.novelty.model.updates < o.recall_min_updates:
            pts = pts[:0]
        elif o.recall_min_width_m > 0 and len(pts):
            pts = pts[on_footprints(pts, [c for c in cands
                                          if c.width_m >= o.recall_min_width_m], 0.05)]
        if not len(pts):
            self._recall.append(np.zeros((0, 3)))
            return
        key = np.floor(pts / 0.1).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)
        self._recall.append(np.asarray(pts, np.float64)[np.sort(first)])

    def _depth_cue(self, fr, vehicle, res, kd: int) -> np.ndarray:
        """Coarse full-frame stereo (``depth_cue`` matcher, image at most
        ``depth_cue_width_px`` wide): a cell is raised when at least ``depth_cue_min_fraction``
        of its coarse pixels reproject into the height band within ``max_range_m``."""
        o: StereoNoveltyConfig = self.options
        disp, kc, calib, pts, px = self._coarse_pass(fr, vehicle, o.depth_cue)
        self._coarse = (disp, kc)
        h = self._coarse_heights(pts, calib)
        inb = band_mask(pts, h, o.band_min_m, o.band_max_m,
                        min(o.max_range_m, o.depth_cue_max_range_m))
        rows, cols = res.mask.shape
        cell = res.cell_px * kd / float(kc)              # a novelty cell in coarse pixels
        ci = np.minimum((px[inb, 1] // cell).astype(np.int64), rows - 1)
        cj = np.minimum((px[inb, 0] // cell).astype(np.int64), cols - 1)
        ok = (px[inb, 1] < rows * cell) & (px[inb, 0] < cols * cell)
        counts = np.bincount(ci[ok] * cols + cj[ok], minlength=rows * cols).reshape(rows, cols)
        if o.canopy_floor:
            self._canopy_src = (pts, px, kc)
        raised = counts >= o.depth_cue_min_fraction * cell * cell
        return dilate_cells(raised, o.depth_cue_dilate_cells)

    def _coarse_heights(self, pts: np.ndarray, calib) -> np.ndarray:
        """Heights of the coarse pass's points; with ``ground_fit`` the frame's ground is
        fitted to them here (every other height of the frame is taken above it)."""
        o: StereoNoveltyConfig = self.options
        h, self._ground = local_heights(pts, o, calib.mount.z_m)
        if o.ground_for_laser and not o.ground_fit:
            from .ground import fit_ground
            self._laser_ground = fit_ground(pts, x_max_m=min(o.ground_max_range_m,
                                                             o.max_range_m))
        if o.ground_local:
            self._coarse_pts = pts
        if o.ground_local and not o.ground_local_cue:
            # the depth cue only chooses what is matched densely: it raises cells by the
            # heights above the base ground (level or fit); the local ground judges the dense
            # points
            h = heights_above(self._ground.base, pts, o, calib.mount.z_m)
        return h

    def _coarse_pass(self, fr, vehicle, matcher: str):
        """Full-frame matching at depth_cue_width_px with ``matcher`` (the depth cue's, or BM
        for the ground alone): (disparity, scale factor, scaled calibration, points, pixels)."""
        o: StereoNoveltyConfig = self.options
        H, W = fr.left.shape[:2]
        kc = match_factor(W, o.depth_cue_width_px)
        calib = scaled_calibration(fr.calib, kc)
        key = (matcher, calib.camera.fx, calib.baseline_m)
        if self._cue_key != key:
            self._cue_matcher = make_matcher(replace(o, matcher=matcher,
                                                     block_size=o.depth_cue_block,
                                                     speckle_window=o.depth_cue_speckle_px),
                                             calib.camera.fx, calib.baseline_m)
            self._cue_key = key
        left, right = self._pair_for(fr, kc, self._cue_matcher)
        h, w = left.shape[:2]
        disp, _ = disparity_regions(self._cue_matcher, left, right, [(0, 0, w, h)],
                                    pad_left=o.pad_left)
        drop_dark(disp, left, o.dark_level)
        pts, px = points_from_disparity(disp, calib, None, 1, vehicle, o.use_attitude)
        return disp, kc, calib, pts, px

    def _ground_only(self, fr, vehicle) -> None:
        """``ground_fit`` / ``ground_local`` without the depth cue: the coarse pass for the
        ground alone."""
        _, _, calib, pts, _ = self._coarse_pass(fr, vehicle, "bm")
        self._coarse_heights(pts, calib)

    def _seen_disparity(self, box, k: int) -> float | None:
        """The largest coarse disparity (depth cue pass) inside ``box`` (matching resolution
        1/k), in matching-resolution pixels times ``near_margin``; None without a coarse
        pass this frame."""
        if self._coarse is None:
            return None
        disp, kc = self._coarse
        f = kc / float(k)                           # coarse px -> matching px
        x0, y0, x1, y1 = box
        sub = disp[int(y0 // f):int(math.ceil(y1 / f)), int(x0 // f):int(math.ceil(x1 / f))]
        return float(sub.max()) * f * self.options.near_margin if sub.size else 0.0

    def _near_disparities(self, calib, nd: int) -> int:
        """``near_min_depth_m`` as a search range at ``calib``'s resolution (a multiple of 16,
        at least ``nd``)."""
        z = self.options.near_min_depth_m
        if z <= 0:
            return nd
        return max(nd, int(math.ceil(calib.camera.fx * calib.baseline_m / z / 16.0)) * 16)

    def _boxes(self, cam_mask: np.ndarray, f: int, full_hw: tuple[int, int], k: int, calib_k,
               nd: int, vehicle):
        """Boxes (at matching resolution, 1/k) covering the mask (at 1/``f`` of the camera's
        ``full_hw``) and their search ranges.

        Regions are found on a mask 8x smaller than the camera's image (boxes grow by up to
        8 px): cheaper than labelling the full-resolution mask. With ``ground_range`` each
        region's box is cut into column bands of ``band_cols``, each trimmed to the rows its
        mask occupies; the foot of a
        band (for ``near_from_foot``) is the lowest masked row of it and its two neighbours in
        the same region (an overhang up to one band wide is still searched from its foot), and
        each band is cut into strips of ``strip_rows`` with their own range
        (:func:`strip_boxes`). Returns (boxes, ranges, parts); ``parts`` (for
        :func:`disparity_regions`) only with ``merge_bands``, else None."""
        o: StereoNoveltyConfig = self.options
        H, W = full_hw
        g = 8
        small = coarse_mask(cam_mask, f, g, (H // g, W // g))
        h, w = H // k, W // k
        sc = lambda v, hi: min(hi, v * g // k)                       # noqa: E731
        scu = lambda v, hi, full: hi if v * g >= full else min(hi, -(-v * g // k))  # noqa: E731
        regions = mask_boxes(small.astype(np.uint8), 0)
        if not o.ground_range:
            return [(sc(x0, w), sc(y0, h), scu(x1, w, W // g * g), scu(y1, h, H // g * g))
                    for (x0, y0, x1, y1) in regions], None, None
        bw = max(1, (o.band_cols * k) // g) if o.band_cols > 0 else None
        nd_near = self._near_disparities(calib_k, nd)
        boxes, ranges = [], []
        parts = [] if o.merge_bands else None
        for (x0, y0, x1, y1) in regions:
            region_b, region_r = [], []
            cuts = list(range(x0, x1, bw)) if bw else [x0]
            bands = []
            for i, c0 in enumerate(cuts):
                c1 = cuts[i + 1] if i + 1 < len(cuts) else x1
                rows = np.flatnonzero(small[y0:y1, c0:c1].any(axis=1))
                bands.append(None if len(rows) == 0 else (c0, y0 + rows[0], c1, y0 + rows[-1] + 1))
            for i, b in enumerate(bands):
                if b is None:
                    continue
                feet = [bands[j][3] for j in (i - 1, i, i + 1)
                        if 0 <= j < len(bands) and bands[j] is not None]
                bx = (sc(b[0], w), sc(b[1], h), scu(b[2], w, W // g * g),
                      scu(b[3], h, H // g * g))
                foot = scu(max(feet), h, H // g * g) - 1
                seen = self._seen_disparity(bx, k)
                bb, rr = strip_boxes(calib_k, [bx], nd, vehicle, o.strip_rows,
                                     o.ground_slack_m, o.pitch_slack_deg,
                                     o.near_from_foot and seen is not None, foot_row=foot,
                                     seen_max_disp=seen or 0.0, nd_near=nd_near)
                region_b += bb
                region_r += rr
            if o.merge_bands:
                region_b, region_r, region_p = merge_strips(
                    region_b, region_r, self._stereo.matcher_for(calib_k).margin,
                    max_width=o.merge_max_cols)
                parts += region_p
            boxes += region_b
            ranges += region_r
        return boxes, ranges, parts

    def process(self, inputs: SensorInputs) -> Detections:
        fr = inputs.stereo
        o: StereoNoveltyConfig = self.options
        self.cue.check()                  # a required cue that cannot run: no decision at all
        cam = fr.calib.camera
        K = cam.matrix()
        M = fr.calib.mount.camera_to_vehicle()
        H, W = fr.left.shape[:2]
        self._coarse = None
        self._canopy_src = None
        swapped = self.novelty.set_aside_other_light(fr.illumination)
        if swapped:
            log.warning("%s: the novelty model loaded at start was learnt by day and the "
                        "strobe lights these frames: set aside%s", self.name,
                        " for the strobe-lit model saved beside it" if swapped == "night model"
                        else ", learning afresh (with the boot check)")
        t0, c0 = time.perf_counter(), time.thread_time()
        kd = match_factor(W, o.descriptor_width_px)
        if kd > 1:
            Kd = scaled_calibration(fr.calib, kd).camera.matrix()
            cell = (int(o.cell_px) // kd) if o.cell_px else None
            res = self.novelty.detect(self._pair(fr, kd)[0], Kd, M, inputs.vehicle, cell)
        else:
            res = self.novelty.detect(fr.left, K, M, inputs.vehicle)
        t1, c1 = time.perf_counter(), time.thread_time()
        self._ground = GroundModel.level()
        self._laser_ground = None
        self._coarse_pts = None
        if (o.ground_fit or o.ground_local or o.ground_for_laser) and o.depth_cue == "off":
            self._ground_only(fr, inputs.vehicle)
        extra = self._extra_cues(fr, inputs.vehicle, res, kd)
        t1c, c1c = time.perf_counter(), time.thread_time()
        # the mask of what is matched, at the descriptor resolution (1/kd); the matching
        # resolution's mask and the boxes' coarse mask are made from it, never from an image of
        # the camera's full size (that round trip cost ~2 ms a frame at 1280x1024)
        cam_mask = self._cells_to_match(res, (W // kd, H // kd), extra)
        k = match_factor(W, o.match_width_px)
        calib = scaled_calibration(fr.calib, k)
        matcher = self._stereo.matcher_for(calib)
        left, right = self._pair_for(fr, k, matcher)
        sel = rescale_mask(cam_mask, kd, k, left.shape[:2])
        boxes, ranges, parts = self._boxes(cam_mask, kd, (H, W), k, calib, matcher.nd,
                                           inputs.vehicle)
        disp, work = disparity_regions(matcher, left, right, boxes, ranges, parts,
                                        pad_left=o.pad_left)
        if o.dark_level > 0 and boxes:
            # only the matched boxes: the rest of the disparity is 0 anyway
            for (x0, y0, x1, y1) in boxes:
                drop_dark(disp[y0:y1, x0:x1], left[y0:y1, x0:x1], o.dark_level)
        t2, c2 = time.perf_counter(), time.thread_time()
        pts, px = points_from_disparity(disp, calib, sel, max(1, o.point_stride // k),
                                        inputs.vehicle, o.use_attitude)
        ground = self._ground
        if o.ground_local and o.ground_local_dense and len(pts):
            # the dense points see the ground around what was matched (the coarse pass is
            # sparse on far stubble: 15 m ahead only an object's own bins had coarse points)
            src = pts if self._coarse_pts is None else np.concatenate([self._coarse_pts, pts])
            ground = self._ground = local_ground_of(src, o, getattr(ground, "base", ground))
        h = heights_above(ground, pts, o, calib.mount.z_m)
        keep = band_mask(pts, h, o.band_min_m, o.band_max_m, o.max_range_m)
        low_added = None
        if (0 < o.low_band_min_m < o.band_min_m and len(pts)
                and (o.low_band_night or fr.illumination == "day")
                and self.novelty.model.updates >= o.low_band_min_updates):
            low = band_mask(pts, h, o.low_band_min_m, o.band_min_m, o.max_range_m) & ~keep
            if low.any():
                idx = np.flatnonzero(low)
                low_added = np.zeros(len(pts), bool)
                names = ("novelty", "learned")
                if o.low_band_max_novel_share > 0:
                    names = ("novelty-compact", "learned")
                    self._compact_novelty(o.low_band_max_novel_share)
                low_added[idx[self._other_cue(px[idx], k / float(kd), names)]] = True
                keep |= low_added
        canopy, under_canopy = self._below_canopy(pts, px, h, keep, ground, calib.mount.z_m,
                                                  k, kd)
        if o.support_min > 0 and keep.any():
            idx = np.flatnonzero(keep)
            sup = vertical_support(disp, px[idx], pts[idx], calib, ground,
                                   vehicle=inputs.vehicle, use_attitude=o.use_attitude,
                                   known_min=o.support_known_min)
            keep[idx[sup < o.support_min]] = False
        ncc_dropped = self._drop_poor_matches(fr, k, calib, disp, px, keep)
        self._drop_stalks(pts, px, h, keep, k / float(kd))
        xy = dedupe_cells(pts[keep, :2])
        cands = self._candidates(disp, pts[keep], px[keep], h[keep], k / float(kd))
        self._remember(pts[keep], cands)
        t3, c3 = time.perf_counter(), time.thread_time()
        # obstacle-mask feedback: cells near what was just detected are never learnt
        fb = keep if low_added is None or o.low_band_feedback else keep & ~low_added
        if under_canopy is not None:
            # what the canopy took is no obstacle, but nor is it field the box can vouch for:
            # it stays out of the update as before (learnt, an obstacle seen far off by its
            # lower part, which the depth cue raised, was field by the time it came near:
            # tests/test_canopy.py, the cattle)
            fb = fb | under_canopy
        exclude = obstacle_cells(px[fb] * (k / kd), res.mask.shape, res.cell_px,
                                 self._margin_px(W, kd))
        boot = None
        if o.boot_guard and not self.novelty.first_sent:
            boot = self._boot_check(fr, inputs.vehicle, res, kd, extra)
            if len(boot["xy"]):
                xy = dedupe_cells(np.concatenate([xy, boot["xy"]]))
                cands = tuple(cands) + boot["candidates"]
        self.novelty.learn(res, exclude, first_exclude=None if boot is None else boot["exclude"],
                           light=fr.illumination)
        t4, c4 = time.perf_counter(), time.thread_time()
        self.last = (res, cam_mask, exclude)     # cam_mask at the descriptor resolution
        self.last_points = (pts, px, h, keep, k)  # for tools: this frame's dense points
        self.last_disp = disp                    # for tools: the matched disparity (1/k)
        self._pyramid.clear()
        self._coarse = None
        rows, cols = res.mask.shape
        h, w = left.shape[:2]
        for_laser = None
        if o.ground_for_laser and not o.use_attitude:   # the vehicle frame, as the laser's
            for_laser = self._laser_ground if self._laser_ground is not None else ground
            if getattr(for_laser, "source", "level") == "level":
                for_laser = None                         # no fit this frame: nothing to say
        # what this camera saw where, for the laser's returns ([grid] laser_confirm_by): the
        # masks at the descriptor resolution, half a novelty cell of slack up and down
        view = CameraView(self._source_masks, Kd if kd > 1 else K, M, fr.calib.mount.position,
                          o.max_range_m, slack_px=res.cell_px // 2,
                          min_depth_m=(o.near_min_depth_m if o.near_view and
                                       o.near_min_depth_m > 0 else o.min_depth_m),
                          stereo_look=StereoLook(fr.left, fr.right, cam.fx, cam.fy, cam.cx,
                                                 cam.cy, fr.calib.baseline_m, M,
                                                 fr.calib.mount.position))
        return Detections(points_xy=xy, candidates=cands, ground=for_laser, view=view, debug={
            "ground": ground.to_dict(), "candidates": len(cands),
            "boot": None if boot is None else {"candidates": len(boot["candidates"]),
                                               "excluded_cells": int(boot["exclude"].sum())},
            "novel_fraction": float(res.mask.mean()),
            "canopy": None if not o.canopy_floor else {
                "height_m": canopy,
                "dropped_points": 0 if under_canopy is None else int(under_canopy.sum())},
            "novel_cells_raw": int(res.raw.sum()),
            "ncc_dropped": ncc_dropped,
            # cells of the novelty grid each cue raised (a pixel mask counts in cell areas)
            "cue_cells": {n: int(np.count_nonzero(c)) if c.shape == res.mask.shape else
                          int(round(np.count_nonzero(c) / float(res.cell_px ** 2)))
                          for n, c in extra.items() if c is not None},
            "model_samples": self.novelty.model.size,
            "model_updates": self.novelty.model.updates,
            "stereo_px_fraction": work / float(h * w),
            "match_factor": k, "descriptor_factor": kd,
            "boxes": len(boxes),
            "stabiliser": self.novelty.stabiliser.source,
            "grid": (rows, cols), "cell_px": res.cell_px,
            "ms": {"novelty": 1e3 * (t1 - t0), "cues": 1e3 * (t1c - t1),
                   "stereo": 1e3 * (t2 - t1c), "points": 1e3 * (t3 - t2),
                   "learn": 1e3 * (t4 - t3)},
            # the same stages in this thread's CPU time (not inflated by other processes)
            "cpu_ms": {"novelty": 1e3 * (c1 - c0), "cues": 1e3 * (c1c - c1),
                       "stereo": 1e3 * (c2 - c1c), "points": 1e3 * (c3 - c2),
                       "learn": 1e3 * (c4 - c3)}})

    def _boot_check(self, fr, vehicle, res, kd: int, extra: dict) -> dict:
        """Full-frame dense stereo (the pipeline's matcher at matching resolution) before the
        novelty model has been initialised: its candidates of at least ``boot_min_points``
        points are this frame's obstacles, and their cells (grown by ``obstacle_margin_px``)
        plus the learned cue's cells are the first update's ``first_exclude``."""
        o: StereoNoveltyConfig = self.options
        H, W = fr.left.shape[:2]
        k = match_factor(W, o.match_width_px)
        calib = scaled_calibration(fr.calib, k)
        matcher = self._stereo.matcher_for(calib)
        left, right = self._pair_for(fr, k, matcher)
        h, w = left.shape[:2]
        nb = matcher.nd if not o.near_boot else self._near_disparities(calib, matcher.nd)
        disp, _ = disparity_regions(matcher, left, right, [(0, 0, w, h)],
                                    None if nb == matcher.nd else [(0, nb)],
                                    pad_left=o.pad_left)
        drop_dark(disp, left, o.dark_level)
        pts, px = points_from_disparity(disp, calib, None, max(1, o.point_stride // k), vehicle,
                                        o.use_attitude)
        hh, g = local_heights(pts, o, calib.mount.z_m)
        keep = band_mask(pts, hh, o.band_min_m, o.band_max_m, o.max_range_m)
        smin = max(o.support_min, o.boot_support_min)
        if smin > 0 and keep.any():
            idx = np.flatnonzero(keep)
            sup = vertical_support(disp, px[idx], pts[idx], calib, g, vehicle=vehicle,
                                   use_attitude=o.use_attitude)
            keep[idx[sup < smin]] = False
        # before any model: only the learned cue can speak for a stalk
        self._drop_stalks(pts, px, hh, keep, k / float(kd), ("learned",))
        P, PX, HH = pts[keep], px[keep], hh[keep]
        conf = point_confidence(disp, PX, o.confidence_px)
        # only what the box can vouch for: enough supported points, standing on the ground
        # (a cell kept out of the first update that is only stereo noise stays novel, is
        # matched again, and its noise keeps it out of every later update: a lock-in)
        cands = tuple(c for c in cluster_candidates(P[:, :2], HH, conf, pipeline=self.name)
                      if c.points >= o.boot_min_points and c.ground_contact)
        inside = on_footprints(P, cands, 0.2)
        rows, cols = res.mask.shape
        exclude = obstacle_cells(PX[inside] * (k / kd), (rows, cols), res.cell_px,
                                 self._margin_px(W, kd))
        # only below the horizon (a cell's top at least one cell under it): the sky and the
        # skyline are learnt whatever the boot pass matched there. A textureless sky gets
        # smooth false disparities that pass every check; kept out of the first update it
        # stays novel, is matched on every frame and its false obstacles keep it out of every
        # later update (measured: 3.0 -> 7.5 false cells a frame on the empty field). A
        # person 5-15 m ahead stands mostly below the horizon (feet 57-170 px under it at
        # 640 px): their body stays out of the model.
        vh = self._horizon_row(calib, vehicle) * (k / kd)
        top = np.arange(rows) * res.cell_px
        above = top < vh + o.boot_horizon_cells * res.cell_px
        exclude[above, :] = False
        if o.boot_above_horizon and inside.any():
            # the candidates' own points there, cell by cell (no margin: a margin above the
            # horizon is sky and skyline, the lock-in the rule above is for)
            near = cands
            if o.boot_above_horizon_half_width_m > 0:
                near = [c for c in cands if abs(c.y_m) - c.width_m / 2
                        <= o.boot_above_horizon_half_width_m]
            mine = on_footprints(P, near, 0.2) if near else np.zeros(len(P), bool)
            own = obstacle_cells(PX[mine] * (k / kd), (rows, cols), res.cell_px, 0.0)
            exclude |= own & above[:, None]
        cue = extra.get("learned")
        if cue is not None and np.any(cue):
            if cue.shape != (rows, cols):
                cue = cv2.resize(cue.astype(np.float32), (cols, rows),
                                 interpolation=cv2.INTER_AREA) > 0.25
            exclude |= cue.astype(bool)
        return {"exclude": exclude, "candidates": cands, "xy": P[inside, :2]}

    def _margin_px(self, width: int, kd: int) -> float:
        """``obstacle_margin_px`` in pixels of the descriptor image (the camera's ``width`` /
        ``kd``): given for an image ``obstacle_margin_ref_px`` wide, or for the camera's own
        image when that is 0."""
        o: StereoNoveltyConfig = self.options
        if o.obstacle_margin_ref_px > 0:
            return o.obstacle_margin_px * (width / float(kd)) / float(o.obstacle_margin_ref_px)
        return o.obstacle_margin_px / kd

    def _horizon_row(self, calib, vehicle) -> float:
        """The image row (of ``calib``'s image) of the level horizon, with the vehicle's pitch
        when ``use_attitude``."""
        o: StereoNoveltyConfig = self.options
        cam = calib.camera
        pitch = math.radians(calib.mount.pitch_deg)
        if o.use_attitude and vehicle is not None:
            pitch += float(vehicle.pitch_rad)
        return cam.cy - cam.fy * math.tan(pitch)

    def _below_canopy(self, pts, px, h, keep, ground, mount_z: float, k: int, kd: int):
        """``canopy_floor``: clear ``keep`` (in place) for the obstacle points under the
        field's canopy + margin that only the depth cue put into matching. Returns (the
        canopy's height or None, a mask of the points dropped or None)."""
        o: StereoNoveltyConfig = self.options
        if not o.canopy_floor or self._canopy_src is None:
            return None, None
        cpts, cpx, kc = self._canopy_src
        ch = heights_above(ground, cpts, o, mount_z)
        # the cue masks are read only for the points the quantile can take (the coarse pass
        # has tens of thousands; most are soil or out of range)
        can = np.flatnonzero((ch >= o.canopy_min_m) & (ch <= o.canopy_max_m)
                             & (cpts[:, 0] > 0) & (cpts[:, 0] <= o.canopy_max_range_m))
        now = canopy_height(ch[can], cpts[can], self._other_cue(cpx[can], kc / float(kd)), o)
        if now is not None:
            self._canopies.append(now)
        canopy = float(np.median(self._canopies)) if self._canopies else None
        if canopy is None or not keep.any():
            return canopy, None
        floor = min(canopy + o.canopy_margin_m, o.canopy_max_m)
        idx = np.flatnonzero(keep & (h < floor))
        dropped = np.zeros(len(keep), bool)
        dropped[idx[~self._other_cue(px[idx], k / float(kd))]] = True
        keep &= ~dropped
        return canopy, dropped

    def _drop_poor_matches(self, fr, k: int, calib, disp, px, keep) -> int:
        """``match_ncc_min``: clear ``keep`` (in place) for the obstacle points whose left and
        right windows do not correlate at their disparity (:func:`.stereo.match_correlation`),
        those nearer than ``match_ncc_from_m`` along the camera's axis spared. ``disp``, ``px``
        (N, 2) and ``calib`` at matching resolution (1/``k``). Returns how many were dropped."""
        o: StereoNoveltyConfig = self.options
        if o.match_ncc_min <= 0 or not keep.any():
            return 0
        idx = np.flatnonzero(keep)
        pi = px[idx].astype(np.intp)
        dk = disp[pi[:, 1], pi[:, 0]]
        if o.match_ncc_from_m > 0:
            # z-depth = fx B / d: nearer than match_ncc_from_m is d above fx B / that
            far = dk <= calib.camera.fx * calib.baseline_m / o.match_ncc_from_m
            idx, pi, dk = idx[far], pi[far], dk[far]
        gl, gr = self._grey_pair(fr, k)
        ncc = match_correlation(gl, gr, pi, dk, scale=gl.shape[1] / 640.0)
        low = ncc < o.match_ncc_min                          # (NaN: nothing said, kept)
        keep[idx[low]] = False
        return int(low.sum())

    def _drop_stalks(self, pts, px, h, keep, f: float, names=("novelty", "learned")) -> int:
        """``stalk_max_width_m``: clear ``keep`` (in place) for the obstacle points that are a
        stalk (:func:`.candidates.stalk_points`: thin, short, raised by geometry alone; the
        cues in ``names`` count as another cue). ``pts`` (N, 3), ``px`` (N, 2) at matching
        resolution, ``h`` their heights; ``f``: matching px -> descriptor px. Returns how
        many were dropped."""
        o: StereoNoveltyConfig = self.options
        if o.stalk_max_width_m <= 0 or not keep.any():
            return 0
        idx = np.flatnonzero(keep)
        other = self._other_cue(px[idx], f, names)
        st = stalk_points(pts[idx, :2], h[idx], other, o.stalk_max_width_m,
                          o.stalk_max_length_m, o.stalk_max_height_m,
                          max_range_m=o.stalk_max_range_m)
        keep[idx[st]] = False
        return int(st.sum())

    def _compact_novelty(self, max_share: float) -> None:
        """``_source_masks['novelty-compact']``: the novelty mask's connected regions that
        cover at most ``max_share`` of the image."""
        m = self._source_masks.get("novelty")
        if m is None or not m.any():
            return
        n, labels = cv2.connectedComponents((m > 0).view(np.uint8), connectivity=8,
                                            ltype=cv2.CV_32S)
        area = np.bincount(labels.ravel(), minlength=n)
        small = area <= max_share * m.size
        small[0] = False
        self._source_masks["novelty-compact"] = small[labels].view(np.uint8) * np.uint8(255)

    def _other_cue(self, px, f: float, names=("novelty", "learned")):
        """Per point (pixels ``px`` at matching resolution; ``f``: matching px -> descriptor
        px): True where a cue other than geometry (novelty, the learned cue) put the pixel
        into matching this frame."""
        out = np.zeros(len(px), bool)
        for key, m in getattr(self, "_source_masks", {}).items():
            if key not in names:
                continue
            u = np.minimum((px[:, 0] * f).astype(np.intp), m.shape[1] - 1)
            v = np.minimum((px[:, 1] * f).astype(np.intp), m.shape[0] - 1)
            out |= m[v, u] > 0
        return out

    def _candidates(self, disp, pts, px, h, f: float):
        """The frame's obstacle points as candidates: per-point confidence from the dense
        disparity, per-point cue flags from the masks that put the pixel into matching
        (``f``: matching px -> descriptor-resolution px)."""
        o: StereoNoveltyConfig = self.options
        if len(pts) == 0:
            return ()
        conf = point_confidence(disp, px, o.confidence_px)
        flags = {}
        names = {"novelty": "novelty", "learned": "cue"}
        for key, m in getattr(self, "_source_masks", {}).items():
            if key not in names:
                continue                      # the depth cue is geometry (the base source)
            u = np.minimum((px[:, 0] * f).astype(np.intp), m.shape[1] - 1)
            v = np.minimum((px[:, 1] * f).astype(np.intp), m.shape[0] - 1)
            flags[names[key]] = m[v, u] > 0
        return cluster_candidates(pts[:, :2], h, conf, flags, pipeline=self.name)

    def close(self) -> None:
        self.novelty.close()
