"""Would a second planar laser, tilted down to meet the ground a few metres ahead, see what
the level one cannot (dogs, people lying, thin stakes) without stopping for stubble?

    python tools/tilted_laser_probe.py KIND SEEDS --minutes 2 [--meet 5,7] [--mount-z 0.7]
        [--config extra.toml] [--json]

Drives each training seed as ``fieldguard campaign`` does with the shipped box (the level
laser alone unless the config says otherwise) and, at every cycle, casts a SECOND scan in the
simulator (the same SICK-like geometry: +-135 deg, 0.5 deg) from a mount at ``--mount-z``
pitched down so that its plane meets flat ground ``--meet`` metres ahead of the mount. The
second scan is not fed to the box (the drive is the shipped box's); it is judged here, with
only what a box would know:

- each return projected with the mount and the vehicle's IMU roll and pitch;
- the scan's own ground: a tilted plane hits the ground along a line across the path, so
  each return's ground is a low percentile (``--pct``) of the heights of the returns within
  ``--window`` metres of it across the path and 2 m along it;
- a return is an obstacle when it stands more than T above that ground, on a run of
  neighbouring beams at least W wide (:func:`appliance.perception.laser.segment_widths`).

Then the simulator's truth says what each return hit (ground, stubble, which obstacle). For
each (T, W) it reports, in the corridor ahead (0-10 m beyond the front, within the zone's half
width + 0.5 m): the cycles with an obstacle return on ground or stubble (what would be a
false SLOW or STOP: per hour, and in the stop zone), and per obstacle class the objects it
flagged at least once, how far ahead of the front at the farthest, and — for the obstacles
the shipped box collided with — whether the tilted scan flagged them before the collision.

Training seeds only (< 1000): a tool for deciding what to build (a hardware question), not a
score. No second laser exists in the product; this measures whether one is worth adding.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from tools.laser_ground_probe import drive_each, training_laser_setup  # noqa: E402

HEIGHTS = (0.2, 0.3, 0.4)          # T: above the scan's own ground
WIDTHS = (0.1, 0.2, 0.3)           # W: a run of beams at least this wide
CORRIDOR_M = 10.0


def parse_list(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def scan_heights(r: np.ndarray, ang: np.ndarray, mount, roll: float, pitch: float,
                 window_m: float = 1.5, pct: float = 10.0, along_m: float = 12.0,
                 region: tuple[float, float, float] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tilted scan as a box would read it: (points (N, 3) in the vehicle's gravity-aligned
    frame, height of each above the scan's own ground (nan where no return), valid mask).
    The ground under a return is the ``pct`` percentile of the heights of the returns within
    ``window_m`` across (y) and ``along_m`` along (x) of it (itself included): the plane cuts
    the ground along a line, so most returns around any one are ground. The window along must
    reach the line from what stands before it: the plane hits an object of height h up to
    h x meet / mount height before the line (3.2 m for a 0.45 m dog, a 0.7 m mount meeting the
    ground 5 m ahead), where the object's own returns are all there is. ``region`` (x_min,
    x_max, |y| max): only returns there are judged (and serve as ground), the rest are not
    valid."""
    from hal.types import rotation_rpy
    ok = np.isfinite(r) & (r >= 0.3)
    local = np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros_like(r)], axis=1)
    rot = rotation_rpy(roll, pitch, 0.0) @ mount.rotation()
    pts = np.where(ok[:, None], local, 0.0) @ rot.T + mount.position
    if region is not None:
        ok &= (pts[:, 0] >= region[0]) & (pts[:, 0] <= region[1]) & (
            np.abs(pts[:, 1]) <= region[2])
    above = np.full(len(r), np.nan)
    idx = np.flatnonzero(ok)
    if len(idx):
        p = pts[idx]
        near = ((np.abs(p[:, None, 1] - p[None, :, 1]) <= window_m)
                & (np.abs(p[:, None, 0] - p[None, :, 0]) <= along_m))
        z = np.where(near, p[None, :, 2], np.nan)
        ground = np.nanpercentile(z, pct, axis=1)
        above[idx] = p[:, 2] - ground
    return pts, above, ok


def flag(r: np.ndarray, above: np.ndarray, ok: np.ndarray, step_rad: float, t_m: float,
         w_m: float, jump_m: float = 0.15) -> np.ndarray:
    """Obstacle returns: more than ``t_m`` above the scan's ground, on a run of neighbouring
    such beams (ranges within ``jump_m``) at least ``w_m`` wide."""
    from appliance.perception.laser import segment_widths
    high = ok & (np.nan_to_num(above, nan=-np.inf) > t_m)
    if not high.any():
        return high
    return high & (segment_widths(np.nan_to_num(r, nan=0.0), high, step_rad, jump_m) >= w_m)


def probe_drive(kind: str, seed: int, minutes: float, extra: dict, meets: list[float],
                mount_z: float, window_m: float, pct: float) -> dict:
    from appliance.campaign import make_spec
    from appliance.campaign_drive import Drive
    from drivers.sim.field import laser_geometry
    from drivers.sim.world import MAT_OBSTACLE, MAT_STUBBLE
    from hal.types import Mount
    spec = make_spec(kind, seed, minutes, 0.5, extra)
    d = Drive(kind, seed, minutes, config_data=spec["config"], stereo_scale=0.5)
    d.build()
    z, f = d.zones, d.field
    world = f.scene.world
    base = laser_geometry()
    # one second scanner per meet: the field's laser geometry on a lower-pitched mount
    geos = {m: replace(base, mount=Mount(base.mount.x_m, 0.0, mount_z, 0.0,
                                         math.degrees(math.atan2(mount_z, m)), 0.0))
            for m in meets}
    ang = base.angles_rad()
    step = abs(math.radians(base.angle_step_deg))
    cycles = [0]
    # per meet: per (T, W): [false cycles in corridor, false cycles in the stop zone]
    false = {m: {(t, w): [0, 0] for t in HEIGHTS for w in WIDTHS} for m in meets}
    # per meet: obstacle id -> {"cls", "hit": farthest ahead hit, (T, W): farthest flagged}
    seen: dict = {m: {} for m in meets}
    hit_t: dict[str, int] = {}                      # obstacle id -> cycle of its collision
    ground_ok = {m: 0 for m in meets}               # cycles the plane met ground in the path

    def after(res):
        cycles[0] += 1
        v = res.inputs.vehicle
        roll, pitch = (v.roll_rad, v.pitch_rad) if v is not None else (0.0, 0.0)
        stop_len = res.verdict.stop_len_m if res.verdict is not None else z.min_stop_m
        veh = f.vehicle
        for oid in veh.obstacles_hit:
            hit_t.setdefault(oid, cycles[0])
        seq = res.inputs.laser.seq if res.inputs.laser is not None else cycles[0]
        for i, (m, g) in enumerate(geos.items()):
            # the simulator's laser model (ranges, noise, no return = nan), its own noise stream
            r = np.asarray(f.render_laser(0, seq, geometry=g, sensor=20 + i).ranges_m,
                           np.float64)
            pts, above, ok = scan_heights(
                r, ang, g.mount, roll, pitch, window_m, pct,
                region=(z.front_x_m - 2.0, z.front_x_m + CORRIDOR_M + 2.0,
                        z.half_width_m + 0.5 + window_m))
            ahead = pts[:, 0] - z.front_x_m
            corr = ok & (ahead >= 0) & (ahead <= CORRIDOR_M) & (
                np.abs(pts[:, 1]) <= z.half_width_m + 0.5)
            if not corr.any():
                continue
            c, _, rb = f._sensor_pose(g.mount)                 # where each beam hit
            dirs = (rb @ np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])).T
            wp = c + dirs * np.nan_to_num(r)[:, None]
            wx, wy = wp[:, 0].astype(np.float32), wp[:, 1].astype(np.float32)
            _, mat = world.height(wx, wy)
            mat = np.where(corr, mat, -1)
            obst = mat >= MAT_OBSTACLE
            if (corr & ~obst & (mat != MAT_STUBBLE)).any():
                ground_ok[m] += 1
            ids = {int(k): world.obstacles[int(k) - MAT_OBSTACLE] for k in np.unique(mat[obst])}
            for k, o in ids.items():
                e = seen[m].setdefault(o.id, {"cls": o.cls, "hit": 0.0})
                if o.id in hit_t:
                    continue                        # after the collision: not counted
                e["hit"] = max(e["hit"], float(ahead[mat == k].max()))
            for t in HEIGHTS:
                for w in WIDTHS:
                    fl = flag(r, above, corr, step, t, w)
                    bad = fl & ~obst
                    if bad.any():
                        false[m][(t, w)][0] += 1
                        if (ahead[bad] <= stop_len).any():
                            false[m][(t, w)][1] += 1
                    for k, o in ids.items():
                        sel = fl & (mat == k)
                        if sel.any() and o.id not in hit_t:
                            e = seen[m][o.id]
                            e[(t, w)] = max(e.get((t, w), 0.0), float(ahead[sel].max()))

    d.daemon.loop.on_cycle.append(after)
    res = d.run()["result"]
    return {"seed": seed, "cycles": cycles[0], "hours": cycles[0] / d.rate / 3600.0,
            "false": false, "seen": seen, "collided": sorted(hit_t), "ground_cycles": ground_ok,
            "false_stops": res["false_stops"], "collisions": res["collisions"]}


def summarise(drives: list[dict], meets: list[float]) -> dict:
    hours = sum(dr["hours"] for dr in drives)
    out = {"drives": len(drives), "hours": round(hours, 3),
           "shipped_box": {"false_stops": sum(dr["false_stops"] for dr in drives),
                           "collisions": sum(dr["collisions"] for dr in drives)},
           "meets": []}
    for m in meets:
        rows = []
        for t in HEIGHTS:
            for w in WIDTHS:
                fc = sum(dr["false"][m][(t, w)][0] for dr in drives)
                fz = sum(dr["false"][m][(t, w)][1] for dr in drives)
                classes: dict = {}
                collided = {"objects": 0, "flagged": 0}
                for dr in drives:
                    for oid, e in dr["seen"][m].items():
                        if e["hit"] <= 0 and (t, w) not in e:
                            continue
                        b = classes.setdefault(e["cls"], {"hit": 0, "flagged": 0, "far": []})
                        b["hit"] += 1
                        if (t, w) in e:
                            b["flagged"] += 1
                            b["far"].append(e[(t, w)])
                    for oid in dr["collided"]:
                        collided["objects"] += 1
                        e = dr["seen"][m].get(oid)
                        if e is not None and (t, w) in e:
                            collided["flagged"] += 1
                rows.append({
                    "T_m": t, "W_m": w,
                    "false_cycles_per_h": round(fc / hours, 1) if hours else None,
                    "false_stop_zone_cycles_per_h": round(fz / hours, 1) if hours else None,
                    "classes": {c: {"hit": b["hit"], "flagged": b["flagged"],
                                    "farthest_median_m": (round(float(np.median(b["far"])), 1)
                                                          if b["far"] else None)}
                                for c, b in sorted(classes.items())},
                    "collided_flagged_before": collided})
        out["meets"].append({"meet_m": m, "rows": rows,
                             "plane_on_ground_share": round(
                                 sum(dr["ground_cycles"][m] for dr in drives)
                                 / max(1, sum(dr["cycles"] for dr in drives)), 3)})
    return out


def print_table(s: dict) -> None:
    print(f"{s['drives']} drives, {s['hours']} h; the shipped box on these drives: "
          f"{s['shipped_box']['false_stops']} false stops, "
          f"{s['shipped_box']['collisions']} collisions")
    for mm in s["meets"]:
        print(f"\nsecond laser meeting flat ground {mm['meet_m']} m ahead of the mount "
              f"(plane on the ground in the path in {100 * mm['plane_on_ground_share']:.0f} % "
              f"of cycles)")
        print("T m  W m  false cycles/h (stop zone)  collided obstacles flagged before  "
              "per class: flagged/hit (farthest flagged, median m)")
        for r in mm["rows"]:
            cl = "; ".join(f"{c} {b['flagged']}/{b['hit']} ({b['farthest_median_m']})"
                           for c, b in r["classes"].items())
            col = r["collided_flagged_before"]
            print(f"{r['T_m']:<4} {r['W_m']:<4} {r['false_cycles_per_h']:>7} "
                  f"({r['false_stop_zone_cycles_per_h']})  {col['flagged']}/{col['objects']}  "
                  f"{cl}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seeds", help="training seeds, e.g. 1-10")
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--meet", default="5,7",
                    help="where the tilted plane meets flat ground, m ahead of the mount "
                         "(comma-separated: one second laser each, judged apart)")
    ap.add_argument("--mount-z", type=float, default=0.7, help="the second laser's height, m")
    ap.add_argument("--window", type=float, default=1.5,
                    help="the scan's own ground: returns within this many m across")
    ap.add_argument("--pct", type=float, default=10.0,
                    help="the scan's own ground: this percentile of their heights")
    ap.add_argument("--config", default=None, help="TOML merged over the drive's config")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    a = ap.parse_args(argv)
    try:
        meets = parse_list(a.meet)
    except ValueError:
        meets = []
    if not meets or any(m <= 0 for m in meets) or a.mount_z <= 0:
        print(f"tilted_laser_probe: --meet is a list of positive distances like 5,7 and "
              f"--mount-z positive (got {a.meet!r}, {a.mount_z})", file=sys.stderr)
        return 2
    setup = training_laser_setup("tilted_laser_probe", a.seeds, a.config)
    if setup is None:
        return 2
    seeds, extra = setup
    drives = drive_each("tilted_laser_probe", seeds,
                        lambda s: probe_drive(a.kind, s, a.minutes, extra, meets, a.mount_z,
                                              a.window, a.pct))
    summary = summarise(drives, meets)
    if a.json:
        print(json.dumps(summary, indent=1))
    else:
        print_table(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
