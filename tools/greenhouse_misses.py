#!/usr/bin/env python3
"""Frame by frame, open loop: what the rgbd pipeline sees of each greenhouse obstacle as the
vehicle comes up to it, and where the points in the stop zone that are on no obstacle come from.

    python tools/greenhouse_misses.py --seeds 1-4 [--frames 2500] [--every 4] [--set k=v ...]
                                      [--json out.json]

The greenhouse-coverage scene of each (training) seed is driven open loop along its route (never
stopped: the vehicle drives through everything, so every approach range is seen). A frame is
rendered when an obstacle's footprint is within 7 m ahead of the front and 1.5 m across (every
frame), else every ``--every``-th frame (the empty aisle: phantoms). Per rendered frame, per
obstacle with pixels in the image (the simulator's material map): its distance from the vehicle's
front, its pixels, those with depth, suspected by the slope, in an obstacle group, and whether
any projected point lies within 0.3 m of its footprint. Per frame, the projected points in the
stop zone at standstill (2.0 m from the front, half width 1.25 m: the campaign's zones) that lie
on no obstacle (0.3 m): their material (bush, leaf, ground, sky/cover), height and cue.

Never run it on seeds >= 1000 (the acceptance set).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from appliance.perception import SensorInputs  # noqa: E402
from appliance.perception.rgbd import RgbdPipeline, RgbdPipelineConfig  # noqa: E402
from drivers.sim.field import SimField  # noqa: E402
from drivers.sim.world import MAT_BUSH, MAT_GROUND, MAT_LEAF, MAT_OBSTACLE, MAT_SKY  # noqa: E402
from hal.types import GateState  # noqa: E402

MAT_NAMES = {MAT_SKY: "sky", MAT_GROUND: "ground", MAT_BUSH: "bush", MAT_LEAF: "leaf"}
BANDS = [(0.0, 0.85), (0.85, 1.4), (1.4, 2.0), (2.0, 3.0), (3.0, 4.0), (4.0, 5.0)]


def pixel_counts(m, fr, r) -> dict:
    """What the rgbd pipeline's analysis ``r`` made of the obstacle's pixels ``m`` in RGB-D
    frame ``fr``: all, with depth, suspected, raised by colour, texture, depth holes."""
    return {"px": int(m.sum()), "depth_px": int((m & (fr.depth_m > 0)).sum()),
            "sus_px": int((m & r.suspected).sum()),
            "colour_px": int((m & r.colour_obstacles).sum()),
            "texture_px": int((m & r.texture_obstacles).sum())
            if r.texture_obstacles is not None else 0,
            "hole_px": int((m & r.hole_obstacles).sum())
            if r.hole_obstacles is not None else 0}


def parse_seeds(s: str) -> list[int]:
    out = []
    for part in s.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    if any(x >= 1000 for x in out):
        raise SystemExit("seeds >= 1000 are the acceptance set: not here")
    return out


def parse_set(items) -> dict:
    kw = {}
    for it in items or ():
        k, v = it.split("=", 1)
        f = {f.name: f for f in dataclasses.fields(RgbdPipelineConfig)}[k]
        d = f.default
        kw[k] = (v.lower() in ("1", "true", "yes")) if isinstance(d, bool) else \
            type(d)(v) if not isinstance(d, tuple) else tuple(x for x in v.split(",") if x)
    return kw


def band(d: float) -> str | None:
    for a, b in BANDS:
        if a <= d < b:
            return f"{a:.2f}-{b:.2f}"
    return None


def drive(seed: int, frames: int, every: int, pipe: RgbdPipeline, stop_len: float = 2.0,
          half_width: float = 1.25, near_m: float = 0.3):
    field = SimField("greenhouse-coverage", seed=seed, sensors=("rgbd",), rate_hz=10.0)
    veh = field.vehicle
    rear, length, width = field.scene.footprint
    front = -rear + length
    obs = field.world.obstacles
    per_obs = []          # one row per (frame, obstacle in view)
    phantom = []          # one row per frame with stop-zone points on no obstacle
    n_rendered = 0
    for i in range(frames):
        if veh.finished:
            break
        fps = [veh.footprint_in_vehicle(k) for k in range(len(obs))]
        ahead = [k for k, p in enumerate(fps) if len(p) and
                 ((p[:, 0] > front - 0.3) & (p[:, 0] < front + 7.0) & (np.abs(p[:, 1]) < 1.5)).any()]
        if ahead or i % every == 0:
            n_rendered += 1
            views: list = []
            fr = field.render_rgbd(i * 100_000_000, i, view_out=views)
            st = field.vehicle_state(i * 100_000_000, i)
            mat = views[0].mat
            r = pipe.analyse(SensorInputs(i * 100_000_000, rgbd=fr, vehicle=st), detail=False)
            pts = r.points_xy
            for k, o in enumerate(obs):
                m = mat == MAT_OBSTACLE + k
                npx = int(m.sum())
                if npx == 0:
                    continue
                p = fps[k]
                if not len(p):
                    continue
                dist = float(p[:, 0].min() - front)
                lat = float(np.abs(p[:, 1]).min())
                near = False
                if len(pts):
                    d2 = ((pts[:, None, :] - p[None, ::4, :]) ** 2).sum(-1).min(1)
                    near = bool((d2 < near_m ** 2).any())
                rows = np.nonzero(m.any(1))[0]
                per_obs.append({
                    "seed": seed, "frame": i, "id": o.id, "cls": o.cls,
                    "tone": getattr(o, "tone", ""), "height_m": round(o.height_m, 3),
                    "placement": getattr(o, "placement", ""),
                    "dist_m": round(dist, 3), "lat_m": round(lat, 3),
                    **pixel_counts(m, fr, r), "obs_px": int((m & r.obstacles).sum()),
                    "bottom_row": int(rows.max()), "top_row": int(rows.min()),
                    "detected": near})
            # stop-zone points on no obstacle
            if len(pts):
                inz = (pts[:, 0] >= front) & (pts[:, 0] < front + stop_len) & \
                    (np.abs(pts[:, 1]) < half_width)
                if inz.any():
                    zp = pts[inz]
                    on_obs = np.zeros(len(zp), bool)
                    for p in fps:
                        if len(p):
                            d2 = ((zp[:, None, :] - p[None, ::4, :]) ** 2).sum(-1).min(1)
                            on_obs |= d2 < near_m ** 2
                    if (~on_obs).any():
                        ph = zp[~on_obs]
                        phantom.append({"seed": seed, "frame": i, "points": int(len(ph)),
                                        "x_min": round(float(ph[:, 0].min() - front), 2),
                                        "y_med": round(float(np.median(ph[:, 1])), 2),
                                        **_sources(r, mat, fr, pipe, front, stop_len,
                                                   half_width, fps, near_m)})
        field.step(0.1, GateState.CLEAR)
    return per_obs, phantom, n_rendered


def _sources(r, mat, fr, pipe, front, stop_len, half_width, fps, near_m) -> dict:
    """Material / cue / height of the obstacle pixels whose 3-D points are the phantom ones."""
    cam, mount = fr.calib.camera, fr.calib.mount
    proj = r.projected if r.projected is not None else r.obstacles
    v, u = np.nonzero(proj)
    z = fr.depth_m[v, u]
    ok = (z > 0)
    v, u, z = v[ok], u[ok], z[ok]
    out: dict = {}
    if len(z):
        x = (u - cam.cx) / cam.fx * z
        y = (v - cam.cy) / cam.fy * z
        p = np.stack([x, y, z], 1) @ mount.camera_to_vehicle().T + mount.position
        inz = (p[:, 0] >= front) & (p[:, 0] < front + stop_len) & (np.abs(p[:, 1]) < half_width)
        on_obs = np.zeros(len(p), bool)
        for q in fps:
            if len(q):
                d2 = ((p[:, None, :2] - q[None, ::4, :]) ** 2).sum(-1).min(1)
                on_obs |= d2 < near_m ** 2
        sel = inz & ~on_obs
        mats = mat[v[sel], u[sel]]
        names = defaultdict(int)
        for mm, c in zip(*np.unique(mats, return_counts=True)):
            names[MAT_NAMES.get(int(mm), "obstacle" if mm >= MAT_OBSTACLE else str(mm))] += int(c)
        out["materials"] = dict(names)
        out["height_p50"] = round(float(np.median(p[sel, 2])), 3) if sel.any() else None
        out["height_max"] = round(float(p[sel, 2].max()), 3) if sel.any() else None
        cues = {}
        for name, mk in (("colour", r.colour_obstacles), ("texture", r.texture_obstacles)):
            if mk is not None:
                cues[name] = int(mk[v[sel], u[sel]].sum())
        out["cues"] = cues
        out["rows"] = [int(v[sel].min()), int(v[sel].max())] if sel.any() else None
    if r.hole_points:
        hp = r.points_xy[len(r.points_xy) - r.hole_points:]
        inz = (hp[:, 0] >= front) & (hp[:, 0] < front + stop_len) & (np.abs(hp[:, 1]) < half_width)
        out["hole_points_in_zone"] = int(inz.sum())
    return out


def summarise(per_obs: list[dict]) -> dict:
    """Per class and distance band: frames in view, detected, and the obstacle ids never held."""
    tab: dict = defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for row in per_obs:
        b = band(row["dist_m"])
        if b is None or row["lat_m"] > 0.9:
            continue
        t = tab[row["cls"]][b]
        t[0] += 1
        t[1] += int(row["detected"])
    return {c: {b: f"{v[1]}/{v[0]}" for b, v in sorted(d.items())} for c, d in tab.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1-4")
    ap.add_argument("--frames", type=int, default=2500)
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--set", action="append", help="RgbdPipelineConfig key=value")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import cv2
    cv2.setNumThreads(1)
    pipe = RgbdPipeline(RgbdPipelineConfig(**parse_set(a.set)))
    per_obs, phantom, n = [], [], 0
    t0 = time.process_time()
    for s in parse_seeds(a.seeds):
        po, ph, k = drive(s, a.frames, a.every, pipe)
        per_obs += po
        phantom += ph
        n += k
        print(f"seed {s}: {k} frames rendered, {len(po)} obstacle-frames, {len(ph)} frames with "
              f"stop-zone points on no obstacle ({time.process_time() - t0:.0f} s CPU)",
              file=sys.stderr)
    summ = summarise(per_obs)
    print(json.dumps({"rendered": n, "by_class_band": summ,
                      "phantom_frames": len(phantom)}, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps({"per_obstacle": per_obs, "phantom": phantom,
                                            "summary": summ, "set": a.set}, indent=0))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
