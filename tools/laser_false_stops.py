"""What did the laser hit when the box stopped for nothing? One closed-loop campaign drive with
the laser pipeline, and per false stop the returns in and just beyond the stop zone, each with
the simulator's truth at the hit.

    python tools/laser_false_stops.py KIND SEED --minutes 2 [--config extra.toml]

Runs the drive exactly as ``fieldguard campaign`` does (appliance/campaign_drive.Drive, with
``[perception] pipelines = ["laser"]`` unless the config says otherwise). For each return at
most 3 m beyond the stop zone and within the zone's half width, at the first cycle of each
false STOP: where the pipeline put it (vehicle frame, scan plane level as the paper mounts
it), how high above the real ground at that place the beam hit, what it hit (ground, stubble,
an obstacle) and the height of what stands at that point (a tuft's stalks are ragged per 2 cm:
the beam may have hit a taller neighbour); and the vehicle's pitch and roll. Prints one
JSON line per false stop and a summary (returns by material, their heights above the ground).
With a camera pipeline beside the laser (``--config``), each return also says whether that
camera confirmed it as ``[grid] laser_confirm_by`` would (the config's list, or novelty,
learned and points), and ``--picture DIR`` writes, per false stop, the camera's image with
its novelty mask and the returns drawn on it (green: confirmed, red: not).
Training seeds only (< 1000): this is a tool for finding causes.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402


def draw_picture(path: Path, image: np.ndarray, view, xyz: np.ndarray, inside, conf,
                 hits: list[str], title: str) -> None:
    """The camera's image with its novelty mask tinted blue and the laser returns ``xyz``
    (vehicle frame) drawn where they project: green where the camera confirmed them, red
    where it had them in view and did not, each labelled with what the beam really hit."""
    import cv2
    img = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    h, w = img.shape[:2]
    m = view.masks.get("novelty")
    if m is not None:
        big = cv2.resize(m, (w, h), interpolation=cv2.INTER_NEAREST) > 0
        img[big] = (0.6 * img[big] + 0.4 * np.array([255, 80, 0])).astype(np.uint8)
    u, v, _ = view.project(xyz)
    sx, sy = w / float(view.shape[1]), h / float(view.shape[0])
    for i in np.flatnonzero(inside):
        col = (0, 200, 0) if conf[i] else (0, 0, 255)
        p = (int(u[i] * sx), int(v[i] * sy))
        cv2.circle(img, p, 4, col, -1)
    labelled = set()
    for i in np.flatnonzero(inside):
        if hits[i] in labelled:
            continue
        labelled.add(hits[i])
        cv2.putText(img, hits[i], (int(u[i] * sx) + 6, int(v[i] * sy) - 6),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(img, title, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    cv2.putText(img, "blue: novel; laser returns green: camera confirms, red: it does not",
                (8, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--config", default=None, help="TOML merged over the drive's config")
    ap.add_argument("--picture", default=None, metavar="DIR",
                    help="with a camera pipeline: one PNG per false stop into DIR")
    ap.add_argument("--stereo-scale", type=float, default=0.5,
                    help="the stereo pair's size against 1280x1024, as the campaign's "
                         "(0.1-1.0; default 0.5)")
    a = ap.parse_args(argv)
    if not 0.1 <= a.stereo_scale <= 1.0:
        print(f"laser_false_stops: --stereo-scale must be in [0.1, 1.0], got {a.stereo_scale}",
              file=sys.stderr)
        return 2
    if a.seed >= 1000:
        print("laser_false_stops: seeds >= 1000 are the acceptance set; look for causes on "
              "training seeds", file=sys.stderr)
        return 2
    from appliance.campaign import load_extra_config, make_spec
    from hal.errors import FieldguardError
    from appliance.campaign_drive import Drive, deep_merge
    from drivers.sim.world import MAT_BUSH, MAT_GROUND, MAT_LEAF, MAT_OBSTACLE, MAT_STUBBLE
    materials = {MAT_GROUND: "ground", MAT_STUBBLE: "stubble", MAT_BUSH: "bush",
                 MAT_LEAF: "leaf"}
    try:
        extra = deep_merge({"perception": {"pipelines": ["laser"]}},
                           load_extra_config(a.config) if a.config else {})
    except FieldguardError as exc:
        print(f"laser_false_stops: {exc}", file=sys.stderr)
        return 2
    spec = make_spec(a.kind, a.seed, a.minutes, a.stereo_scale, extra)
    d = Drive(a.kind, a.seed, a.minutes, config_data=spec["config"], stereo_scale=a.stereo_scale)
    d.build()
    from appliance.decision import camera_confirms, camera_views
    from appliance.perception.laser import plane_points
    confirm_by = d.cfg.grid.laser_confirm_by or ("novelty", "learned", "points")
    if a.picture:
        Path(a.picture).mkdir(parents=True, exist_ok=True)
    z, f = d.zones, d.field
    world = f.scene.world
    n_ev = [0]
    hits: list[dict] = []

    def after(res):
        fresh = [e for e in d.events[n_ev[0]:] if e.get("event") == "stop"]
        n_ev[0] = len(d.events)
        scan = res.inputs.laser
        if scan is None or not any(e["kind"] == "false" for e in fresh):
            return
        g = scan.geometry
        r = np.asarray(scan.ranges_m, float)
        ang = g.angles_rad()
        ok = np.isfinite(r)
        loc = np.stack([r * np.cos(ang), r * np.sin(ang), 0 * r], 1)[ok]
        c, _, rb = f._sensor_pose(g.mount)
        wp = c + loc @ rb.T                               # where the beam really hit
        vx, vy = g.mount.x_m + loc[:, 0], g.mount.y_m + loc[:, 1]
        stop_len = res.verdict.stop_len_m if res.verdict is not None else z.min_stop_m
        near = (vx - z.front_x_m >= 0) & (vx - z.front_x_m <= stop_len + 3.0) & (
            np.abs(vy) <= z.half_width_m)
        wx, wy = wp[near, 0].astype(np.float32), wp[near, 1].astype(np.float32)
        ground = world.ground(wx, wy)
        top, mat = world.height(wx, wy)
        roll, pitch, _ = f.vehicle.attitude()
        # the camera's say on each of them, as [grid] laser_confirm_by would judge it
        cams = camera_views(res.detections)
        xyz = np.column_stack(plane_points(loc, g.mount))[near]   # where the pipeline puts them
        inside = conf = None
        if cams:
            inside, conf = camera_confirms(cams, xyz, confirm_by, d.cfg.grid.laser_confirm_radius_m)
        for ev in fresh:
            if ev["kind"] != "false":
                continue
            rows = []
            for i, (x, y, hz, gz, tz, m) in enumerate(zip(vx[near], vy[near], wp[near, 2],
                                                          ground, top, mat)):
                what = ("obstacle" if m >= MAT_OBSTACLE
                        else materials.get(int(m), str(int(m))))
                row = {"x_m": round(float(x), 2), "y_m": round(float(y), 2),
                       "in_stop_zone": bool(x - z.front_x_m <= stop_len),
                       "hit_above_ground_m": round(float(hz - gz), 2),
                       "hit": what, "top_above_ground_m": round(float(tz - gz), 2)}
                if inside is not None:
                    row["camera"] = ("confirmed" if conf[i] else "unconfirmed") if inside[i] \
                        else "out of view"
                rows.append(row)
            if a.picture and cams and res.inputs.stereo is not None:
                path = Path(a.picture) / f"{a.kind}-{a.seed}-{ev['t_s']:.1f}s.png"
                draw_picture(path, res.inputs.stereo.left, cams[0].view, xyz, inside, conf,
                             [r["hit"] for r in rows],
                             f"{a.kind} {a.seed}, false stop at {ev['t_s']:.1f} s")
            rec = {"t_s": ev["t_s"], "duration_s": ev.get("duration_s"),
                   "pitch_deg": round(float(np.degrees(pitch)), 2),
                   "roll_deg": round(float(np.degrees(roll)), 2),
                   "sensor_above_ground_m": round(float(
                       c[2] - world.ground(np.float32(c[0]), np.float32(c[1]))), 3),
                   "returns": rows}
            hits.append(rec)
            print(json.dumps(rec), flush=True)

    d.daemon.loop.on_cycle.append(after)
    res = d.run()["result"]
    allr = [h for rec in hits for h in rec["returns"] if h["in_stop_zone"]]
    by = {}
    for h in allr:
        by.setdefault(h["hit"], []).append(h["hit_above_ground_m"])
    summary = {"kind": a.kind, "seed": a.seed, "false_stops": res["false_stops"],
               "stop_zone_returns": len(allr),
               "by_hit": {k: {"returns": len(v),
                              "above_ground_m_p10_p50_p90": [round(float(q), 2) for q in
                                                             np.percentile(v, [10, 50, 90])]}
                          for k, v in sorted(by.items())}}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
