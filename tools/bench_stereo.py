"""Speed of the stereo-novelty pipeline at 1280x1024 on one core, per stage, against
full-frame stereo with the same matcher, measured in the same run.

    python tools/bench_stereo.py [--scale 1.0] [--matcher sgbm] [--learn 6] [--frames 4] [--reps 8]

Frames come from the simulated field (stubble-empty to learn, then stubble-day frames with the
obstacle course in view). OpenCV runs on one thread. Prints p50/p99/max per stage and the ratio.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def frames(scene, n, start, scale):
    from drivers.sim.field import SimField
    from hal.types import GateState
    f = SimField(scene, seed=0, sensors=("stereo",), stereo_scale=scale)
    out = []
    for i in range(start + n):
        if i >= start:
            out.append(f.render(i * 100_000_000, i))
        f.step(0.1, GateState.CLEAR)
    return out


def pct(xs):
    a = np.asarray(xs)
    return f"p50 {np.percentile(a, 50):7.1f}  p99 {np.percentile(a, 99):7.1f}  max {a.max():7.1f}"


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--matcher", default="sgbm")
    ap.add_argument("--learn", type=int, default=6)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--start", type=int, default=20, help="first course frame")
    ap.add_argument("--reps", type=int, default=8)
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    from appliance.perception import SensorInputs
    from appliance.perception.stereo import StereoConfig, StereoPipeline
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline

    t0 = time.time()
    learn = frames("stubble-empty", a.learn, 0, a.scale)
    course = frames("stubble-day", a.frames, a.start, a.scale)
    print(f"rendered {len(learn) + len(course)} frames at scale {a.scale} "
          f"({learn[0].stereo.left.shape[1]}x{learn[0].stereo.left.shape[0]}) in "
          f"{time.time() - t0:.1f} s; OpenCV threads {cv2.getNumThreads()}")
    nov = StereoNoveltyPipeline(StereoNoveltyConfig(matcher=a.matcher, update_every_frames=2))
    full = StereoPipeline(StereoConfig(matcher=a.matcher))
    inp = lambda s: SensorInputs(s.stereo.stamp_ns, stereo=s.stereo, vehicle=s.vehicle)  # noqa
    for s in learn:
        nov.process(inp(s))
        nov.novelty.wait_idle(60)
    stages: dict[str, list[float]] = {}
    whole, whole_full, novel, px = [], [], [], []
    try:
        for _ in range(a.reps):
            for s in course:
                t = time.perf_counter()
                d = nov.process(inp(s))
                whole.append(1e3 * (time.perf_counter() - t))
                for k, v in d.debug["ms"].items():
                    stages.setdefault(k, []).append(v)
                novel.append(d.debug["novel_fraction"])
                px.append(d.debug["stereo_px_fraction"])
                t = time.perf_counter()
                full.process(inp(s))
                whole_full.append(1e3 * (time.perf_counter() - t))
                nov.novelty.wait_idle(60)     # keep a model update out of the timed calls
    finally:
        nov.close()
    print(f"model: {nov.novelty.model.size} samples; novel cells {100 * np.mean(novel):.1f}% "
          f"of the grid; stereo matched {100 * np.mean(px):.1f}% of the pixels (crops incl.)")
    print(f"{len(whole)} timed frames, ms:")
    for k, v in stages.items():
        print(f"  stage {k:<10} {pct(v)}")
    print(f"  stereo-novelty ({a.matcher}) whole  {pct(whole)}")
    print(f"  full-frame {a.matcher} stereo        {pct(whole_full)}")
    print(f"  speed-up (p50): {np.percentile(whole_full, 50) / np.percentile(whole, 50):.1f}x")


if __name__ == "__main__":
    main()
