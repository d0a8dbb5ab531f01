"""Time the simulator's sensors: CPU ms per stereo pair (scale 1.0 and 0.5), laser scan, RGB-D frame.

    .venv/bin/python tools/bench_sim.py [--frames 8] [--scene stubble-day] [--stages] [--json]
                                        [--baseline] [--engine numba|numpy]
    taskset -c 1 .venv/bin/python tools/bench_sim.py --json --baseline   # the issue-13 figures

Times are CPU time of this process (``time.process_time``: every thread's CPU, so threads cannot
hide work) per frame, p50 and best of the frames, with the process pinned to ONE core (``--cpu``,
default core 1; ``--cpu -1`` leaves the affinity alone). CPU time is what counts on a machine
shared with others: contention disturbs it far less than wall time. The vehicle moves 0.1 s
between frames (so the frames differ as they do in a drive).

``--json`` prints one JSON object:

- ``stereo_640x512_cpu_ms``: a 640x512 stereo pair (both images rendered and exposed) PLUS the
  laser scan PLUS the vehicle step, i.e. the simulator's whole work per cycle of a stereo drive;
  ``stereo_640x512_pair_only_cpu_ms`` is the pair alone;
- ``stereo_1280x1024_cpu_ms``: a 1280x1024 stereo pair;
- ``rgbd_640x480_cpu_ms``: one 640x480 RGB-D frame (colour + Kinect-class depth), stubble field;
  ``rgbd_640x480_greenhouse_cpu_ms`` the same in the greenhouse;
- ``laser_cpu_ms``: one 541-beam laser scan;
- ``*_best_cpu_ms``: the best frame of each; ``targets_ms`` the issue's targets; and the
  settings (frames, scene, seed, cpu affinity, commit, the 1-minute load average);
- with ``--baseline``: ``numpy_baseline_cpu_ms`` (the whole-array numpy renderer, the
  simulator before numba, timed in the same run) and ``speedup_vs_numpy``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.sim import SimField  # noqa: E402
import drivers.sim.render as render  # noqa: E402

TARGETS_MS = {"stereo_640x512_cpu_ms": 30.0, "stereo_1280x1024_cpu_ms": 100.0,
              "rgbd_640x480_cpu_ms": 15.0}


def bench(fn, field: SimField, n: int, step_inside: bool = False) -> list[float]:
    """CPU ms of ``fn(stamp, seq)`` over n frames (after one warm-up frame). With
    ``step_inside`` the vehicle step is timed too (it is part of a drive's cycle)."""
    fn(0, 0)                                    # warm-up (texture load, caches)
    out = []
    for i in range(1, n + 1):
        if not step_inside:
            field.step(0.1)
        t0 = time.process_time()
        if step_inside:
            field.step(0.1)
        fn(i, i)
        out.append((time.process_time() - t0) * 1e3)
    return out


def _commit() -> str:
    try:
        root = Path(__file__).resolve().parents[1]
        c = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                           capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--",
                                "drivers/sim"], capture_output=True, text=True,
                               timeout=10).stdout.strip()
        return c + ("+dirty(drivers/sim)" if dirty else "")
    except Exception:                            # noqa: BLE001 - informational only
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--scene", default="stubble-day")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cpu", type=int, default=1,
                    help="pin to this core (default 1; -1: leave the affinity alone)")
    ap.add_argument("--stages", action="store_true", help="per-stage times of the camera renderer")
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    ap.add_argument("--baseline", action="store_true",
                    help="also time the whole-array numpy renderer in this run (ratios)")
    ap.add_argument("--engine", choices=("numba", "numpy"), default="numba")
    a = ap.parse_args(argv)
    if a.frames < 1:
        print("bench_sim: error: --frames must be >= 1", file=sys.stderr)
        return 2
    if a.cpu >= 0 and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {a.cpu})
        except OSError as e:
            print(f"bench_sim: error: cannot pin to core {a.cpu} ({e}); use --cpu -1",
                  file=sys.stderr)
            return 2
    render.ENGINE = a.engine
    rows = []
    res: dict = {}
    stages = {}

    def stereo(scale, with_laser):
        sensors = ("stereo", "laser") if with_laser else ("stereo",)
        f = SimField(a.scene, seed=a.seed, sensors=sensors, stereo_scale=scale)
        if with_laser:
            def fn(st, sq):
                f.render_stereo(st, sq)
                f.render_laser(st, sq)
        else:
            fn = f.render_stereo
        if a.stages:
            render.TIMING = {}
        t = bench(fn, f, a.frames, step_inside=with_laser)
        if a.stages:
            stages[f"scale {scale}{' +laser' if with_laser else ''}"] = {
                k: round(v / (2 * (a.frames + 1)), 1) for k, v in render.TIMING.items()}
            render.TIMING = None
        cam = f.stereo_calibration.camera
        return t, f"{cam.width}x{cam.height}"

    t, wh = stereo(0.5, True)
    rows.append((f"stereo pair {wh} + laser + vehicle step", t))
    res["stereo_640x512_cpu_ms"] = t
    t, wh = stereo(0.5, False)
    rows.append((f"stereo pair {wh} alone", t))
    res["stereo_640x512_pair_only_cpu_ms"] = t
    t, wh = stereo(1.0, False)
    rows.append((f"stereo pair {wh}", t))
    res["stereo_1280x1024_cpu_ms"] = t
    f = SimField(a.scene, seed=a.seed, sensors=("laser",))
    t = bench(f.render_laser, f, a.frames * 4)
    rows.append(("laser scan 541 beams", t))
    res["laser_cpu_ms"] = t
    f = SimField(a.scene, seed=a.seed, sensors=("rgbd",))
    t = bench(f.render_rgbd, f, a.frames)
    rows.append(("RGB-D frame 640x480", t))
    res["rgbd_640x480_cpu_ms"] = t
    g = SimField("greenhouse", seed=a.seed, sensors=("rgbd",))
    t = bench(g.render_rgbd, g, a.frames)
    rows.append(("RGB-D frame 640x480 (greenhouse)", t))
    res["rgbd_640x480_greenhouse_cpu_ms"] = t

    base: dict = {}
    if a.baseline:
        # the same work with the whole-array numpy renderer, in this run (a ratio is what the
        # shared machine's load cannot distort much)
        eng = render.ENGINE
        render.ENGINE = "numpy"
        try:
            nb = max(2, a.frames // 2)
            f = SimField(a.scene, seed=a.seed, sensors=("stereo", "laser"), stereo_scale=0.5)

            def fn(st, sq):
                f.render_stereo(st, sq)
                f.render_laser(st, sq)
            base["stereo_640x512_cpu_ms"] = bench(fn, f, nb, step_inside=True)
            f = SimField(a.scene, seed=a.seed, sensors=("stereo",), stereo_scale=1.0)
            base["stereo_1280x1024_cpu_ms"] = bench(f.render_stereo, f, nb)
            f = SimField(a.scene, seed=a.seed, sensors=("rgbd",))
            base["rgbd_640x480_cpu_ms"] = bench(f.render_rgbd, f, nb)
            f = SimField(a.scene, seed=a.seed, sensors=("laser",))
            base["laser_cpu_ms"] = bench(f.render_laser, f, nb * 4)
        finally:
            render.ENGINE = eng
        for k, t in base.items():
            rows.append((f"numpy baseline: {k}", t))
    if a.json:
        out: dict = {}
        for k, t in res.items():
            out[k] = round(statistics.median(t), 1)
            out[k.replace("_cpu_ms", "_best_cpu_ms")] = round(min(t), 1)
        if base:
            out["numpy_baseline_cpu_ms"] = {k: round(statistics.median(t), 1)
                                            for k, t in base.items()}
            out["speedup_vs_numpy"] = {k: round(statistics.median(t) / max(out[k], 1e-9), 2)
                                       for k, t in base.items()}
        out["engine"] = render.ENGINE
        try:
            out["load_avg_1min"] = round(os.getloadavg()[0], 1)
        except OSError:
            pass
        out["stereo_640x512_includes"] = "stereo pair + 541-beam laser scan + vehicle step"
        out["targets_ms"] = TARGETS_MS
        out["met"] = {k: out[k] <= v for k, v in TARGETS_MS.items()}
        out["clock"] = "time.process_time (CPU of the whole process), p50 over frames"
        out["frames"] = a.frames
        out["scene"] = a.scene
        out["seed"] = a.seed
        out["cpu_affinity"] = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
            else None
        out["commit"] = _commit()
        if stages:
            out["stages_ms_per_view"] = stages
        print(json.dumps(out, indent=1))
        return 0
    for name, st in stages.items():
        print(f"  stages (ms per view, {name}):", st)
    print(f"{'sensor (CPU ms per frame)':44s} {'p50':>8s} {'best':>8s} {'max':>8s}")
    for name, t in rows:
        print(f"{name:44s} {statistics.median(t):8.1f} {min(t):8.1f} {max(t):8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
