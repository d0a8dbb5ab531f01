"""Would a ground estimate ahead let the planar laser tell a stubble tuft from an obstacle?

    python tools/laser_ground_probe.py KIND SEEDS --minutes 2 [--config extra.toml] [--json]

Drives each training seed as ``fieldguard campaign`` does (laser pipeline unless the config
says otherwise; the defaults' ``min_width_m``) and at EVERY cycle reads the simulator's truth
for each return the pipeline keeps in the path ahead (0-8 m beyond the vehicle's front,
within the zone's half width + 0.5 m): what the beam hit, and how high above the real ground
at that place it hit (the scan plane's height there: 0.7 m on the flat, less where the ground
rises or the vehicle pitches nose-down). A rule "drop a return where the plane is lower than
T above the ground there" needs the ground ahead, which a planar laser does not measure (the
stereo pipeline's fitted ground, appliance/perception/ground.py, would be one source); this
probe measures, with the TRUE ground (an upper bound on what an estimate can give), what such
a rule would remove for each T:

- stubble: the share of the stubble returns it removes (in the stop zone and in the path);
- obstacles: per class, the share of (obstacle, cycle) sightings in the path it loses
  entirely (every kept return of that obstacle that cycle below T), and the median distance
  from the front at which each obstacle was first seen, with and without the rule.

``--confirm novelty,learned,points`` (with a config that runs a camera pipeline beside the
laser) adds what ``[grid] laser_confirm_by`` would say of the same returns: the share of the
stubble returns the camera had in view that it leaves unconfirmed (a SLOW instead of a STOP),
and per obstacle class the sightings it does not confirm (docs/proving-ground.md "The laser
confirmed by the camera").

Training seeds only (< 1000): a tool for deciding what to build, not a score.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

THRESHOLDS = (0.45, 0.5, 0.55, 0.6, 0.65)


def parse_seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def training_laser_setup(tool: str, seeds_text: str, config: str | None
                         ) -> tuple[list[int], dict] | None:
    """For the laser probes: (the training seeds of ``seeds_text``, the drives' extra config:
    the laser alone with ``config`` merged over it), or None after one line on stderr naming
    ``tool`` (seeds that do not parse, acceptance seeds, a config that does not load)."""
    try:
        seeds = parse_seeds(seeds_text)
    except ValueError:
        print(f"{tool}: seeds must look like 1-10 or 1,3,5 (got {seeds_text!r})",
              file=sys.stderr)
        return None
    if any(s >= 1000 for s in seeds):
        print(f"{tool}: seeds >= 1000 are the acceptance set; decide on training seeds",
              file=sys.stderr)
        return None
    from appliance.campaign import load_extra_config
    from appliance.campaign_drive import deep_merge
    from hal.errors import FieldguardError
    try:
        return seeds, deep_merge({"perception": {"pipelines": ["laser"]}},
                                 load_extra_config(config) if config else {})
    except FieldguardError as exc:
        print(f"{tool}: {exc}", file=sys.stderr)
        return None


def drive_each(tool: str, seeds: list[int], probe) -> list:
    """``probe(seed)`` for each seed in turn, a progress line on stderr after each."""
    out = []
    for i, s in enumerate(seeds):
        out.append(probe(s))
        print(f"{tool}: {i + 1}/{len(seeds)} drives", file=sys.stderr, flush=True)
    return out


def confirmed(res, loc: np.ndarray, mount, names, radius_m: float) -> np.ndarray:
    """Per laser return (``loc``: scanner-frame points): 1.0 where a camera pipeline's view
    this cycle confirms it as ``[grid] laser_confirm_by = names`` would (appliance/decision.py),
    0.0 where a camera had it in view and did not, nan where no camera had it in view (or
    ``names`` is empty)."""
    from appliance.decision import camera_confirms, camera_views
    from appliance.perception.laser import plane_points
    out = np.full(len(loc), np.nan)
    cams = camera_views(res.detections)
    if not names or not cams or not len(loc):
        return out
    xy, z = plane_points(loc, mount)                      # where the pipeline puts them
    inside, ok = camera_confirms(cams, np.column_stack([xy, z]), names, radius_m)
    out[inside] = ok[inside].astype(float)
    return out


def probe_drive(kind: str, seed: int, minutes: float, extra: dict,
                confirm_by: tuple = (), radius: float = 0.3, stereo_scale: float = 0.5) -> dict:
    from appliance.campaign import make_spec
    from appliance.campaign_drive import Drive
    from appliance.perception.laser import segment_widths
    from drivers.sim.world import MAT_OBSTACLE, MAT_STUBBLE
    spec = make_spec(kind, seed, minutes, stereo_scale, extra)
    d = Drive(kind, seed, minutes, config_data=spec["config"], stereo_scale=stereo_scale)
    d.build()
    z, f = d.zones, d.field
    world = f.scene.world
    lcfg = d.cfg.perception.laser
    # (height above the ground, in the stop zone, the same above the camera's ground or nan)
    # (height above the ground, in the stop zone, the same above the camera's ground or nan,
    #  the camera's confirmation: 1 / 0 / nan as ``confirmed``)
    stubble: list[tuple[float, bool, float, float]] = []
    # (class, obstacle, ahead, max h, max h above the camera's ground or nan)
    # ... + (confirmed by a camera on any return, in the stop zone)
    sightings: list[tuple[str, int, float, float, float, float, bool]] = []

    def after(res):
        scan = res.inputs.laser
        if scan is None:
            return
        g = scan.geometry
        r = np.asarray(scan.ranges_m, float)
        ang = g.angles_rad()
        ok = np.isfinite(r) & (r >= lcfg.min_range_m) & (r <= min(lcfg.max_range_m,
                                                                 g.range_max_m))
        if lcfg.min_width_m > 0:
            ok &= segment_widths(r, ok, abs(np.radians(g.angle_step_deg)),
                                 lcfg.segment_jump_m) >= lcfg.min_width_m
        if not ok.any():
            return
        loc = np.stack([r * np.cos(ang), r * np.sin(ang), 0 * r], 1)[ok]
        c, _, rb = f._sensor_pose(g.mount)
        wp = c + loc @ rb.T                               # where the beam really hit
        ahead = g.mount.x_m + loc[:, 0] - z.front_x_m
        vy = g.mount.y_m + loc[:, 1]
        stop_len = res.verdict.stop_len_m if res.verdict is not None else z.min_stop_m
        near = (ahead >= 0) & (ahead <= 8.0) & (np.abs(vy) <= z.half_width_m + 0.5)
        if not near.any():
            return
        wx, wy = wp[near, 0].astype(np.float32), wp[near, 1].astype(np.float32)
        h = wp[near, 2] - world.ground(wx, wy)
        _, mat = world.height(wx, wy)
        a = ahead[near]
        # the ground a camera pipeline measured this cycle (stereo-novelty ground_for_laser),
        # against the scan plane where the pipeline puts it (vehicle frame)
        cam = next((o.ground for n, o in res.detections.items()
                    if n != "laser" and o is not None and o.ground is not None), None)
        if cam is not None:
            plane_z = (loc @ g.mount.rotation().T)[:, 2] + g.mount.z_m
            he = plane_z[near] - cam.z(g.mount.x_m + loc[near, 0], vy[near])
        else:
            he = np.full(len(h), np.nan)
        conf = confirmed(res, loc[near], g.mount, confirm_by, radius)
        st = mat == MAT_STUBBLE
        stubble.extend(zip(h[st].tolist(), (a[st] <= stop_len).tolist(), he[st].tolist(),
                           conf[st].tolist()))
        for k in np.unique(mat[mat >= MAT_OBSTACLE]):
            m = mat == k
            o = world.obstacles[int(k) - MAT_OBSTACLE]
            c = conf[m]
            sightings.append((o.cls, int(k) - MAT_OBSTACLE, float(a[m].min()),
                              float(h[m].max()), float(np.max(he[m])),
                              float("nan") if np.isnan(c).all() else float(np.nanmax(c)),
                              bool(np.any(a[m] <= stop_len))))

    d.daemon.loop.on_cycle.append(after)
    res = d.run()["result"]
    return {"seed": seed, "stubble": stubble, "sightings": sightings,
            "false_stops": res["false_stops"], "collisions": res["collisions"]}


def summarise(drives: list[dict], estimate: bool = False) -> dict:
    """The removal table with the true ground, or (``estimate``) with the camera's ground
    where it gave one (returns without one count as kept)."""
    col = 2 if estimate else 0
    st = np.array([r[col] for dr in drives for r in dr["stubble"]], float)
    st_zone = np.array([r[col] for dr in drives for r in dr["stubble"] if r[1]], float)
    err = np.array([r[2] - r[0] for dr in drives for r in dr["stubble"]], float)
    err = err[np.isfinite(err)]
    rows = []
    for t in (-np.inf,) + THRESHOLDS:               # -inf: no rule (a hit may read a cm below
        #                                             the sampled ground: -inf keeps those too)
        row = {"T_m": None if t == -np.inf else t,
               "stubble_removed": round(float(np.mean(st < t)), 3) if len(st) else None,
               "stubble_stop_zone_removed": (round(float(np.mean(st_zone < t)), 3)
                                             if len(st_zone) else None),
               "classes": {}}
        by: dict[str, dict] = {}
        for dr in drives:
            first: dict = {}
            for cls, k, ahead, *hs in dr["sightings"]:
                hmax = hs[1] if estimate else hs[0]
                b = by.setdefault(cls, {"sightings": 0, "lost": 0, "first": []})
                b["sightings"] += 1
                if hmax < t:                              # nan (no estimate): kept
                    b["lost"] += 1
                else:
                    first[(cls, k)] = max(first.get((cls, k), 0.0), ahead)
            seen = {(cls, k) for cls, k, *_ in dr["sightings"]}
            for key in seen:
                by[key[0]]["first"].append(first.get(key))
        for cls, b in sorted(by.items()):
            held = [x for x in b["first"] if x is not None]
            row["classes"][cls] = {
                "sightings": b["sightings"],
                "lost": round(b["lost"] / b["sightings"], 3),
                "objects": len(b["first"]), "never_seen": len(b["first"]) - len(held),
                "first_seen_median_m": round(float(np.median(held)), 2) if held else None}
        rows.append(row)
    oe = np.array([x[4] - x[3] for dr in drives for x in dr["sightings"]], float)
    oe = oe[np.isfinite(oe)]
    return {"drives": len(drives), "ground": "camera" if estimate else "true",
            "stubble_returns": int(len(st)),
            "estimated_share": round(float(len(err) / max(1, len(st))), 3),
            "stubble_error_p10_p50_p90": ([round(float(q), 3) for q in
                                           np.percentile(err, [10, 50, 90])] if len(err) else None),
            "obstacle_error_p10_p50_p90": ([round(float(q), 3) for q in
                                             np.percentile(oe, [10, 50, 90])] if len(oe) else None),
            "stubble_stop_zone_returns": int(len(st_zone)),
            "stubble_h_p10_p50_p90": ([round(float(q), 2) for q in
                                       np.nanpercentile(st, [10, 50, 90])]
                                      if np.isfinite(st).any() else None),
            "rows": rows}


def summarise_confirm(drives: list[dict]) -> dict:
    """What ``[grid] laser_confirm_by`` would say of the returns the camera had in view: the
    share of stubble returns it leaves unconfirmed (a SLOW instead of a STOP), in the path and
    in the stop zone, and per obstacle class the share of (obstacle, cycle) sightings with no
    confirmed return, and the obstacles that had returns in the stop zone in view and were
    never confirmed there."""
    st = np.array([r[3] for dr in drives for r in dr["stubble"]], float)
    stz = np.array([r[3] for dr in drives for r in dr["stubble"] if r[1]], float)
    out = {"stubble_in_view": int(np.isfinite(st).sum()),
           "stubble_unconfirmed": (round(float(np.mean(st[np.isfinite(st)] == 0)), 3)
                                   if np.isfinite(st).any() else None),
           "stubble_stop_zone_in_view": int(np.isfinite(stz).sum()),
           "stubble_stop_zone_unconfirmed": (round(float(np.mean(stz[np.isfinite(stz)] == 0)), 3)
                                             if np.isfinite(stz).any() else None),
           "classes": {}}
    for dr in drives:
        zone: dict = {}
        for cls, k, ahead, _h, _he, conf, in_zone in dr["sightings"]:
            b = out["classes"].setdefault(cls, {"sightings_in_view": 0, "unconfirmed": 0,
                                               "zone_objects": 0, "zone_never_confirmed": 0})
            if np.isnan(conf):
                continue
            b["sightings_in_view"] += 1
            b["unconfirmed"] += int(conf == 0)
            if in_zone:
                zone[(cls, k)] = max(zone.get((cls, k), 0.0), conf)
        for (cls, _k), best in zone.items():
            out["classes"][cls]["zone_objects"] += 1
            out["classes"][cls]["zone_never_confirmed"] += int(best == 0)
    for b in out["classes"].values():
        n = b["sightings_in_view"]
        b["unconfirmed"] = round(b["unconfirmed"] / n, 3) if n else None
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seeds", help="training seeds, e.g. 1-10")
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--config", default=None, help="TOML merged over the drive's config")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    ap.add_argument("--estimate", action="store_true",
                    help="the table with the camera's ground (the config must run "
                         "stereo-novelty with ground_for_laser) instead of the true one")
    ap.add_argument("--confirm", default="",
                    help="also what [grid] laser_confirm_by = these (comma-separated, e.g. "
                         "novelty,learned,points) would leave unconfirmed (the config must "
                         "run a camera pipeline beside the laser)")
    ap.add_argument("--stereo-scale", type=float, default=0.5,
                    help="the stereo pair's size against 1280x1024, as the campaign's "
                         "(0.1-1.0; default 0.5)")
    a = ap.parse_args(argv)
    if not 0.1 <= a.stereo_scale <= 1.0:
        print(f"laser_ground_probe: --stereo-scale must be in [0.1, 1.0], got {a.stereo_scale}",
              file=sys.stderr)
        return 2
    from appliance.perception.view import CONFIRM_NAMES
    confirm_by = tuple(n for n in a.confirm.split(",") if n)
    bad = [n for n in confirm_by if n not in CONFIRM_NAMES]
    if bad:
        print(f"laser_ground_probe: --confirm: unknown camera evidence {bad[0]!r}; known: "
              f"{', '.join(CONFIRM_NAMES)}", file=sys.stderr)
        return 2
    setup = training_laser_setup("laser_ground_probe", a.seeds, a.config)
    if setup is None:
        return 2
    seeds, extra = setup
    drives = drive_each("laser_ground_probe", seeds,
                        lambda s: probe_drive(a.kind, s, a.minutes, extra, confirm_by,
                                              stereo_scale=a.stereo_scale))
    summary = summarise(drives, a.estimate)
    if confirm_by:
        summary["confirm"] = {"by": list(confirm_by), **summarise_confirm(drives)}
    if a.json:
        print(json.dumps(summary))
        return 0
    if confirm_by:
        c = summary["confirm"]
        pct = (lambda v: "-" if v is None else f"{100 * v:.0f} %")
        print(f"laser_confirm_by {list(confirm_by)}: stubble returns a camera had in view "
              f"{c['stubble_in_view']}, unconfirmed {pct(c['stubble_unconfirmed'])}; in the "
              f"stop zone {c['stubble_stop_zone_in_view']}, unconfirmed "
              f"{pct(c['stubble_stop_zone_unconfirmed'])}")
        for cls, b in sorted(c["classes"].items()):
            print(f"  {cls}: sightings in view {b['sightings_in_view']}, unconfirmed "
                  f"{pct(b['unconfirmed'])}; in the stop zone {b['zone_objects']} objects, "
                  f"never confirmed there {b['zone_never_confirmed']}")
    print(f"{summary['drives']} drives, {summary['stubble_returns']} stubble returns kept in "
          f"the path ({summary['stubble_stop_zone_returns']} in the stop zone), plane above "
          f"the {summary['ground']} ground at them p10/p50/p90 "
          f"{summary['stubble_h_p10_p50_p90']} m")
    if summary["stubble_error_p10_p50_p90"] is not None:
        print(f"the camera's ground gave a height for {100 * summary['estimated_share']:.0f} % "
              f"of them; camera minus true, p10/p50/p90: stubble "
              f"{summary['stubble_error_p10_p50_p90']} m, obstacles "
              f"{summary['obstacle_error_p10_p50_p90']} m")
    classes = sorted({c for r in summary["rows"] for c in r["classes"]})
    print("| T (m) | stubble removed | in stop zone | " + " | ".join(
        f"{c}: lost, never, first seen" for c in classes) + " |")
    print("|---" * (3 + len(classes)) + "|")
    for r in summary["rows"]:
        cells = []
        for c in classes:
            v = r["classes"].get(c)
            cells.append("-" if v is None else
                         f"{100 * v['lost']:.0f} %, {v['never_seen']}/{v['objects']}, "
                         f"{v['first_seen_median_m']} m")
        pc = ["-" if v is None else f"{100 * v:.0f} %"
              for v in (r["stubble_removed"], r["stubble_stop_zone_removed"])]
        tm = "none" if r["T_m"] is None else f"{r['T_m']:.2f}"
        print(f"| {tm} | {pc[0]} | {pc[1]} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
