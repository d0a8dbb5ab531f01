"""Does the stereo-novelty pipeline see a low obstacle (a person lying, a dog) in the path?
Open loop on a training coverage drive: the vehicle drives its lane at cruise (no stops), from
``--lead`` m before the obstacle until it reaches it; every frame goes through one pipeline per
``--set`` variant, and per frame this prints the obstacle's distance, the dense points on its
footprint (all / in the band), their heights, and the band points elsewhere in the vehicle's
corridor (0-10 m ahead, |y| <= 1.2 m: what a lower band would stop for).

    python tools/low_obstacle_probe.py stubble-coverage 10 c1 [--set band_min_m=0.25] ...

Training seeds only (< 1000).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def _val(v: str):
    for f in (int, float):
        try:
            return f(v)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(v, v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("obstacle")
    ap.add_argument("--lead", type=float, default=30.0, help="start this far before it (m)")
    ap.add_argument("--warm", type=int, default=45, help="frames before that (model learns)")
    ap.add_argument("--set", action="append", default=[], help="variant: k=v[,k=v] (repeat)")
    ap.add_argument("--every", type=int, default=2, help="print every n-th frame")
    a = ap.parse_args(argv)
    if a.seed >= 1000:
        sys.exit("training seeds only (< 1000)")
    cv2.setNumThreads(1)
    from appliance.evaluation import footprint_distance
    from appliance.perception import SensorInputs
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    from drivers.sim import SimField
    from hal.types import GateState
    f = SimField(a.kind, seed=a.seed, sensors=("stereo",), stereo_scale=0.5)
    ob = next(o for o in f.world.obstacles if o.id == a.obstacle)
    s_ob = f.scene.route_s_of(ob.x, ob.y)
    print(f"{a.kind} {a.seed} {ob.id} {ob.cls} h={ob.height_m:.2f} l={ob.length_m:.2f} "
          f"w={ob.width_m:.2f} yaw={ob.yaw_deg:.0f} route s={s_ob:.1f} "
          f"stubble_height={f.scene.params['stubble_height']:.2f}")
    variants = [{}] + [{k: _val(v) for k, v in (kv.split("=") for kv in s.split(","))}
                       for s in a.set]
    pipes = [StereoNoveltyPipeline(dataclasses.replace(StereoNoveltyConfig(),
                                                       model_state="off", **v), background=False)
             for v in variants]
    start = s_ob - a.lead - a.warm * f.scene.cruise_mps / 10.0
    f.vehicle.s = max(0.0, start)
    f.vehicle.speed = f.scene.cruise_mps
    seq = 0
    print("frame dist | per variant: on-footprint pts all/band, h p50/p95, det pts near | "
          "corridor band pts elsewhere")
    tot = [[0, 0] for _ in variants]
    while f.vehicle.s < s_ob - 1.0:
        s = f.render(seq * 100_000_000, seq)
        tr = next((t for t in s.truth if t["id"] == ob.id), None)
        row = []
        for i, p in enumerate(pipes):
            det = p.process(SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo,
                                         vehicle=s.vehicle))
            if tr is None:
                continue
            pts, px, h, keep, k = p.last_points
            on = footprint_distance(pts[:, :2], tr) <= 0.1 if len(pts) else np.zeros(0, bool)
            hh = h[on]
            near = (bool(len(det.points_xy))
                    and int((footprint_distance(det.points_xy, tr) <= 0.3).sum()))
            corr = keep & ~on & (pts[:, 0] < tr["x_m"] - 0.5) & (np.abs(pts[:, 1]) <= 1.2) \
                if len(pts) else np.zeros(0, bool)
            if -0.5 < tr["x_m"] < 15:
                tot[i][0] += 1
                tot[i][1] += bool(near)
            row.append(f"{int(on.sum())}/{int((on & keep).sum())} "
                       f"{np.percentile(hh, 50) if len(hh) else 0:.2f}/"
                       f"{np.percentile(hh, 95) if len(hh) else 0:.2f} {int(near)} | "
                       f"{int(corr.sum())}")
        if tr is not None and seq % a.every == 0:
            print(f"{seq:4d} {tr['x_m']:5.1f} || " + " || ".join(row), flush=True)
        f.step(0.1, GateState.CLEAR)
        seq += 1
    for v, (n, d) in zip(variants, tot):
        print(f"variant {v or 'defaults'}: obstacle 0-15 m ahead in {n} frames, "
              f"detected (points within 0.3 m) in {d}")
    for p in pipes:
        p.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
