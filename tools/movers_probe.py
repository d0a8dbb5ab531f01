"""What the movers' tracker would stop for, and what is really there. One closed-loop campaign
drive per seed, run exactly as ``fieldguard campaign`` does (appliance/campaign_drive.Drive)
with ``[tracking] movers`` on but NOT applied (the box decides as without it: the drive is the
base drive), and per cycle a record of every confirmed track the movers' tracker holds that
moves (Kalman speed >= 0.3 m/s, 3 hits or more): its features (Kalman and fitted velocity, the
fit's residual, its run of hits, size, sources, points) and the truth (the nearest real
obstacle's distance from the track's centre, whether it is a walker walking now), and
whether the movers' rule as configured would have stopped for it.

    python tools/movers_probe.py stubble-crossing 1,2 --minutes 4 --out /tmp/probe.jsonl \
        [--config extra.toml] [--shadow-range 100]

Then ``--summary /tmp/probe.jsonl`` prints, for tracks on a real walker (within 1 m) and for
the rest, how the features are spread: the numbers to set the movers' thresholds on (training
seeds only: the acceptance seeds >= 1000 are never probed).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

BOX = {"perception": {"pipelines": ["stereo-novelty", "laser"]}, "tracking": {"movers": True}}


def probe(kind: str, seed: int, minutes: float, extra: dict | None, out,
          shadow_cfg=None) -> int:
    from appliance.campaign import make_spec
    from appliance.campaign_drive import Drive, deep_merge
    from appliance.decision import DecisionCore
    spec = make_spec(kind, seed, minutes, 0.5, deep_merge(BOX, extra or {}))
    d = Drive(kind, seed, minutes, config_data=spec["config"], stereo_scale=0.5)
    d.build()
    core = d.daemon.loop.core
    orig = DecisionCore._with_movers
    n = [0]
    shadow = None
    if shadow_cfg is not None:        # the same rule under another config, on the same input
        shadow = DecisionCore(shadow_cfg(core.cfg))
    cost = {"movers_ms": [], "shadow_ms": [], "differ": 0, "cycles": 0}

    def observe(pic, detections, vehicle, now_ns):
        c0 = time.thread_time()
        applied = orig(core, pic, detections, vehicle, now_ns)
        cost["movers_ms"].append((time.thread_time() - c0) * 1e3)
        if shadow is not None:
            c0 = time.thread_time()
            other = orig(shadow, pic, detections, vehicle, now_ns)
            cost["shadow_ms"].append((time.thread_time() - c0) * 1e3)
            cost["cycles"] += 1
            if (other.verdict.in_stop > 0) != (applied.verdict.in_stop > 0) or \
                    (other.verdict.in_slow > 0) != (applied.verdict.in_slow > 0):
                cost["differ"] += 1
        would = applied.verdict.in_stop > pic.verdict.in_stop
        tr = core.movers
        x, y, yaw = d.vehicle.pose()
        c, s = math.cos(yaw), math.sin(yaw)
        tw = d.field.world.time_s if hasattr(d.field.world, "time_s") else 0.0
        by_id = {t.id: t for t in tr.tracks}
        for v in tr.views(confirmed_only=True):
            t = by_id.get(v.id)
            if v.coasting or t is None or t.hits < 3 or math.hypot(v.vx_mps, v.vy_mps) < 0.3:
                continue
            fx, fy, rms, span, nfit = tr.motion_fit(t)
            wx, wy = x + c * v.x_m - s * v.y_m, y + s * v.x_m + c * v.y_m
            best, walker = math.inf, False
            for o in d.field.world.obstacles:
                dist = max(0.0, math.hypot(o.x - wx, o.y - wy) - 0.5 * math.hypot(
                    o.length_m, o.width_m))
                if dist < best:
                    best, walker = dist, o.velocity_now(tw) != (0.0, 0.0)
            out.write(json.dumps({
                "kind": kind, "seed": seed, "t_s": round(now_ns / 1e9, 1), "id": v.id,
                "x_m": round(v.x_m, 2), "y_m": round(v.y_m, 2),
                "kalman_mps": round(math.hypot(v.vx_mps, v.vy_mps), 2),
                "fit_mps": round(math.hypot(fx, fy), 2), "fit_rms_m": round(rms, 3),
                "fit_span_s": round(span, 2), "fit_n": nfit, "run": t.run, "hits": t.hits,
                "length_m": round(v.length_m, 2), "width_m": round(v.width_m, 2),
                "points": int(t.points), "sources": list(v.sources),
                "stopped_for": bool(would and v.id in applied.verdict.track_ids),
                "real_m": None if best == math.inf else round(best, 2), "walker": walker,
            }) + "\n")
            n[0] += 1
        return pic                      # not applied: the base drive

    core._with_movers = observe
    d.run()
    for k in ("movers_ms", "shadow_ms"):
        a = np.array(cost[k]) if cost[k] else np.zeros(1)
        print(f"{kind} {seed}: {k} p50 {np.percentile(a, 50):.2f} p99 {np.percentile(a, 99):.2f}"
              f" max {a.max():.2f}", flush=True)
    if shadow is not None:
        print(f"{kind} {seed}: the shadow config's verdict (stop / slow) differs in "
              f"{cost['differ']} of {cost['cycles']} cycles", flush=True)
    return n[0]


def summary(path: str) -> None:
    rows = [json.loads(x) for x in open(path)]
    groups = {"on a walker (<= 1 m)": [r for r in rows if r["real_m"] is not None
                                       and r["real_m"] <= 1.0 and r["walker"]],
              "on a still obstacle (<= 1 m)": [r for r in rows if r["real_m"] is not None
                                               and r["real_m"] <= 1.0 and not r["walker"]],
              "on nothing real": [r for r in rows if r["real_m"] is None or r["real_m"] > 1.0]}
    keys = ("kalman_mps", "fit_mps", "fit_rms_m", "run", "width_m", "length_m", "points")
    for name, g in groups.items():
        tracks = {(r["kind"], r["seed"], r["id"]) for r in g}
        stops = {(r["kind"], r["seed"], r["id"]) for r in g if r["stopped_for"]}
        print(f"{name}: {len(g)} records, {len(tracks)} tracks, {len(stops)} would stop")
        if not g:
            continue
        for k in keys:
            a = np.array([r[k] for r in g], float)
            print(f"  {k:11s} p10 {np.percentile(a, 10):7.3f}  p50 {np.percentile(a, 50):7.3f}"
                  f"  p90 {np.percentile(a, 90):7.3f}")
        src = {}
        for r in g:
            key = "+".join(r["sources"])
            src[key] = src.get(key, 0) + 1
        print("  sources", dict(sorted(src.items(), key=lambda a: -a[1])))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", nargs="?")
    ap.add_argument("seeds", nargs="?", help="e.g. 1,2,3 (training seeds only)")
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--config", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--summary", default=None, help="summarise a probe's JSONL")
    ap.add_argument("--shadow-range", type=float, default=None,
                    help="also run the movers' rule with [tracking] movers_range_m = this on "
                         "the same input, timing both and counting the cycles their stop/slow "
                         "verdicts differ in")
    a = ap.parse_args(argv)
    if a.summary:
        summary(a.summary)
        return 0
    if not (a.kind and a.seeds and a.out):
        ap.error("give KIND SEEDS --out FILE, or --summary FILE")
    seeds = [int(s) for s in a.seeds.split(",")]
    if any(s >= 1000 for s in seeds):
        ap.error("seeds >= 1000 are the acceptance set: not probed")
    from appliance.campaign import load_extra_config
    extra = load_extra_config(a.config) if a.config else None
    with open(a.out, "w") as out:
        for s in seeds:
            sh = None
            if a.shadow_range is not None:
                def sh(cfg, r=a.shadow_range):
                    return dataclasses.replace(cfg, tracking=dataclasses.replace(
                        cfg.tracking, movers_range_m=r))
            k = probe(a.kind, s, a.minutes, extra, out, sh)
            print(f"{a.kind} {s}: {k} records", flush=True)
    summary(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
