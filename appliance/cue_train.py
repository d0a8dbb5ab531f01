"""Training the learned cue from run folders (``fieldguard train-cue``; issue #8).

Labels come from the run format's truth: every obstacle of a frame's truth file is a box in the
vehicle frame (footprint centre, length, width, height, yaw); its eight corners projected
through the camera's mount and intrinsics give a convex silhouette in the image. A cell whose
area is at least half inside a silhouette is a positive; a cell with no silhouette pixel is a
negative, right up to the silhouette's edge (so the cue learns to stop at an obstacle's
outline, not a cell beyond it); a cell less than half inside is left out (unsure). With
RGB-D, silhouette pixels whose depth is off the box's depth span by more than 0.3 m are not
the obstacle (a bush in front of it, the path behind), and cells with less than a quarter of
their depth inside the camera's range are left out (truth lists only obstacles within the
depth range, so a far obstacle there would be a wrong negative; a cell on the edge of a bush
against the far view is kept: it is the hardest negative there is).

The model: a scikit-learn pipeline (standardisation, a two-layer perceptron) on the cell
features of appliance.perception.cue_features (59 from the image; RGB-D runs add 6 of the
depth's shape), exported to ONNX with skl2onnx and checked
against scikit-learn's own output before it is written. The decision threshold is chosen on
held-out frames (every 5th block of 10 frames of each run) as the lowest that keeps the share of
negative cells called obstacle-like at or under ``max_fpr``. Needs the ``train`` extra
(scikit-learn, skl2onnx); the box itself only runs the ONNX file.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from appliance.cue_model import INPUT_NAME, OUTPUT_NAME, VERSION, CueModel, CueModelError
from appliance.perception.cue_features import (DEPTH_FEATURE_SET, FEATURE_SET, FEATURE_SETS,
                                               cell_features, grid_shape, scale_to_width)
from drivers.runfolder import RunReader
from hal.types import Mount, PinholeCalibration

DEPTH_TOLERANCE_M = 0.3


# ---------------------------------------------------------------------------------------------
# labels from truth
# ---------------------------------------------------------------------------------------------
def box_corners(ob: dict) -> np.ndarray:
    """(8, 3) corners of a truth obstacle's box in the vehicle frame."""
    yaw = math.radians(ob.get("yaw_deg", 0.0))
    c, s = math.cos(yaw), math.sin(yaw)
    L, W = ob["length_m"] / 2.0, ob["width_m"] / 2.0
    H = ob.get("height_m") or 1.0
    out = []
    for dz in (0.0, H):
        for dx, dy in ((L, W), (L, -W), (-L, -W), (-L, W)):
            out.append((ob["x_m"] + c * dx - s * dy, ob["y_m"] + s * dx + c * dy,
                        ob.get("z_m", 0.0) + dz))
    return np.array(out, np.float64)


def project_silhouette(ob: dict, cam: PinholeCalibration, mount: Mount,
                       size_wh: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float]] | None:
    """(bool mask of the box's convex silhouette at ``size_wh``, (nearest, farthest) z-depth of
    its corners), or None when the box is not in front of the camera. ``cam`` is the
    calibration at its own size; the mask is scaled to ``size_wh``."""
    R = mount.camera_to_vehicle()                  # optical -> vehicle
    q = (box_corners(ob) - mount.position) @ R      # vehicle -> optical, row vectors
    front = q[:, 2] > 0.05
    if front.sum() < 8:                            # partly behind the camera: not labelled
        return None
    sx, sy = size_wh[0] / cam.width, size_wh[1] / cam.height
    u = (cam.fx * q[:, 0] / q[:, 2] + cam.cx) * sx
    v = (cam.fy * q[:, 1] / q[:, 2] + cam.cy) * sy
    mask = np.zeros((size_wh[1], size_wh[0]), np.uint8)
    hull = cv2.convexHull(np.stack([u, v], 1).astype(np.float32))
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    return mask.view(bool), (float(q[:, 2].min()), float(q[:, 2].max()))


def cell_labels(truth: list[dict], cam: PinholeCalibration, mount: Mount,
                size_wh: tuple[int, int], cell_px: int, depth_m: np.ndarray | None = None,
                depth_range: tuple[float, float] | None = None):
    """(label (rows, cols) int8: 1 positive, 0 negative, -1 left out; class name per cell or
    ""). ``depth_m`` (at ``size_wh``) refines silhouettes and drops cells out of range."""
    W, H = size_wh
    rows, cols = grid_shape((H, W), cell_px)
    inside = np.zeros((H, W), bool)
    owner = np.full((rows, cols), "", object)
    best = np.zeros((rows, cols), np.float32)
    for ob in truth:
        got = project_silhouette(ob, cam, mount, size_wh)
        if got is None:
            continue
        m, (z0, z1) = got
        if depth_m is not None:
            d = depth_m
            m = m & ((d <= 0) | ((d >= z0 - DEPTH_TOLERANCE_M) & (d <= z1 + DEPTH_TOLERANCE_M)))
        inside |= m
        frac = cv2.resize(m[:rows * cell_px, :cols * cell_px].astype(np.float32), (cols, rows),
                          interpolation=cv2.INTER_AREA)
        better = frac > best
        owner[better] = ob.get("class", "?")
        best = np.maximum(best, frac)
    anyfrac = cv2.resize(inside[:rows * cell_px, :cols * cell_px].astype(np.float32),
                         (cols, rows), interpolation=cv2.INTER_AREA)
    label = np.full((rows, cols), -1, np.int8)
    label[anyfrac <= 0] = 0
    label[best >= 0.5] = 1
    if depth_m is not None and depth_range is not None:
        lo, hi = depth_range
        d = depth_m[:rows * cell_px, :cols * cell_px]
        valid = ((d >= lo) & (d <= hi)).astype(np.float32)
        in_range = cv2.resize(valid, (cols, rows), interpolation=cv2.INTER_AREA) >= 0.25
        label[(label == 0) & ~in_range] = -1
    owner[label != 1] = ""
    return label, owner


# ---------------------------------------------------------------------------------------------
# data set
# ---------------------------------------------------------------------------------------------
def domain_of(reader: RunReader) -> str:
    if reader.info.stereo is not None:
        return "stereo"
    if reader.info.rgbd is not None:
        return "rgbd"
    raise CueModelError(f"run {reader.info.name!r} ({reader.path}) has neither stereo nor "
                        "RGB-D images: the learned cue needs camera images")


def frame_image(reader: RunReader, i: int, domain: str, width: int):
    """(BGR image at ``width`` px wide, depth at the same size or None, camera, mount, depth
    range), or None when the frame's images are missing."""
    if domain == "stereo":
        fr = reader.stereo(i)
        if fr is None:
            return None
        img, depth, cal = fr.left, None, fr.calib
        rng = None
    else:
        fr = reader.rgbd(i)
        if fr is None:
            return None
        img, depth, cal = fr.color, fr.depth_m, fr.calib
        rng = (cal.min_range_m, cal.max_range_m)
    img, depth = scale_to_width(img, width, depth_m=depth)
    return img, depth, cal.camera, cal.mount, rng


@dataclass
class DataSet:
    x: np.ndarray                      # (N, F) float32
    y: np.ndarray                      # (N,) int8
    cls: np.ndarray                    # (N,) object: class of positives, "" for negatives
    val: np.ndarray                    # (N,) bool: held-out frame
    frames: int = 0
    runs: list = field(default_factory=list)
    negative_images: int = 0


def jitter(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A photometric variant of a training image: per-channel gains 0.8-1.2, overall
    brightness 0.65-1.35 and gamma 0.75-1.33 -- light, white balance and exposure change from
    field to field and hour to hour; the cue must not learn one afternoon's colours."""
    x = img.astype(np.float32) * np.float32(1 / 255.0)
    x *= rng.uniform(0.8, 1.2, 3).astype(np.float32) * np.float32(rng.uniform(0.65, 1.35))
    np.clip(x, 0.0, 1.0, out=x)
    x = np.power(x, np.float32(np.exp(rng.uniform(np.log(0.75), np.log(1.33)))))
    return (x * 255.0 + 0.5).astype(np.uint8)


def build_dataset(runs: list[str | os.PathLike], domain: str | None = None, every: int = 2,
                  width: int = 640, cell_px: int = 16, neg_per_frame: int = 600,
                  val_fraction: float = 0.2, seed: int = 0, augment: int = 1,
                  negatives=(), progress=None) -> tuple[DataSet, str]:
    """Features and labels of every ``every``-th frame with truth of every run; each training
    frame also gives ``augment`` photometric variants (:func:`jitter`; held-out frames are
    used as they are). ``negatives``: photographs of clear ground (image files): every cell
    of them is a training negative (the field's real appearance, for a new field)."""
    rng = np.random.default_rng(seed)
    readers = []
    for r in runs:
        rd = RunReader(r)
        d = domain_of(rd)
        if domain is None:
            domain = d
        elif d != domain and not (domain == "rgbd" and rd.info.rgbd is not None):
            raise CueModelError(f"run {rd.info.name!r} ({rd.path}) is a {d!r} run; the other "
                                f"runs are {domain!r} (train one domain per model)")
        readers.append(rd)
    jobs = []
    for rd in readers:
        idx = [i for i in range(0, len(rd), max(1, every))
               if rd.file(i, "truth", "json").exists()]
        if not idx:
            raise CueModelError(f"run {rd.info.name!r} ({rd.path}) has no frame with a truth "
                                "file: nothing to learn from")
        # held out: every 5th block of 10 frames of every run (neighbouring frames are alike,
        # so single frames would leak; one block at the end would hold only the end's scenery)
        period = max(2, int(round(1.0 / val_fraction))) if val_fraction > 0 else 0
        jobs += [(rd, i, bool(period) and (i // 10) % period == period - 1) for i in idx]
    xs, ys, cs, vs = [], [], [], []
    for n, (rd, i, is_val) in enumerate(jobs):
        got = frame_image(rd, i, domain, width)
        if got is not None:
            img, depth, cam, mount, drange = got
            h, w = img.shape[:2]
            lab, owner = cell_labels(rd.truth(i) or [], cam, mount, (w, h), cell_px, depth,
                                     drange)
            for variant in range(1 + (0 if is_val else max(0, augment))):
                feats = cell_features(img if variant == 0 else jitter(img, rng), cell_px,
                                      depth if domain == "rgbd" else None)
                pos = np.flatnonzero(lab.ravel() == 1)
                neg = np.flatnonzero(lab.ravel() == 0)
                if len(neg) > neg_per_frame:
                    neg = rng.choice(neg, neg_per_frame, replace=False)
                take = np.concatenate([pos, neg])
                f = feats.reshape(-1, feats.shape[-1])
                xs.append(f[take])
                ys.append(lab.ravel()[take])
                cs.append(owner.ravel()[take])
                vs.append(np.full(len(take), is_val))
        if progress is not None:
            progress(n + 1, len(jobs))
    n_neg_images = 0
    for f in negatives or ():
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if img is None:
            raise CueModelError(f"{f}: not an image OpenCV can read (--negatives takes photos "
                                "of ground with no obstacle on it)")
        if domain == "rgbd":
            raise CueModelError("--negatives is for image-only (stereo) models; an RGB-D "
                                "model needs depth with every frame (record a run instead)")
        img, _ = scale_to_width(img, width, cell_px)
        for variant in range(1 + max(0, augment)):
            feats = cell_features(img if variant == 0 else jitter(img, rng), cell_px)
            f2 = feats.reshape(-1, feats.shape[-1])
            take = rng.choice(len(f2), min(len(f2), neg_per_frame), replace=False)
            xs.append(f2[take])
            ys.append(np.zeros(len(take), np.int8))
            cs.append(np.full(len(take), "", object))
            vs.append(np.zeros(len(take), bool))
        n_neg_images += 1
    if not xs:
        raise CueModelError("no frame with images and truth in the runs given")
    ds = DataSet(np.concatenate(xs).astype(np.float32), np.concatenate(ys),
                 np.concatenate(cs), np.concatenate(vs), frames=len(jobs),
                 runs=[str(rd.path) for rd in readers])
    ds.negative_images = n_neg_images
    if not (ds.y == 1).any():
        raise CueModelError("the runs' truth puts no obstacle on any whole cell: nothing "
                            "obstacle-like to learn")
    return ds, domain


# ---------------------------------------------------------------------------------------------
# training and export
# ---------------------------------------------------------------------------------------------
def _sklearn():
    try:
        from sklearn.neural_network import MLPClassifier
        from sklearn.pipeline import Pipeline
        from sklearn.preprocessing import StandardScaler
        from skl2onnx import convert_sklearn
        from skl2onnx.common.data_types import FloatTensorType
    except ImportError as exc:
        raise CueModelError(f"training needs the 'train' extra (pip install "
                            f"'fieldguard[train]': scikit-learn, skl2onnx): {exc}") from None
    return MLPClassifier, Pipeline, StandardScaler, convert_sklearn, FloatTensorType


def fit(ds: DataSet, hidden: tuple[int, ...] = (32, 16), neg_ratio: float = 4.0,
        seed: int = 0, max_iter: int = 300):
    """The scikit-learn pipeline fitted on the training frames (negatives subsampled to
    ``neg_ratio`` per positive)."""
    MLPClassifier, Pipeline, StandardScaler, _, _ = _sklearn()
    rng = np.random.default_rng(seed)
    tr = ~ds.val
    pos = np.flatnonzero(tr & (ds.y == 1))
    neg = np.flatnonzero(tr & (ds.y == 0))
    if len(pos) == 0:
        raise CueModelError("no positive cell in the training frames (all in held-out frames?)")
    k = int(min(len(neg), max(1, neg_ratio * len(pos))))
    take = np.concatenate([pos, rng.choice(neg, k, replace=False)])
    model = Pipeline([("scale", StandardScaler()),
                      ("mlp", MLPClassifier(hidden_layer_sizes=hidden, alpha=1e-3,
                                            learning_rate_init=2e-3, max_iter=max_iter,
                                            early_stopping=True, n_iter_no_change=15,
                                            random_state=seed))])
    model.fit(ds.x[take], ds.y[take].astype(np.int64))
    return model


def choose_threshold(p_neg: np.ndarray, max_fpr: float) -> float:
    """The lowest threshold (P(obstacle) strictly above it) that calls at most ``max_fpr`` of
    these negative cells obstacle-like (at least 0.5)."""
    if len(p_neg) == 0:
        return 0.5
    q = float(np.quantile(p_neg, 1.0 - max_fpr))
    return float(min(max(q, 0.5), 0.999))


def report(p: np.ndarray, ds_y: np.ndarray, ds_cls: np.ndarray, thr: float) -> dict:
    pos, neg = ds_y == 1, ds_y == 0
    hit = p > thr
    per = {}
    for c in sorted(set(ds_cls[pos])):
        m = pos & (ds_cls == c)
        per[c] = {"cells": int(m.sum()), "recall": round(float(hit[m].mean()), 4)}
    return {"positive_cells": int(pos.sum()), "negative_cells": int(neg.sum()),
            "recall": round(float(hit[pos].mean()), 4) if pos.any() else None,
            "false_alarm_rate": round(float(hit[neg].mean()), 5) if neg.any() else None,
            "per_class": per}


def export(model, path: str | os.PathLike, meta: dict) -> Path:
    """ONNX file with fieldguard's metadata; returns its path."""
    _, _, _, convert_sklearn, FloatTensorType = _sklearn()
    mlp = model.steps[-1][1]
    n = int(meta["n_features"])
    onx = convert_sklearn(model, initial_types=[(INPUT_NAME, FloatTensorType([None, n]))],
                          options={id(mlp): {"zipmap": False}}, target_opset=17)
    # skl2onnx names its outputs "label" and "probabilities"; make sure of ours
    names = [o.name for o in onx.graph.output]
    if OUTPUT_NAME not in names:
        raise CueModelError(f"the converter's outputs are {names}, expected {OUTPUT_NAME!r}")
    onx.doc_string = "fieldguard learned cue: P(obstacle-like) per image cell"
    onx.producer_name = "fieldguard train-cue"
    onx.model_version = int(VERSION)
    del onx.metadata_props[:]
    for k, v in meta.items():
        e = onx.metadata_props.add()
        e.key, e.value = k, v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".part")
    tmp.write_bytes(onx.SerializeToString())
    os.replace(tmp, p)                  # never a half-written model under the real name
    return p


def train_cue(runs, out, domain=None, every=2, width=640, cell_px=16, hidden=(32, 16),
              max_fpr=0.01, seed=0, augment=1, negatives=(), progress=None, log=print) -> dict:
    """Everything ``fieldguard train-cue`` does; returns the training summary (also stored in
    the model's ``trained_on`` metadata)."""
    t0 = time.monotonic()
    _sklearn()                        # the train extra is there before any frame is read
    ds, domain = build_dataset(runs, domain, every, width, cell_px, seed=seed, augment=augment,
                               negatives=negatives, progress=progress)
    log(f"train-cue: {ds.frames} frames, {len(ds.y)} cells "
        f"({int((ds.y == 1).sum())} obstacle-like), {int(ds.val.sum())} held out")
    model = fit(ds, hidden, seed=seed)
    has_val = bool(ds.val.any())
    vx, vy, vc = (ds.x[ds.val], ds.y[ds.val], ds.cls[ds.val]) if has_val else \
        (ds.x, ds.y, ds.cls)
    p_val = model.predict_proba(vx)[:, 1]
    thr = choose_threshold(p_val[vy == 0], max_fpr)
    summary = {
        "runs": [Path(r).name for r in ds.runs], "frames": ds.frames, "every": every,
        "domain": domain, "hidden": list(hidden), "seed": seed, "max_fpr": max_fpr,
        "augment": augment,
        "negative_images": [Path(f).name for f in negatives or ()],
        "threshold": round(thr, 5),
        "held_out": report(p_val, vy, vc, thr) | {"frames_are": "held-out" if has_val
                                                  else "training (no held-out frames)"},
        "train": report(model.predict_proba(ds.x[~ds.val])[:, 1], ds.y[~ds.val],
                        ds.cls[~ds.val], thr),
    }
    fset = DEPTH_FEATURE_SET if domain == "rgbd" else FEATURE_SET
    meta = {"fieldguard_cue_version": VERSION, "feature_set": fset,
            "n_features": str(len(FEATURE_SETS[fset])), "cell_px": str(cell_px),
            "image_width_px": str(width), "threshold": f"{thr:.6f}", "domain": domain,
            "trained_on": summary}
    path = export(model, out, meta)
    # what the box will run must agree with what was trained
    onnx_p = CueModel(path).score(vx)
    diff = float(np.max(np.abs(onnx_p - p_val))) if len(vx) else 0.0
    summary["export_max_abs_diff"] = diff
    summary["seconds"] = round(time.monotonic() - t0, 1)
    if diff > 1e-4:
        raise CueModelError(f"the exported model disagrees with the trained one by {diff:.2g} "
                            "(more than 1e-4); not using it", file=str(path))
    log(f"train-cue: threshold {thr:.3f}; held-out recall {summary['held_out']['recall']}, "
        f"false-alarm rate {summary['held_out']['false_alarm_rate']}; "
        f"ONNX vs scikit-learn max |diff| {diff:.2g}")
    return summary
