"""`fieldguard train-cue` and `fieldguard cue`: the learned cue's model from run folders, and
a look at what a model makes of images (issue #8)."""
from __future__ import annotations

import json
import sys
from pathlib import Path


def _hidden(text: str) -> tuple[int, ...]:
    try:
        h = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        h = ()
    if not h or any(v < 1 or v > 1024 for v in h):
        raise SystemExit(f"fieldguard: error: --hidden wants layer sizes like 32,16 (1..1024), "
                         f"got {text!r}")
    return h


def cmd_train_cue(a) -> int:
    from appliance.cue_model import CueModelError
    from appliance.cue_train import train_cue
    from appliance.progress import Progress
    if not 0.0 < a.max_fpr < 0.5:
        raise CueModelError(f"--max-fpr must be in (0, 0.5), got {a.max_fpr}")
    if a.every < 1 or a.cell_px < 4 or a.width < 64 or not 0 <= a.augment <= 10:
        raise CueModelError("--every must be >= 1, --cell-px >= 4, --width >= 64, "
                            "--augment 0..10")
    for r in a.runs:
        if not Path(r, "run.toml").is_file():
            raise CueModelError(f"{r}: not a run folder (no run.toml; see docs/run-format.md)")
    summary = train_cue(a.runs, a.out, domain=a.domain, every=a.every, width=a.width,
                        cell_px=a.cell_px, hidden=_hidden(a.hidden), max_fpr=a.max_fpr,
                        seed=a.seed, augment=a.augment, negatives=a.negatives or (),
                        progress=Progress("train-cue: frames", 1),
                        log=lambda m: print(m, file=sys.stderr))
    if a.json:
        print(json.dumps(summary, indent=2, default=float))
    else:
        ho = summary["held_out"]
        print(f"wrote {a.out}: {summary['domain']} cue, threshold {summary['threshold']:.3f}, "
              f"{summary['frames']} frames of {len(summary['runs'])} run(s)")
        print(f"held-out cells: recall {ho['recall']}, false-alarm rate "
              f"{ho['false_alarm_rate']} ({ho['positive_cells']} obstacle, "
              f"{ho['negative_cells']} other)")
        for c, v in ho["per_class"].items():
            print(f"  {c:<18} {v['cells']:>6} cells  recall {v['recall']:.3f}")
    return 0


def cmd_cue(a) -> int:
    """Score images with a cue model: per image NAME.cue.npy (P per cell) and an overlay."""
    import cv2
    import numpy as np

    from appliance.cue_model import load_cue_model
    from appliance.perception.cue import LearnedCue
    from appliance.progress import Progress
    model = load_cue_model(a.model or None, a.domain)
    cue = LearnedCue("required", a.domain, model=model)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    def listing(items):
        out = []
        for f in items:
            p = Path(f)
            out += sorted(q for q in p.iterdir()
                          if q.suffix.lower() in (".png", ".jpg", ".jpeg", ".pgm")) \
                if p.is_dir() else [p]
        return out

    files = listing(a.images)
    depths = listing(a.depth) if a.depth else []
    if model.uses_depth and len(depths) != len(files):
        print(f"fieldguard: error: {model.path} is an RGB-D model: give one --depth image per "
              f"colour image ({len(files)} colour, {len(depths)} depth)", file=sys.stderr)
        return 2
    prog = Progress("cue", len(files))
    rows = []
    for n, f in enumerate(files):
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if img is None:
            print(f"fieldguard: error: {f}: not an image OpenCV can read", file=sys.stderr)
            return 2
        depth = None
        if model.uses_depth:
            raw = cv2.imread(str(depths[n]), cv2.IMREAD_UNCHANGED)
            if raw is None or raw.ndim != 2 or raw.shape != img.shape[:2]:
                print(f"fieldguard: error: {depths[n]}: not a single-channel depth image of "
                      f"{img.shape[1]}x{img.shape[0]} (registered to {f})", file=sys.stderr)
                return 2
            depth = raw.astype(np.float32) * np.float32(a.depth_unit)
        p, cell = cue.scores(img, depth)
        hit = p > cue.threshold
        np.save(out / f"{f.stem}.cue.npy", p.astype(np.float32))
        ov = img.copy()
        for (i, j) in zip(*np.nonzero(hit)):
            y0, x0 = int(i * cell), int(j * cell)
            cv2.rectangle(ov, (x0, y0), (int(x0 + cell) - 1, int(y0 + cell) - 1), (0, 0, 255), 2)
        cv2.imwrite(str(out / f"{f.stem}.cue.png"), ov)
        rows.append({"image": str(f), "cells": int(p.size), "obstacle_like": int(hit.sum()),
                     "fraction": round(float(hit.mean()), 5)})
        prog(n + 1)
    tot = sum(r["cells"] for r in rows)
    hits = sum(r["obstacle_like"] for r in rows)
    summary = {"model": model.path, "threshold": cue.threshold, "images": rows,
               "cells": tot, "obstacle_like": hits,
               "fraction": round(hits / tot, 5) if tot else None}
    (out / "cue-summary.json").write_text(json.dumps(summary, indent=2))
    if a.json:
        print(json.dumps(summary, indent=2))
    else:
        for r in rows:
            print(f"{r['obstacle_like']:>5}/{r['cells']:<5} obstacle-like  {r['image']}")
        print(f"total: {hits}/{tot} cells obstacle-like ({summary['fraction']:.2%}); "
              f"overlays in {out}")
    return 0


def register(sub) -> None:
    t = sub.add_parser("train-cue", help="train the learned cue (ONNX) from run folders",
                       description="Train the learned 'obstacle-like' cell cue from run folders "
                                   "with truth (docs/run-format.md) and write it as ONNX with "
                                   "its metadata; see docs/learned-cue.md. Needs the 'train' "
                                   "extra (scikit-learn, skl2onnx).")
    t.add_argument("runs", nargs="+", metavar="RUN", help="run folders (stereo or RGB-D)")
    t.add_argument("--out", required=True, type=Path, help="model file to write (.onnx)")
    t.add_argument("--domain", choices=("stereo", "rgbd"),
                   help="which pipeline the model is for (default: from the first run)")
    t.add_argument("--every", type=int, default=2, help="use every N-th frame with truth")
    t.add_argument("--width", type=int, default=640, help="images are scaled to this width")
    t.add_argument("--cell-px", type=int, default=16, help="cell size at that width")
    t.add_argument("--hidden", default="32,16", help="hidden layer sizes of the perceptron")
    t.add_argument("--max-fpr", type=float, default=0.01,
                   help="share of held-out non-obstacle cells the threshold may call "
                        "obstacle-like")
    t.add_argument("--negatives", nargs="+", metavar="IMAGE",
                   help="photographs of the clear field (no obstacle): every cell a negative")
    t.add_argument("--augment", type=int, default=1,
                   help="photometric variants (light, white balance, gamma) per training frame")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--json", action="store_true", help="print the training summary as JSON")
    t.set_defaults(func=cmd_train_cue)

    c = sub.add_parser("cue", help="score images with a learned cue model",
                       description="Run a cue model over images (files or folders): writes "
                                   "NAME.cue.npy (P(obstacle-like) per cell), NAME.cue.png "
                                   "(obstacle-like cells boxed) and cue-summary.json.")
    c.add_argument("images", nargs="+", metavar="IMAGES")
    c.add_argument("--model", default="", help="cue model (default: the shipped one)")
    c.add_argument("--domain", choices=("stereo", "rgbd"), default="stereo")
    c.add_argument("--depth", nargs="+", metavar="DEPTH",
                   help="registered 16-bit depth images, one per colour image (RGB-D models)")
    c.add_argument("--depth-unit", type=float, default=0.001,
                   help="metres per depth count (0.001 = mm; TUM: 0.0002)")
    c.add_argument("--out", required=True, help="output folder")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=cmd_cue)
