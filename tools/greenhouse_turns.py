#!/usr/bin/env python3
"""Could the Kinect have seen it? For every obstacle the vehicle hits on TRAINING
greenhouse-coverage seeds (driven open loop along the route, never stopped), what the RGB-D
camera could see of it in the seconds before contact — geometry only, no rendering, so hundreds
of seeds take minutes.

    python tools/greenhouse_turns.py --seeds 1-299 [--window-s 8] [--render headland]
                                     [--json out.json]
    python tools/greenhouse_turns.py --drive SEED:OBSTACLE_ID:SECONDS ...

Per hit: its class, placement (in-path, beside, crossing, headland = the end bays the U-turns
pass through), the frames of the last ``--window-s`` seconds in which it was visible to the
Kinect (``SimField._visible``: in the image, 0.5-5 m, a clear line of sight past the bush rows
and the other obstacles), of those the frames in which it lay in the stop-zone corridor ahead
(half width 0.5 m as the greenhouse runs, 0-4.5 m beyond the front), the largest yaw rate in
the last 2 s (turning), and one verdict:

- ``never in view``: visible in fewer than 2 frames of the window — no perception can stop for
  it (the end bay is hidden by the bush row's end from the lane, and in the 1-1.25 m U-turn the
  swept path is outside the 57 deg view and under the image's bottom edge);
- ``in view beside the zone``: seen (>= 2 frames) but never in the straight stop-zone corridor,
  then out of view before the vehicle turned into it — only a box that remembers what it saw
  and tests the turn's swept path could stop;
- ``in view in the zone``: seen in the corridor ahead: the box's business (a closed-loop drive
  says whether it stopped).

The geometric test is optimistic (its line of sight ignores the bushes' leaves): with
``--render headland`` (or ``all``) every frame it calls visible for an obstacle of that placement
is rendered, and the obstacle counts as seen there only with at least 50 pixels of valid depth in
the Kinect's image (the simulator's material map); the rgbd pipeline (defaults) runs on that
frame, and ``detected_frames`` counts the frames whose points lie within 0.3 m of its footprint.

``--drive SEED:ID:SECONDS``: closed loop instead (the real daemon, appliance/campaign_drive.py's
Drive, one process, one core) for that many simulated seconds on the seed's field with every
obstacle removed but that one (the lane's own obstacles would end the drive before the turn: a
greenhouse drive stands at its first true stop); prints the drive's collisions, stops, missed
stops and events.

Seeds >= 1000 (the acceptance set) are refused.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.sim.field import SimField  # noqa: E402
from drivers.sim.world import MAT_OBSTACLE  # noqa: E402
from hal.types import GateState  # noqa: E402

sys.path.insert(0, str(ROOT / "tools"))
from greenhouse_misses import parse_seeds  # noqa: E402

RATE_HZ = 10.0


def verdict(n_seen: int, n_zone: int) -> str:
    if n_seen < 2:
        return "never in view"
    return "in view in the zone" if n_zone >= 2 else "in view beside the zone"


def hits(seed: int, window_s: float = 8.0, half_width_m: float = 0.5, reach_m: float = 4.5,
         max_frames: int = 6000, render: str = "none", pipe=None) -> list[dict]:
    """One training seed driven open loop: one row per obstacle hit (see the module doc)."""
    if seed >= 1000:
        raise SystemExit("seeds >= 1000 are the acceptance set: not here")
    f = SimField("greenhouse-coverage", seed=seed, sensors=("rgbd",), rate_hz=RATE_HZ)
    veh = f.vehicle
    rear, length, _ = f.scene.footprint
    front = -rear + length
    obs = f.world.obstacles
    seen: dict[int, list] = {k: [] for k in range(len(obs))}    # (frame, ahead, |lat|, in zone)
    detected: dict[int, list] = {k: [] for k in range(len(obs))}   # frames with points on it
    yaw_rates: list[float] = []
    done: set[int] = set()
    out = []
    win = int(round(window_s * RATE_HZ))
    for i in range(max_frames):
        if veh.finished:
            break
        x, y, _ = veh.pose()
        cams = None
        for k, o in enumerate(obs):
            if k in done or math.hypot(o.x - x, o.y - y) > 7.0:
                continue
            if cams is None:
                cams = f._cameras()
            if f._visible(k, cams):
                p = veh.footprint_in_vehicle(k)
                if render == "all" or render == o.placement:
                    stamp = i * int(1e9 / RATE_HZ)
                    views: list = []
                    fr = f.render_rgbd(stamp, i, view_out=views)
                    m = views[0].mat == MAT_OBSTACLE + k
                    if int((m & (fr.depth_m > 0)).sum()) < 50:
                        continue
                    if pipe is not None:
                        from appliance.perception import SensorInputs
                        r = pipe.analyse(SensorInputs(stamp, rgbd=fr,
                                                      vehicle=f.vehicle_state(stamp, i)),
                                         detail=False)
                        pts = r.points_xy
                        if len(pts) and (((pts[:, None, :] - p[None, ::4, :]) ** 2).sum(-1)
                                         .min(1) < 0.09).any():
                            detected[k].append(i)
                ahead = p[:, 0] - front
                zone = bool(((np.abs(p[:, 1]) < half_width_m) & (ahead >= 0) &
                             (ahead <= reach_m)).any())
                seen[k].append((i, float(ahead.min()), float(np.abs(p[:, 1]).min()), zone))
        yaw_rates.append(abs(veh.yaw_rate))
        n_hit = len(veh.obstacles_hit)
        f.step(1.0 / RATE_HZ, GateState.CLEAR)
        for oid in veh.obstacles_hit[n_hit:]:
            k = next(j for j, o in enumerate(obs) if o.id == oid)
            if k in done:
                continue
            done.add(k)
            o = obs[k]
            s = [r for r in seen[k] if r[0] >= i - win]
            n_zone = sum(r[3] for r in s)
            d = [j for j in detected[k] if j >= i - win]
            p = veh.footprint_in_vehicle(k)
            out.append({
                "seed": seed, "id": oid, "cls": o.cls, "placement": o.placement,
                "height_m": round(o.height_m, 2), "frame": i,
                "contact_ahead_m": round(float(p[:, 0].min() - front), 2),
                "yaw_rate_max_2s": round(max(yaw_rates[-int(2 * RATE_HZ):]), 2),
                "seen_frames": len(s), "seen_in_zone_frames": n_zone,
                "rendered": render in ("all", o.placement),
                "detected_frames": len(d) if pipe is not None else None,
                "last_seen_s_before": None if not s else round((i - s[-1][0]) / RATE_HZ, 1),
                "last_seen_ahead_m": None if not s else round(s[-1][1], 2),
                "last_seen_lat_m": None if not s else round(s[-1][2], 2),
                "verdict": verdict(len(s), n_zone)})
    return out


def lone_drive(seed: int, oid: str, seconds: float) -> dict:
    """Closed loop on training ``seed`` with only obstacle ``oid`` in the field (module doc)."""
    if seed >= 1000:
        raise SystemExit("seeds >= 1000 are the acceptance set: not here")
    from appliance.campaign_drive import Drive
    d = Drive("greenhouse-coverage", seed, seconds / 60.0).build()
    f = d.field
    o = next(o for o in f.world.obstacles if o.id == oid)
    f.world.obstacles[:] = [o]
    f.vehicle._footprints = [f.vehicle._footprint_points(o)]
    out = d.run()
    r = out["result"]
    return {"seed": seed, "obstacle": f"{oid}/{o.cls}", "placement": o.placement,
            "simulated_s": r["simulated_s"], "distance_m": r["distance_m"],
            "collisions": r["collided_with"],
            "true_stops": r["true_stops"], "false_stops": r["false_stops"],
            "missed_stops": r["missed_stops"], "detections": r["detections"],
            "events": [(e["t_s"], e["event"], e["kind"], e["obstacle"], e["real_nearest_m"],
                        e.get("duration_s"), e["reason"]) for e in out["events"]]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1-299")
    ap.add_argument("--window-s", type=float, default=8.0)
    ap.add_argument("--render", default="none",
                    help="none | all | a placement (headland): render the frames the geometry "
                         "calls visible and run the rgbd pipeline on them")
    ap.add_argument("--drive", nargs="*", default=None, metavar="SEED:ID:SECONDS")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import cv2
    cv2.setNumThreads(1)
    if a.drive:
        res = []
        for spec in a.drive:
            seed, oid, secs = spec.split(":")
            t0 = time.process_time()
            res.append(lone_drive(int(seed), oid, float(secs)))
            print(json.dumps({**res[-1], "cpu_s": round(time.process_time() - t0)}), flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps(res, indent=0))
        return 0
    pipe = None
    if a.render != "none":
        from appliance.perception.rgbd import RgbdPipeline, RgbdPipelineConfig
        pipe = RgbdPipeline(RgbdPipelineConfig())
    rows: list[dict] = []
    t0 = time.process_time()
    for s in parse_seeds(a.seeds):
        rows += hits(s, a.window_s, render=a.render, pipe=pipe)
    tab = Counter((r["placement"], r["verdict"]) for r in rows)
    print(f"{len(rows)} obstacles hit on {len(parse_seeds(a.seeds))} seeds "
          f"({time.process_time() - t0:.0f} s CPU)")
    for (pl, v), n in sorted(tab.items()):
        print(f"  {pl:10s} {v:26s} {n:5d}")
    by_cls = Counter((r["cls"], r["verdict"]) for r in rows if r["placement"] == "headland")
    print("headland, by class:")
    for (c, v), n in sorted(by_cls.items()):
        print(f"  {c:18s} {v:26s} {n:5d}")
    if pipe is not None:
        ren = [r for r in rows if r["rendered"]]
        print(f"rendered ({a.render}): {len(ren)} hits; detected by the rgbd pipeline in >= 2 "
              f"frames of the window: "
              f"{sum(r['detected_frames'] >= 2 for r in ren)}; by verdict:")
        for v in ("never in view", "in view beside the zone", "in view in the zone"):
            rv = [r for r in ren if r["verdict"] == v]
            print(f"  {v:26s} {len(rv):4d} hits, detected in >= 2 frames: "
                  f"{sum(r['detected_frames'] >= 2 for r in rv)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=0))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
