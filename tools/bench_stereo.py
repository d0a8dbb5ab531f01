"""Speed of the stereo-novelty pipeline at 1280x1024 on one core, per stage, against
full-frame stereo with the same matcher, measured in the same run.

    python tools/bench_stereo.py [--scale 1.0] [--matcher sgbm] [--learn 6] [--frames 4] [--reps 8]
                                 [--scene stubble-day] [--set key=value ...] [--interleave]

Frames come from the simulated field (stubble-empty to learn, then frames of --scene with the
obstacle course in view). OpenCV runs on one thread. Prints p50/p99/max per stage (wall), the
whole pipeline in wall AND thread CPU time (time.thread_time: what this thread used, not
inflated by other processes on a shared machine), the load average before/after, and the
ratio against full-frame stereo at native resolution and at the pipeline's matching
resolution. ``--set`` overrides [perception.stereo-novelty] options (e.g. --set depth_cue=off).
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
    ap.add_argument("--scene", default="stubble-day")
    ap.add_argument("--per-frame", action="store_true", help="print every frame's CPU time")
    ap.add_argument("--interleave", action="store_true",
                    help="time the pipeline and the two full-frame matchers on each frame in "
                         "turn instead of in three passes")
    ap.add_argument("--no-decision", action="store_true",
                    help="do not time the box's decision (fusion, tracking, zones) after "
                         "each pipeline call")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="stereo-novelty option (value parsed as JSON, else a string)")
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    from appliance.perception import SensorInputs
    from appliance.perception.stereo import StereoConfig, StereoPipeline
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline

    import json
    opts = {"matcher": a.matcher, "update_every_frames": 2}
    for kv in a.set:
        k, _, v = kv.partition("=")
        try:
            opts[k] = json.loads(v)
        except ValueError:
            opts[k] = v
    t0 = time.time()
    learn = frames("stubble-empty", a.learn, 0, a.scale)
    course = frames(a.scene, a.frames, a.start, a.scale)
    print(f"rendered {len(learn) + len(course)} frames at scale {a.scale} "
          f"({learn[0].stereo.left.shape[1]}x{learn[0].stereo.left.shape[0]}) in "
          f"{time.time() - t0:.1f} s; OpenCV threads {cv2.getNumThreads()}")
    cfg = StereoNoveltyConfig(**opts)
    print("stereo-novelty options:", {k: getattr(cfg, k) for k in sorted(opts)},
          f"match_width_px={cfg.match_width_px}")
    nov = StereoNoveltyPipeline(cfg)
    # the same matcher settings as the pipeline's (block, colour ...), over the whole frame
    from dataclasses import fields
    same = {f.name: getattr(cfg, f.name) for f in fields(StereoConfig)
            if f.name != "match_width_px"}
    full = StereoPipeline(StereoConfig(**same))
    full_k = StereoPipeline(StereoConfig(**same, match_width_px=cfg.match_width_px))
    inp = lambda s: SensorInputs(s.stereo.stamp_ns, stereo=s.stereo, vehicle=s.vehicle)  # noqa
    for s in learn:
        nov.process(inp(s))
        nov.novelty.wait_idle(60)
    # the box's decision after perception, as the daemon runs it: fusion into the grid, the
    # default [tracking] (the cell decision with the movers' tracker beside it), the zones;
    # the frames' stamps are made monotonic (the reps replay the same frames)
    from appliance.config import default_config
    from appliance.decision import DecisionCore, decision_name
    dcfg = default_config()
    core = DecisionCore(dcfg)
    tick = 0
    dec_cpu: list[float] = []
    stages: dict[str, list[float]] = {}
    stages_cpu: dict[str, list[float]] = {}
    whole, cpu, whole_full, cpu_full, whole_k, cpu_k, novel, px, cues = ([] for _ in range(9))
    load0 = os.getloadavg()
    try:
        runs = ((nov, whole, cpu), (full, whole_full, cpu_full), (full_k, whole_k, cpu_k))
        # default: each pipeline in its own pass over the frames (as in the daemon, where
        # nothing else touches the caches between frames); --interleave runs the three on
        # each frame in turn (full-frame SGBM's 300+ MB buffers then evict the pipeline's
        # working set every frame: a pessimistic figure)
        passes = [runs] if a.interleave else [(r,) for r in runs]
        for group in passes:
            for _ in range(a.reps):
                for s in course:
                    for pipe, wl, cl in group:
                        t, c = time.perf_counter(), time.thread_time()
                        d = pipe.process(inp(s))
                        cl.append(1e3 * (time.thread_time() - c))
                        wl.append(1e3 * (time.perf_counter() - t))
                        if pipe is nov and not a.no_decision:
                            tick += 1
                            c = time.thread_time()
                            core.perceive({"stereo-novelty": d}, s.vehicle, tick * 100_000_000)
                            dec_cpu.append(1e3 * (time.thread_time() - c))
                        if pipe is nov:
                            for k, v in d.debug["ms"].items():
                                stages.setdefault(k, []).append(v)
                            for k, v in d.debug["cpu_ms"].items():
                                stages_cpu.setdefault(k, []).append(v)
                            novel.append(d.debug["novel_fraction"])
                            px.append(d.debug["stereo_px_fraction"])
                            cues.append(sum(d.debug.get("cue_cells", {}).values()))
                nov.novelty.wait_idle(60)     # keep a model update out of the timed calls
    finally:
        nov.close()
    load1 = os.getloadavg()
    k = full_k.process(inp(course[0])).debug["match_factor"]
    print(f"model: {nov.novelty.model.size} samples; novel cells {100 * np.mean(novel):.1f}% "
          f"of the grid; extra-cue cells {np.mean(cues):.1f}/frame; stereo matched "
          f"{100 * np.mean(px):.1f}% of the matching-resolution pixels (crops incl.)")
    print(f"load average (1 min) {load0[0]:.2f} before, {load1[0]:.2f} after, on "
          f"{os.cpu_count()} cores: wall times are inflated by other processes, CPU times less")
    print(f"{len(whole)} timed frames, ms:")
    if a.per_frame:
        print("  stereo-novelty CPU per frame (rep x frame):",
              " ".join(f"{v:.1f}" for v in cpu))
    for k_, v in stages.items():
        print(f"  stage {k_:<10} wall {pct(v)}")
        print(f"  stage {k_:<10} CPU  {pct(stages_cpu[k_])}")
    print(f"  stereo-novelty ({a.matcher}) whole    wall {pct(whole)}")
    print(f"  stereo-novelty ({a.matcher}) whole    CPU  {pct(cpu)}")
    best = np.asarray(cpu).reshape(a.reps, len(course)).min(axis=0)
    print(f"  stereo-novelty ({a.matcher}) each frame's best of {a.reps} reps, CPU: "
          f"median {np.median(best):.1f}  max {best.max():.1f}  (what the frames cost without "
          f"the machine's noise: the spread above is other tenants of a shared host)")
    if dec_cpu:
        both = np.asarray(cpu) + np.asarray(dec_cpu)
        print(f"  decision ({decision_name(dcfg.tracking)}: fusion, tracking, zones) CPU  "
              f"{pct(dec_cpu)}")
        print(f"  stereo-novelty + decision       CPU  {pct(both)}")
    print(f"  full-frame {a.matcher} native          wall {pct(whole_full)}")
    print(f"  full-frame {a.matcher} native          CPU  {pct(cpu_full)}")
    print(f"  full-frame {a.matcher} at 1/{k} (as matched) CPU  {pct(cpu_k)}")
    r = lambda x, y: np.percentile(x, 50) / np.percentile(y, 50)  # noqa: E731
    print(f"  speed-up (CPU p50) vs full-frame native: {r(cpu_full, cpu):.1f}x, "
          f"vs full-frame at the same matching resolution: {r(cpu_k, cpu):.1f}x; "
          f"(wall p50 vs native: {r(whole_full, whole):.1f}x)")
    if dec_cpu:
        print(f"  perception + decision vs full-frame at the same matching resolution (CPU "
              f"p50): {r(cpu_k, both):.2f}x")


if __name__ == "__main__":
    main()
