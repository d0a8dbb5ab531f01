#!/usr/bin/env python3
"""Open loop, one obstacle at a time: every class of the greenhouse-coverage distribution in every
colour the distribution draws (own, hi-vis, field-coloured, other), placed in the path of a
TRAINING seed's greenhouse, the vehicle driving up to it and through it; per frame whether the
rgbd pipeline's points lie on it (0.3 m), by distance from the vehicle's front.

    python tools/greenhouse_sweep.py [--seed 5] [--every 2] [--set k=v ...] [--json out.json]
    python tools/greenhouse_sweep.py --buckets [--seed 5] [--every 3]

``--buckets``: the bucket only, at the two ends of the distribution's size (x0.85 and x1.15 of the
prototype's diameter and height), in eight colours (its own yellow, a hi-vis red, the soil-,
dark-brown- and green-grey-coloured field palette entries, the "other" palette's black, the
bush green of the look-alike crate, the galvanised shiny bucket of the hand-placed greenhouse:
the last three are not drawn for buckets by greenhouse-coverage), each on the centre line and at
the bush edge (y = -(path half width - 0.05), where greenhouse-coverage puts "beside" things).

The colours are the scene module's palettes (drivers/sim/scenes.py ``_HIVIS``,
``_FIELD_COLOURED``, ``_OTHER``), not draws of any seed; the place is the first lane of the
seed's greenhouse, 8 m ahead of the start, on the path's centre line. Seeds >= 1000 refused.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from appliance.perception import SensorInputs  # noqa: E402
from appliance.perception.rgbd import RgbdPipeline, RgbdPipelineConfig  # noqa: E402
from drivers.sim import scenes as S  # noqa: E402
from drivers.sim.field import SimField  # noqa: E402
from drivers.sim.world import MAT_OBSTACLE  # noqa: E402
from hal.types import GateState  # noqa: E402

sys.path.insert(0, str(ROOT / "tools"))
from greenhouse_misses import parse_set, pixel_counts  # noqa: E402


def variants():
    protos = {o.cls: o for o in S._greenhouse_obstacles(np.random.default_rng(0))}
    out = []
    for cls in ("bucket", "crate", "box"):
        pr = protos[cls]
        cols = [("own", pr.colour)] + [("hi-vis", c) for c in S._HIVIS] + \
            [("field-coloured", c) for c in S._FIELD_COLOURED]
        for tone, c in cols:
            out.append((cls, tone, replace(pr, id="s1", colour=tuple(c), yaw_deg=20.0)))
    out.append(("look-alike-crate", "field-coloured",
                replace(protos["look-alike-crate"], id="s1", yaw_deg=20.0)))
    rng = np.random.default_rng(7)
    for pose in ("standing", "crouching", "lying"):
        for tone, pal in (("hi-vis", S._HIVIS[:1]), ("field-coloured", S._FIELD_COLOURED),
                          ("other", S._OTHER)):
            for c in pal:
                o = S._person(rng, "s1", 0.0, 0.0, pose)
                o = replace(o, colour=tuple(c), yaw_deg=60.0)
                out.append((o.cls, tone, o))
    return out


def bucket_variants(seed: int):
    """(name, obstacle, y) of the --buckets sweep (module doc)."""
    protos = {o.cls: o for o in S._greenhouse_obstacles(np.random.default_rng(0))}
    pr = protos["bucket"]
    half = S.build_scene("greenhouse-coverage", seed).params["path_half_width_m"]
    cols = {"own-yellow": pr.colour, "hivis-red": S._HIVIS[3], "soil": S._FIELD_COLOURED[5],
            "dark-brown": S._FIELD_COLOURED[4], "green-grey": S._FIELD_COLOURED[2],
            "black": S._OTHER[1], "bush-green": protos["look-alike-crate"].colour,
            "galvanised": (0.75, 0.75, 0.78)}
    out = []
    for size, k in (("small", 0.85), ("large", 1.15)):
        for cname, c in cols.items():
            for place, y in (("centre", 0.0), ("edge", -(half - 0.05))):
                o = replace(pr, id="s1", colour=tuple(c), length_m=pr.length_m * k,
                            width_m=pr.width_m * k, height_m=pr.height_m * k,
                            shiny=cname == "galvanised")
                out.append((f"{size} {cname} {place}", o, y))
    return out


def lone_obstacle_field(seed: int, o, x0: float = 9.0):
    """(field, vehicle, front bumper x): a greenhouse-coverage field of ``seed`` holding only
    obstacle ``o``, placed at (x0, 0) on the vehicle's path. Used by this sweep and by
    tests/test_rgbd_ground_coloured.py."""
    field = SimField("greenhouse-coverage", seed=seed, sensors=("rgbd",), rate_hz=10.0)
    o = replace(o, x=x0, y=0.0)
    o.x_start, o.y_start = x0, 0.0
    field.world.obstacles[:] = [o]
    veh = field.vehicle
    veh._footprints = [veh._footprint_points(o)]
    rear, length, _ = field.scene.footprint
    return field, veh, -rear + length


def approach(seed: int, o, pipe, every: int, x0: float = 9.0, y0: float = 0.0):
    field, veh, front = lone_obstacle_field(seed, o, x0)
    if y0:                       # off the centre line (the bush edge): move it there
        ob = field.world.obstacles[0]
        ob.y = ob.y_start = y0
        veh._footprints = [veh._footprint_points(ob)]
    rows = []
    for i in range(400):
        p = veh.footprint_in_vehicle(0)
        dist = float(p[:, 0].min() - front)
        if dist < -0.2:
            break
        if dist <= 6.0 and i % every == 0:
            views: list = []
            fr = field.render_rgbd(i * 100_000_000, i, view_out=views)
            st = field.vehicle_state(i * 100_000_000, i)
            m = views[0].mat == MAT_OBSTACLE
            r = pipe.analyse(SensorInputs(i * 100_000_000, rgbd=fr, vehicle=st), detail=False)
            pts = r.points_xy
            near = False
            if len(pts):
                d2 = ((pts[:, None, :] - p[None, ::4, :]) ** 2).sum(-1).min(1)
                near = bool((d2 < 0.09).any())
            rows.append({"dist_m": round(dist, 2), **pixel_counts(m, fr, r),
                         "detected": near})
        field.step(0.1, GateState.CLEAR)
    return rows


def held_from(rows):
    """The approach's frames 0.85-4.5 m ahead, and the distance it was held continuously from:
    the farthest from which every later frame (down to 0.85 m, the lowest ray) detected it."""
    band = [r for r in rows if 0.85 <= r["dist_m"] <= 4.5]
    held = None
    for r in sorted(band, key=lambda r: r["dist_m"]):
        if not r["detected"]:
            break
        held = r["dist_m"]
    return band, held


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--set", action="append")
    ap.add_argument("--only", default=None, help="class names, comma list")
    ap.add_argument("--buckets", action="store_true", help="the bucket size x colour x place "
                                                            "sweep instead (module doc)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.seed >= 1000:
        raise SystemExit("seeds >= 1000 are the acceptance set: not here")
    import cv2
    cv2.setNumThreads(1)
    pipe = RgbdPipeline(RgbdPipelineConfig(**parse_set(a.set)))
    res = []
    t0 = time.process_time()
    if a.buckets:
        for name, o, y in bucket_variants(a.seed):
            rows = approach(a.seed, o, pipe, a.every, y0=y)
            band, held = held_from(rows)
            # the nearest distance at which it still has pixels with depth in the image
            gone = min([r["dist_m"] for r in rows if r["depth_px"] > 0], default=None)
            res.append({"variant": name, "height_m": round(o.height_m, 2),
                        "diameter_m": round(o.width_m, 2), "y_m": round(y, 2),
                        "detected": sum(r["detected"] for r in band), "frames": len(band),
                        "held_from_m": held, "nearest_in_image_m": gone, "rows": rows})
            print(f"{name:24s} h {o.height_m:.2f} d {o.width_m:.2f} y {y:5.2f}: "
                  f"{res[-1]['detected']:3d}/{len(band):3d} held from {held}, last with depth "
                  f"in the image at {gone} m ({time.process_time() - t0:.0f} s CPU)", flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps(res))
        return 0
    for cls, tone, o in variants():
        if a.only and cls not in a.only.split(","):
            continue
        rows = approach(a.seed, o, pipe, a.every)
        band, held = held_from(rows)
        det = sum(r["detected"] for r in band)
        first = max([r["dist_m"] for r in rows if r["detected"]], default=None)
        res.append({"cls": cls, "tone": tone, "colour": [round(c, 2) for c in o.colour],
                    "height_m": round(o.height_m, 2), "frames_0.85_4.5": len(band),
                    "detected": det, "first_m": first, "held_from_m": held, "rows": rows})
        print(f"{cls:18s} {tone:15s} {str([round(c, 2) for c in o.colour]):20s} "
              f"{det:3d}/{len(band):3d} held from {held} first {first} "
              f"({time.process_time() - t0:.0f} s CPU)", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
