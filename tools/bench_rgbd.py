#!/usr/bin/env python3
"""Per-stage times of the rgbd pipeline at 640x480 on one core.

    taskset -c 0 python tools/bench_rgbd.py [--frames 40] [--run RUN] [--texture always]

Frames come from a greenhouse run folder (``--run``) or are rendered by the simulator (seed 1,
every 10th frame of the path). Threads of OpenCV and the BLAS are pinned to one. Prints p50 /
p99 / max per stage and for the whole ``process()`` call, texture on every frame by default
(the issue's target: whole pipeline p99 <= 15 ms).
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

from appliance.perception import SensorInputs  # noqa: E402
from appliance.perception import rgbd as rgbd_mod  # noqa: E402
from appliance.perception.rgbd import RgbdPipeline, RgbdPipelineConfig  # noqa: E402

STAGES = {  # module attribute -> stage name (wrapped to time them inside analyse())
    "slope_map": "slope (eq. 4)",
    "suspected_map": "threshold + dilation",
    "colour_features": "colour features",
    "obstacle_groups": "groups (decision)",
}


def frames_from(args):
    if args.run:
        from drivers.runfolder import RunReader
        r = RunReader(args.run)
        idx = np.linspace(0, len(r) - 1, args.frames).astype(int)
        return [r.rgbd(int(i)) for i in idx]
    from drivers.sim.field import SimField
    from hal.types import GateState
    f = SimField("greenhouse", seed=1, sensors=("rgbd",))
    out = []
    for i in range(args.frames * 10):
        if i % 10 == 0:
            out.append(f.render_rgbd(i * 100_000_000, i))
        f.step(0.1, GateState.CLEAR)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--run", default=None)
    ap.add_argument("--texture", default="always", choices=("always", "after-colour", "off"))
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    frames = frames_from(a)
    times: dict[str, list[float]] = {}
    acc: dict[str, float] = {}

    def wrap(name, fn):
        def inner(*x, **k):
            t0 = time.perf_counter()
            try:
                return fn(*x, **k)
            finally:
                acc[name] = acc.get(name, 0.0) + (time.perf_counter() - t0) * 1e3
        return inner

    pipe = RgbdPipeline(RgbdPipelineConfig(texture=a.texture))
    pipe._texture_map = wrap("texture (LBP, histograms, chi-square)", pipe._texture_map)
    pipe.colour.classify = wrap("colour classes (eq. 5)", pipe.colour.classify)
    pipe._points = wrap("3-D points", pipe._points)
    for attr, name in STAGES.items():
        setattr(rgbd_mod, attr, wrap(name, getattr(rgbd_mod, attr)))
    pipe.process(SensorInputs(0, rgbd=frames[0]))          # warm-up (caches, imports)
    for _ in range(a.repeat):
        for fr in frames:
            acc.clear()
            t0 = time.perf_counter()
            pipe.process(SensorInputs(0, rgbd=fr))
            total = (time.perf_counter() - t0) * 1e3
            for k, v in acc.items():
                times.setdefault(k, []).append(v)
            times.setdefault("WHOLE process()", []).append(total)
    h, w = frames[0].depth_m.shape
    print(f"rgbd pipeline, {w}x{h}, {len(frames)} frames x {a.repeat}, texture={a.texture}, "
          f"OpenCV threads {cv2.getNumThreads()}, affinity {sorted(os.sched_getaffinity(0))}")
    print(f"{'stage':40s} {'p50 ms':>8s} {'p99 ms':>8s} {'max ms':>8s}")
    for k, v in times.items():
        x = np.asarray(v)
        print(f"{k:40s} {np.percentile(x, 50):8.2f} {np.percentile(x, 99):8.2f} {x.max():8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
