"""``fieldguard novelty IMAGES... [--learn IMAGES...] --out DIR``

Runs the stereo paper's novelty detector over an ordered image sequence (files, folders of
images, or videos) with no stereo, learning online as the daemon does (an update every
``update_every_frames`` frames, in the background thread; this tool waits for each update so
the result does not depend on the machine's speed). ``--learn`` first builds the model from
reference images (photos of the clear field), one update per image. For each input image it
writes ``NAME.novelty.npy`` (float32, rows x cols of the grid, -log10 of the Parzen density:
higher = more novel; inf = no learnt sample within 3 sigma), ``NAME.mask.png`` (image size,
255 = novel after islanding and dilation) and ``NAME.overlay.png``. No stabilisation (there is
no camera model or attitude for a photograph).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from hal.errors import ConfigError, FieldguardError

IMAGE_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm"}
VIDEO_EXT = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg"}


def _expand(paths: list[str]) -> list[tuple[str, object]]:
    """(name, source) in order: source is a Path to an image, or (video path, frame index)."""
    import cv2
    out: list[tuple[str, object]] = []
    for p in map(Path, paths):
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXT)
            if not files:
                raise FieldguardError(f"{p}: no images in this folder")
            out += [(f.stem, f) for f in files]
        elif p.suffix.lower() in VIDEO_EXT:
            cap = cv2.VideoCapture(str(p))
            if not cap.isOpened():
                raise FieldguardError(f"{p}: cannot open video")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            cap.release()
            out += [(f"{p.stem}_{i:06d}", (p, i)) for i in range(max(n, 0))]
        elif p.is_file():
            out.append((p.stem, p))
        else:
            raise FieldguardError(f"{p}: no such file or folder")
    return out


class _Frames:
    """Reads the expanded sources in order (a video is read sequentially)."""

    def __init__(self):
        self._cap = None
        self._cap_path = None

    def read(self, src):
        import cv2
        if isinstance(src, tuple):
            path, i = src
            if self._cap_path != path:
                if self._cap is not None:
                    self._cap.release()
                self._cap, self._cap_path = cv2.VideoCapture(str(path)), path
            ok, img = self._cap.read()
            if not ok:
                raise FieldguardError(f"{path}: cannot read frame {i}")
            return img
        img = cv2.imread(str(src), cv2.IMREAD_COLOR)
        if img is None:
            raise FieldguardError(f"{src}: not an image OpenCV can read")
        return img

    def close(self):
        if self._cap is not None:
            self._cap.release()


def _options(a):
    from appliance.config import load_config, pipeline_options
    from appliance.perception.stereo_novelty import StereoNoveltyConfig
    o = StereoNoveltyConfig(cell_px=32)
    if a.config:
        cfg = load_config(a.config)
        if "stereo-novelty" in cfg.perception.extra:
            o = pipeline_options(cfg, "stereo-novelty")
            if o.cell_px == 0:
                o = dataclasses.replace(o, cell_px=32)
    if a.cell_px:
        o = dataclasses.replace(o, cell_px=a.cell_px)
    if a.rho is not None:
        o = dataclasses.replace(o, rho=a.rho)
    return dataclasses.replace(o, stabilise="off")


def overlay(img, mask):
    import cv2
    import numpy as np
    out = img.copy()
    m = mask > 0
    out[m] = (0.5 * out[m] + np.array([0, 0, 127])).astype(np.uint8)
    cnts, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, cnts, -1, (0, 0, 255), 2)
    return out


def cmd_novelty(a) -> int:
    import cv2
    import numpy as np

    from appliance.perception.novelty import NoveltyDetector, mask_to_camera
    from appliance.progress import Progress
    o = _options(a)
    inputs = _expand(a.images)
    learn = _expand(a.learn) if a.learn else []
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    names = [n for n, _ in inputs]
    if len(set(names)) != len(names):
        raise FieldguardError("two inputs have the same name; outputs would overwrite each other")
    det = NoveltyDetector(o, background=True, exact_scores=True)   # the .npy shows every score
    reader = _Frames()
    try:
        if learn:
            prog = Progress("novelty learn", len(learn))
            for k, (_, src) in enumerate(learn):
                r = det.detect(reader.read(src))
                det.learn(r, force=True)
                det.wait_idle(60.0)
                prog(k + 1, len(learn))
        prog = Progress("novelty", len(inputs))
        novel_share = []
        for k, (name, src) in enumerate(inputs):
            img = reader.read(src)
            r = det.detect(img)
            H, W = img.shape[:2]
            mask = mask_to_camera(r.mask, None, (W, H), r.cell_px)
            np.save(out / f"{name}.novelty.npy", r.score.astype(np.float32))
            cv2.imwrite(str(out / f"{name}.mask.png"), mask)
            cv2.imwrite(str(out / f"{name}.overlay.png"), overlay(img, mask))
            novel_share.append(float(r.mask.mean()))
            det.learn(r)                       # online, as the daemon: every N frames
            det.wait_idle(60.0)
            prog(k + 1, len(inputs))
        if det.updater is not None and det.updater.error is not None:
            raise FieldguardError(f"model update failed: {det.updater.error}")
    finally:
        reader.close()
        det.close()
    print(f"wrote {len(inputs)} x (novelty.npy, mask.png, overlay.png) to {out}; "
          f"model: {det.model.size} samples after {det.model.updates} updates; "
          f"novel cells per image: mean {100 * np.mean(novel_share):.1f}%")
    return 0


def register(sub) -> None:
    p = sub.add_parser("novelty", help="novelty detector over images/videos (no stereo)",
                       description=__doc__.split("\n\n")[1] if __doc__ else None)
    p.add_argument("images", nargs="+", help="image files, folders of images or videos, in order")
    p.add_argument("--learn", nargs="+", metavar="IMAGES",
                   help="reference images of the clear field to learn first")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="config file: its [perception.stereo-novelty] options")
    p.add_argument("--cell-px", type=int, default=0, help="cell size in px (default 32)")
    p.add_argument("--rho", type=float, default=None, help="density threshold (eq. 3 units)")
    p.set_defaults(func=cmd_novelty)


__all__ = ["register", "cmd_novelty", "ConfigError"]
