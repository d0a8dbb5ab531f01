"""Time the simulator's sensors: ms per stereo pair (scale 1.0 and 0.5), laser scan, RGB-D frame.

    .venv/bin/python tools/bench_sim.py [--frames 5] [--scene stubble-day] [--stages]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.sim import SimField  # noqa: E402
import drivers.sim.render as render  # noqa: E402


def bench(fn, field: SimField, n: int) -> list[float]:
    fn(0, 0)                                    # warm-up (texture load, caches)
    out = []
    for i in range(n):
        field.step(0.1)
        t0 = time.perf_counter()
        fn(i, i)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--scene", default="stubble-day")
    ap.add_argument("--stages", action="store_true", help="per-stage times of the camera renderer")
    a = ap.parse_args(argv)
    rows = []
    for scale in (1.0, 0.5):
        f = SimField(a.scene, sensors=("stereo",), stereo_scale=scale)
        if a.stages:
            render.TIMING = {}
        t = bench(f.render_stereo, f, a.frames)
        rows.append((f"stereo pair {f.stereo_calibration.camera.width}x"
                     f"{f.stereo_calibration.camera.height} (scale {scale})", t))
        if a.stages:
            print(f"  stages (ms per view, scale {scale}):",
                  {k: round(v / (2 * (a.frames + 1)), 1) for k, v in render.TIMING.items()})
            render.TIMING = None
    f = SimField(a.scene, sensors=("laser",))
    rows.append(("laser scan 541 beams", bench(f.render_laser, f, a.frames * 4)))
    f = SimField(a.scene, sensors=("rgbd",))
    rows.append(("RGB-D frame 640x480", bench(f.render_rgbd, f, a.frames)))
    g = SimField("greenhouse", sensors=("rgbd",))
    rows.append(("RGB-D frame 640x480 (greenhouse)", bench(g.render_rgbd, g, a.frames)))
    print(f"{'sensor':44s} {'median ms':>10s} {'min ms':>8s} {'max ms':>8s}")
    for name, t in rows:
        print(f"{name:44s} {statistics.median(t):10.1f} {min(t):8.1f} {max(t):8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
