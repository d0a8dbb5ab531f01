"""The learned cue inside a pipeline: required, optional or off (issue #8).

``LearnedCue`` holds a loaded :class:`appliance.cue_model.CueModel` (read once, at construction,
outside the per-frame code) and turns an image into a per-pixel "obstacle-like" mask:

- ``mode = "off"``: nothing is loaded, nothing runs;
- ``mode = "optional"``: a model that cannot be loaded, or an inference that fails, leaves the
  pipeline running without the cue; :meth:`notes` says so (the status page shows it);
- ``mode = "required"``: the same failures raise :class:`CueUnavailable` from the pipeline's
  ``process`` -- the loop reports a pipeline fault and the gate holds STOP, naming the reason.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.schema import _f
from hal.errors import FieldguardError

from .cue_features import cell_features, scale_to_width

log = logging.getLogger("fieldguard.cue")

CUE_MODES = ("off", "optional", "required")


@dataclass(frozen=True)
class CueOptions:
    """The learned cue's keys, the same in every pipeline table that has a cue
    (``[perception.stereo-novelty]``, ``[perception.rgbd]``)."""

    cue: str = _f("off", choices=CUE_MODES,
                  doc="beyond the papers: the learned cue (ONNX, docs/learned-cue.md). "
                      "required: a missing or broken model is a fault (STOP); optional: the "
                      "box runs without it and says so in status")
    cue_model: str = _f("", doc="cue model file from `fieldguard train-cue`; empty = the model "
                                "shipped for the pipeline (appliance/models/)")
    cue_threshold: float = _f(0.0, lo=0.0, hi=1.0,
                              doc="P(obstacle-like) above which a cell counts; 0 = the "
                                  "threshold stored in the model")
    cue_threads: int = _f(1, lo=1, hi=8, doc="cue: onnxruntime intra-op threads")
    cue_open_cells: int = _f(2, lo=0, hi=8, doc="cue: a cell counts only inside a square block "
                                                "of this many obstacle-like cells (0/1 = any)")


class CueUnavailable(FieldguardError):
    """A required learned cue cannot run (missing/broken model, failed inference)."""


class LearnedCue:
    def __init__(self, mode: str, domain: str, model_path: str = "", threshold: float = 0.0,
                 threads: int = 1, model=None):
        if mode not in CUE_MODES:
            raise ValueError(f"cue mode {mode!r}; expected one of {', '.join(CUE_MODES)}")
        self.mode, self.domain = mode, domain
        self.model = None
        self.error: str | None = None
        self.failures = 0
        self.runs = 0
        self._threshold = threshold
        if mode == "off":
            return
        if model is not None:
            self.model = model
        else:
            from appliance.cue_model import load_cue_model   # the file is read outside perception
            try:
                self.model = load_cue_model(model_path or None, domain, threads)
            except FieldguardError as exc:
                self.error = str(exc)
                (log.error if mode == "required" else log.warning)(
                    "learned cue %s: %s", "REQUIRED and unavailable" if mode == "required"
                    else "unavailable, running without it", exc)

    @property
    def enabled(self) -> bool:
        return self.mode != "off"

    @property
    def available(self) -> bool:
        return self.model is not None

    @property
    def threshold(self) -> float:
        if self._threshold > 0:
            return self._threshold
        return self.model.info.threshold if self.model is not None else 0.5

    def check(self) -> None:
        """Raise CueUnavailable when the cue is required and cannot run."""
        if self.mode == "required" and self.model is None:
            raise CueUnavailable(f"learned cue required but unavailable: {self.error}")

    def scores(self, bgr: np.ndarray, depth_m: np.ndarray | None = None
               ) -> tuple[np.ndarray, float] | None:
        """(P(obstacle-like) per cell (rows, cols), cell size in pixels of ``bgr``), or None
        when the cue is off or (optional) unavailable. The image (and the registered depth, for
        a model of the depth feature set) is resized to the width the model was trained at."""
        if self.model is None:
            self.check()
            return None
        info = self.model.info
        k = info.image_width_px / float(bgr.shape[1])
        uses_depth = getattr(self.model, "uses_depth", False)
        if uses_depth and depth_m is None:
            raise CueUnavailable(f"cue model {self.model.path} needs registered depth "
                                 "(an RGB-D model), and none was given")
        img, depth = scale_to_width(bgr, info.image_width_px, info.cell_px,
                                    depth_m if uses_depth else None)
        try:
            feats = cell_features(img, info.cell_px, depth)
            p = self.model.score(feats.reshape(-1, feats.shape[-1])).reshape(feats.shape[:2])
        except Exception as exc:
            self.failures += 1
            msg = f"learned cue failed: {type(exc).__name__}: {exc}"
            if self.mode == "required":
                raise CueUnavailable(msg) from exc
            if self.failures == 1 or self.failures % 100 == 0:
                log.warning("%s (optional: running without it; %d failures)", msg,
                            self.failures)
            self.error = msg
            return None
        self.runs += 1
        return p, info.cell_px / k

    def mask(self, bgr: np.ndarray, out_shape: tuple[int, int], dilate_cells: int = 0,
             open_cells: int = 0, erode_px: int = 0, depth_m: np.ndarray | None = None,
             min_depth_valid: float = 0.0) -> np.ndarray | None:
        """bool (H, W) = ``out_shape`` pixel mask of the obstacle-like cells of ``bgr`` (which
        may be of another size: the mask is scaled to ``out_shape``), or None (see scores).
        ``open_cells`` > 1: only cells that are part of an ``open_cells`` square block of
        obstacle-like cells count (a morphological opening: a lone cell is no obstacle);
        ``dilate_cells``: then grown by that many cells; ``erode_px``: the pixel mask then
        shrunk by that many pixels (a cell on an obstacle's outline is partly background).
        ``min_depth_valid`` > 0 (with ``depth_m``): a cell with less valid depth than that share
        is not obstacle-like here (a shiny object's cells hold only the depth of what is
        around it; depth holes have their own rule)."""
        got = self.scores(bgr, depth_m)
        if got is None:
            return None
        p, _cell = got
        cells = (p > np.float32(self.threshold)).astype(np.uint8)
        if min_depth_valid > 0 and depth_m is not None and cells.any():
            rows, cols = cells.shape
            c = _cell * depth_m.shape[1] / float(bgr.shape[1])
            hh, ww = int(round(rows * c)), int(round(cols * c))
            valid = (depth_m[:hh, :ww] > 0).astype(np.float32)
            frac = cv2.resize(valid, (cols, rows), interpolation=cv2.INTER_AREA)
            cells[frac < np.float32(min_depth_valid)] = 0
        if open_cells > 1 and cells.any():
            cells = cv2.morphologyEx(cells, cv2.MORPH_OPEN,
                                     np.ones((open_cells, open_cells), np.uint8))
        if dilate_cells > 0 and cells.any():
            k = 2 * dilate_cells + 1
            cells = cv2.dilate(cells, np.ones((k, k), np.uint8))
        H, W = out_shape
        rows, cols = cells.shape
        # the cells cover the image but a partial cell at the right/bottom edge
        up = cv2.resize(cells, (int(round(cols * _cell * W / bgr.shape[1])),
                                int(round(rows * _cell * H / bgr.shape[0]))),
                        interpolation=cv2.INTER_NEAREST)
        out = np.zeros((H, W), np.uint8)
        hh, ww = min(H, up.shape[0]), min(W, up.shape[1])
        out[:hh, :ww] = up[:hh, :ww]
        if erode_px > 0 and out.any():
            out = cv2.erode(out, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
        return out.view(bool)

    def notes(self) -> dict:
        """For the status page: what the cue is doing."""
        if self.mode == "off":
            return {"cue": "off"}
        if self.model is None:
            state = ("UNAVAILABLE (required: STOP)" if self.mode == "required"
                     else "unavailable (optional: running without it)")
            return {"cue": state, "cue_error": self.error}
        d = {"cue": f"on ({self.mode})", "cue_model": self.model.path,
             "cue_threshold": round(self.threshold, 4), "cue_runs": self.runs}
        if self.failures:
            d["cue_failures"] = self.failures
            d["cue_error"] = self.error
        return d
