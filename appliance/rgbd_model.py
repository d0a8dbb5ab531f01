"""The RGB-D class model file and the annotation file (the I/O half of the rgbd pipeline).

Model file (``.npz``, read with ``allow_pickle=False``; written by ``fieldguard train-classes``):

    format      "fieldguard-rgbd-classes"
    version     1   (a reader refuses any other version)
    meta        JSON: classes, colour spaces, components, training frames and pixel counts
    lbp         (C, 256) normalised LBP histograms, C = number of classes
    SPACE/means (C, K, 3), SPACE/covs (C, K, 3, 3), SPACE/weights (C, K)   for every colour space

Annotation file (JSON), rectangles and polygons of pixels per class per frame:

    {"format": "fieldguard-rgbd-annotations", "version": 1,
     "classes": ["bush", "pepper", "ground", "cover"],
     "frames": {
        "greenhouse-0/rgbd/color/000010.png": [
            {"class": "bush", "rect": [x, y, w, h]},
            {"class": "ground", "polygon": [[x0, y0], [x1, y1], [x2, y2]]}
        ]}}

A frame key names a colour image: it matches the FRAMES given on the command line whose path
ends with it (so "000010.png" works when only one frame has that name). Pixels are integers,
(0, 0) top-left; a rectangle covers x..x+w-1, y..y+h-1; a polygon is filled (OpenCV fillPoly).
"""
from __future__ import annotations

import json
import tokenize
import zipfile
import zlib
from contextlib import ExitStack
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from appliance.perception.rgbd_classes import RgbdClassModel, train_model
from appliance.perception.rgbd_colour import COLOUR_SPACES, GaussianMixture
from appliance.perception.rgbd_texture import lbp_codes, to_grey
from hal.errors import ConfigError

FORMAT = "fieldguard-rgbd-classes"
VERSION = 1
ANNOTATION_FORMAT = "fieldguard-rgbd-annotations"
# the shipped greenhouse model is package data (appliance/models/), so an installed wheel has it
DEFAULT_MODEL_RESOURCE = ("appliance", "models/greenhouse-classes.npz")


def default_model_path() -> Path:
    """Filesystem path of the shipped model (importlib.resources; a zipped install is
    extracted to a temporary file that lives as long as the process)."""
    ref = resources.files(DEFAULT_MODEL_RESOURCE[0]).joinpath(DEFAULT_MODEL_RESOURCE[1])
    return _RESOURCES.enter_context(resources.as_file(ref))


_RESOURCES = ExitStack()


MAX_MODEL_BYTES = 64 << 20      # unpacked; the shipped model is ~40 kB


class RgbdModelError(ConfigError):
    """A model or annotation file that is missing, corrupt or of the wrong version."""


# ---------------------------------------------------------------------------------------------
# model file
# ---------------------------------------------------------------------------------------------
def save(model: RgbdClassModel, path: str | Path) -> Path:
    p = Path(path)
    meta = dict(model.meta)
    meta.update({"classes": list(model.classes), "colour_spaces": list(model.colour)})
    arrays = {"format": np.array(FORMAT), "version": np.array(VERSION, np.int64),
              "meta": np.array(json.dumps(meta, sort_keys=True)),
              "lbp": np.asarray(model.lbp, np.float64)}
    for space, mixes in model.colour.items():
        ks = {m.k for m in mixes}
        if len(ks) != 1:
            raise ValueError(f"{space}: every class needs the same number of components")
        arrays[f"{space}/means"] = np.stack([m.means for m in mixes])
        arrays[f"{space}/covs"] = np.stack([m.covs for m in mixes])
        arrays[f"{space}/weights"] = np.stack([m.weights for m in mixes])
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "wb") as fh:           # np.savez would add ".npz" to a name without it
        np.savez_compressed(fh, **arrays)
    return p


def load(path: str | Path | None = None) -> RgbdClassModel:
    """Read a model file (None or "" = the shipped greenhouse model, package data); RgbdModelError
    naming the file and what is wrong when it is missing, not a model, of another version or
    inconsistent."""
    p = Path(path) if path else default_model_path()
    where = f"rgbd class model {p}"
    if not p.is_file():
        raise RgbdModelError(f"{where}: no such file (train one with `fieldguard train-classes`)",
                             key="perception.rgbd.model")
    try:
        # what the archive says it unpacks to, before unpacking (a forged size would make
        # np.load allocate it): found by tests/fuzz/fuzz_annotations.py, as was zlib.error
        with zipfile.ZipFile(p) as zf:
            unpacked = sum(i.file_size for i in zf.infolist())
            if any(i.flag_bits & 0x1 for i in zf.infolist()):    # np.load: RuntimeError
                raise RgbdModelError(f"{where}: has encrypted entries, not a model file",
                                     key="perception.rgbd.model")
        if unpacked > MAX_MODEL_BYTES:
            raise RgbdModelError(f"{where}: unpacks to {unpacked} bytes, more than a class "
                                 f"model can be ({MAX_MODEL_BYTES})",
                                 key="perception.rgbd.model")
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error,
            NotImplementedError,              # zipfile: "zip file version 9.3", compression
            tokenize.TokenError, SyntaxError) as exc:   # a garbled .npy header (numpy parses it)
        raise RgbdModelError(f"{where}: not a readable model file ({exc})",
                             key="perception.rgbd.model") from None
    if "format" not in data or str(data["format"]) != FORMAT:
        raise RgbdModelError(f"{where}: not a fieldguard RGB-D class model",
                             key="perception.rgbd.model")
    ver = int(data.get("version", -1))
    if ver != VERSION:
        raise RgbdModelError(f"{where}: model version {ver}, this fieldguard reads version "
                             f"{VERSION}; retrain with `fieldguard train-classes`",
                             key="perception.rgbd.model")
    try:
        meta = json.loads(str(data["meta"]))
        classes = tuple(meta["classes"])
        c = len(classes)
        lbp = np.asarray(data["lbp"], np.float64)
        if lbp.shape != (c, 256) or not np.all(np.isfinite(lbp)):
            raise ValueError(f"lbp has shape {lbp.shape}, expected ({c}, 256)")
        colour = {}
        for space in COLOUR_SPACES:
            means, covs, w = (np.asarray(data[f"{space}/{n}"], np.float64)
                              for n in ("means", "covs", "weights"))
            k = means.shape[1] if means.ndim == 3 else -1
            if means.shape != (c, k, 3) or covs.shape != (c, k, 3, 3) or w.shape != (c, k):
                raise ValueError(f"{space}: shapes {means.shape}, {covs.shape}, {w.shape} do "
                                 f"not fit {c} classes")
            mixes = []
            for i in range(c):
                for cov in covs[i]:
                    np.linalg.cholesky(cov)         # raises if not positive definite
                mixes.append(GaussianMixture(means[i], covs[i], w[i]))
            colour[space] = tuple(mixes)
    except (KeyError, ValueError, TypeError, np.linalg.LinAlgError) as exc:
        raise RgbdModelError(f"{where}: inconsistent model ({exc})",
                             key="perception.rgbd.model") from None
    return RgbdClassModel(classes, colour, lbp, meta)


# ---------------------------------------------------------------------------------------------
# annotations and training
# ---------------------------------------------------------------------------------------------
def load_annotations(path: str | Path) -> dict:
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RgbdModelError(f"annotation file {p}: no such file") from None
    except (OSError, ValueError) as exc:
        raise RgbdModelError(f"annotation file {p}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != ANNOTATION_FORMAT:
        raise RgbdModelError(f"annotation file {p}: needs \"format\": \"{ANNOTATION_FORMAT}\"")
    if doc.get("version") != 1:
        raise RgbdModelError(f"annotation file {p}: version {doc.get('version')!r}, expected 1")
    classes = doc.get("classes")
    frames = doc.get("frames")
    if not isinstance(classes, list) or not classes or not isinstance(frames, dict):
        raise RgbdModelError(f"annotation file {p}: needs a \"classes\" list and a \"frames\" "
                             f"table")
    for key, regions in frames.items():
        if not isinstance(regions, list):
            raise RgbdModelError(f"annotation file {p}: frames[{key!r}] must be a list")
        for i, r in enumerate(regions):
            where = f"annotation file {p}: frames[{key!r}][{i}]"
            if not isinstance(r, dict) or r.get("class") not in classes:
                raise RgbdModelError(f"{where}: \"class\" must be one of {classes}")
            if ("rect" in r) == ("polygon" in r):
                raise RgbdModelError(f"{where}: give exactly one of \"rect\" or \"polygon\"")
            if "rect" in r and (not isinstance(r["rect"], list) or len(r["rect"]) != 4
                                or any(not isinstance(v, int) for v in r["rect"])
                                or r["rect"][2] <= 0 or r["rect"][3] <= 0):
                raise RgbdModelError(f"{where}: \"rect\" must be [x, y, w, h] whole pixels, "
                                     f"w and h > 0")
            if "polygon" in r and (not isinstance(r["polygon"], list) or len(r["polygon"]) < 3
                                   or any(not isinstance(q, list) or len(q) != 2
                                          or not all(_pixel(v) for v in q)
                                          for q in r["polygon"])):
                # (a point at 8e72 made cv2.fillPoly take 25 s: tests/fuzz/fuzz_annotations.py)
                raise RgbdModelError(f"{where}: \"polygon\" must be 3 or more [x, y] points, "
                                     f"each a number of pixels within +-{MAX_PIXEL}")
    return doc


MAX_PIXEL = 100_000


def _pixel(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)
            and abs(v) <= MAX_PIXEL)            # (NaN fails the comparison too)


def region_mask(shape: tuple[int, int], region: dict) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    if "rect" in region:
        x, y, w, h = region["rect"]
        m[max(y, 0):max(y + h, 0), max(x, 0):max(x + w, 0)] = 1
    else:
        cv2.fillPoly(m, [np.round(np.asarray(region["polygon"], np.float64)).astype(np.int32)], 1)
    return m > 0


def match_frames(keys, frames: list[str]) -> dict[str, str]:
    """annotation key -> the one frame path ending with it."""
    out = {}
    norm = [(f, Path(f).as_posix()) for f in frames]
    for key in keys:
        k = Path(key).as_posix()
        hits = [f for f, fp in norm if fp == k or fp.endswith("/" + k)]
        if len(hits) > 1:
            raise RgbdModelError(f"annotation frame {key!r} matches several frames: "
                                 f"{', '.join(hits[:3])}; give a longer key")
        if hits:
            out[key] = hits[0]
    return out


def train_from_files(frames: list[str], annotations: str | Path, components: int = 1,
                     ridge: float = 1.0) -> RgbdClassModel:
    """Read the annotated frames and fit the class model (train_model)."""
    doc = load_annotations(annotations)
    used = match_frames(doc["frames"], frames)
    unmatched = [k for k in doc["frames"] if k not in used]
    if not used:
        raise RgbdModelError(f"none of the {len(doc['frames'])} annotated frames is among the "
                             f"{len(frames)} FRAMES given (keys like {next(iter(doc['frames']), '')!r})")
    samples: dict[str, list] = {c: [] for c in doc["classes"]}
    for key, path in used.items():
        img = cv2.imread(path, cv2.IMREAD_COLOR)
        if img is None:
            raise RgbdModelError(f"frame {path}: cannot read the image")
        codes = lbp_codes(to_grey(img))
        for i, r in enumerate(doc["frames"][key]):
            m = region_mask(img.shape[:2], r)
            if not m.any():
                raise RgbdModelError(f"annotation {key!r} region {i}: no pixels inside the "
                                     f"{img.shape[1]}x{img.shape[0]} image")
            samples[r["class"]].append((img[m], codes[m]))
    empty = [c for c, s in samples.items() if not s]
    if empty:
        raise RgbdModelError(f"classes without any annotated pixels in the given frames: "
                             f"{', '.join(empty)}")
    meta = {"annotations": Path(annotations).name, "frames": sorted(used),
            "unmatched_frames": unmatched}
    try:
        return train_model(samples, components=components, ridge=ridge, meta=meta)
    except ValueError as exc:
        raise RgbdModelError(f"training failed: {exc}") from None
