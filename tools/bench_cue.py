#!/usr/bin/env python3
"""The learned cue's cost per frame on one core (issue #8).

    taskset -c 0 python tools/bench_cue.py [--frames 20] [--repeat 3]

Renders frames of the simulated field (stereo left image at 1280x1024, the paper's camera) and
greenhouse (RGB-D colour at 640x480), and times the shipped models' two stages per frame --
cell features (appliance.perception.cue_features, on the image scaled to the model's width:
640 px for the stereo model, 320 px for the RGB-D one)
and onnxruntime inference (one intra-op thread, sequential) -- and the whole ``LearnedCue.mask``
call the pipelines make. OpenCV and the BLAS are pinned to one thread. Prints p50 / p99 / max
in CPU time of the calling thread (what the cue itself costs) beside wall time, and the load
average before and after. The whole pipelines with the cue on: tools/bench_stereo.py and
tools/bench_rgbd.py with ``--set cue=required``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(v, "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from appliance.cue_model import load_cue_model  # noqa: E402
from appliance.perception.cue import LearnedCue  # noqa: E402
from appliance.perception.cue_features import cell_features, scale_to_width  # noqa: E402


def frames(scene: str, n: int, scale: float):
    from drivers.sim import SimField
    sensors = ("rgbd",) if scene == "greenhouse" else ("stereo",)
    f = SimField(scene, seed=1, sensors=sensors, stereo_scale=scale)
    out = []
    for i in range(n * 5):
        if i % 5 == 0:
            s = f.render(int(i * 1e8), i)
            out.append((s.rgbd.color, s.rgbd.depth_m) if scene == "greenhouse"
                       else (s.stereo.left, None))
        f.step(0.1)
    return out


def stats(xs) -> str:
    a = np.asarray(xs) * 1e3
    return f"p50 {np.percentile(a, 50):6.2f}  p99 {np.percentile(a, 99):6.2f}  max {a.max():6.2f}"


def bench(name: str, imgs, domain: str, repeat: int) -> None:
    model = load_cue_model(None, domain)
    cue = LearnedCue("required", domain, model=model)
    info = model.info
    rec = {k: ([], []) for k in ("features", "inference", "mask (whole cue)")}
    cue.mask(imgs[0][0], imgs[0][0].shape[:2], depth_m=imgs[0][1])     # warm-up (caches)
    for _ in range(repeat):
        for img, depth in imgs:
            h, w = img.shape[:2]
            small, dsmall = scale_to_width(img, info.image_width_px, info.cell_px, depth)
            t0, c0 = time.perf_counter(), time.thread_time()
            f = cell_features(small, info.cell_px, dsmall)
            t1, c1 = time.perf_counter(), time.thread_time()
            model.score(f.reshape(-1, f.shape[-1]))
            t2, c2 = time.perf_counter(), time.thread_time()
            cue.mask(img, (h, w), depth_m=depth)
            t3, c3 = time.perf_counter(), time.thread_time()
            for key, (cw, cc) in (("features", (t1 - t0, c1 - c0)),
                                  ("inference", (t2 - t1, c2 - c1)),
                                  ("mask (whole cue)", (t3 - t2, c3 - c2))):
                rec[key][0].append(cc)
                rec[key][1].append(cw)
    rows, cols = f.shape[:2]
    print(f"\n{name}: {len(imgs)} frames x {repeat}, image {imgs[0][0].shape[1]}x"
          f"{imgs[0][0].shape[0]}"
          f" -> features at {info.image_width_px} px, {rows}x{cols} cells of {info.cell_px} px;"
          f" model {Path(model.path).name}")
    for key, (cpu, wall) in rec.items():
        print(f"  {key:18s} CPU {stats(cpu)}   wall {stats(wall)}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    bench("stereo (stubble-day left image)", frames("stubble-day", a.frames, 1.0), "stereo",
          a.repeat)
    bench("rgbd (greenhouse colour)", frames("greenhouse", a.frames, 1.0), "rgbd", a.repeat)
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
