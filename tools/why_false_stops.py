"""Why does the box stop for nothing? One closed-loop campaign drive, with a picture and the
figures of every false stop.

    python tools/why_false_stops.py KIND SEED --minutes 0.5 --stereo-scale 0.5 --out DIR \
        [--config extra.toml]

Runs the drive exactly as ``fieldguard campaign`` does (appliance/campaign_drive.Drive, the
same config), and at the first cycle of each false STOP episode writes
``DIR/KIND-SEED-tNN.N.png``: the left image with this frame's obstacle pixels (yellow), those
whose points lie in the stop zone (red), the novelty mask's cells (blue tint) and the horizon
row (the level ground's, cyan); beside it a top view of the grid's occupied cells and the zones.
``DIR/KIND-SEED.jsonl``: per false stop the points in the stop zone (range, height, image row
below the horizon), the novelty model's updates so far, and for the 5 cycles before it how many
stop-zone points each cycle had (does one blip pass the two-hit rule, or does it persist?).

An RGB-D drive (the greenhouse: the rgbd pipeline) is explained by its obstacle candidates
instead: per false stop the candidates whose footprint comes within ``--margin`` m of the stop
zone (distance of the near edge ahead of the front, side, size, height, points, the cues that
saw them, ground contact), the vehicle's speed and heading, and the same for the 5 cycles
before; the picture is the colour image beside a top view of those candidates (red: in the
stop zone) and the zones. ``--at T[,T...]`` (RGB-D) also writes that record at these
simulated times, stop or not (``"cause": "asked"``): a true stop to compare with.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import deque
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("--minutes", type=float, default=0.5)
    ap.add_argument("--stereo-scale", type=float, default=0.5)
    ap.add_argument("--config", default=None)
    ap.add_argument("--out", required=True)
    ap.add_argument("--dump", action="store_true",
                    help="also DIR/KIND-SEED-tNN.N.npz per false stop: the stop cycle's and the "
                         "two cycles before's left/right images, disparity, dense points, "
                         "their heights, keep mask, cue masks, pose and calibration")
    ap.add_argument("--at", default="", metavar="T[,T...]",
                    help="RGB-D drives: also a record at these simulated seconds")
    ap.add_argument("--margin", type=float, default=1.0,
                    help="RGB-D drives: candidates within this of the stop zone (m)")
    a = ap.parse_args(argv)
    try:
        at = sorted(float(t) for t in a.at.split(",") if t.strip())
    except ValueError:
        print(f"why_false_stops: error: --at wants seconds separated by commas, not {a.at!r}",
              file=sys.stderr)
        return 2
    from appliance.campaign import load_extra_config, make_spec
    from appliance.campaign_drive import Drive
    extra = load_extra_config(a.config) if a.config else None
    spec = make_spec(a.kind, a.seed, a.minutes, a.stereo_scale, extra)
    d = Drive(a.kind, a.seed, a.minutes, config_data=spec["config"],
              stereo_scale=a.stereo_scale)
    d.build()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = open(out / f"{a.kind}-{a.seed}.jsonl", "w")
    pipe = next((p for p in d.daemon.pipelines if hasattr(p, "novelty")), None)
    if pipe is None and any(p.name == "rgbd" for p in d.daemon.pipelines):
        return rgbd_main(a, d, out, log, at)
    if pipe is None:
        runs = ", ".join(p.name for p in d.daemon.pipelines)
        print(f"why_false_stops: error: the drive runs {runs}, not stereo-novelty or rgbd: this "
              "tool explains those pipelines' false stops (for the laser's: "
              "tools/laser_false_stops.py)", file=sys.stderr)
        return 2
    if at:
        print("why_false_stops: error: --at is for RGB-D drives (a stereo drive's records are "
              "written at its false stops)", file=sys.stderr)
        return 2
    z = d.zones
    hist: deque = deque(maxlen=6)
    frames: deque = deque(maxlen=3)
    n_events = [0]

    def in_zone(xy, stop_len):
        a_ = xy[:, 0] - z.front_x_m
        return (a_ >= 0) & (a_ <= stop_len) & (np.abs(xy[:, 1]) <= z.half_width_m)

    def after(res):
        stop_len = res.verdict.stop_len_m if res.verdict is not None else z.min_stop_m
        pts, px, h, keep, k = pipe.last_points
        kp, kpx, kh = pts[keep], px[keep], h[keep]
        zmask = in_zone(kp[:, :2], stop_len) if len(kp) else np.zeros(0, bool)
        cells = np.asarray(res.cells_xy, float).reshape(-1, 2)
        if a.dump:
            fr_ = res.inputs.stereo
            x_, y_, yaw_ = d.vehicle.pose()
            frames.append({"left": fr_.left, "right": fr_.right,
                           "disp": np.asarray(getattr(pipe, "last_disp", np.zeros(0))),
                           "pts": pts, "px": px, "h": h, "keep": keep, "k": k,
                           "cells": cells, "pose": np.array([x_, y_, yaw_, d.vehicle.speed]),
                           "t_s": res.index / d.rate, "stop_len": stop_len,
                           "att": np.array([float(getattr(res.inputs.vehicle, "roll_rad", 0.0)
                                                  or 0.0),
                                            float(getattr(res.inputs.vehicle, "pitch_rad", 0.0)
                                                  or 0.0)]),
                           **{f"mask_{n}": m for n, m in
                              getattr(pipe, "_source_masks", {}).items()}})
        hist.append({"t_s": round(res.index / d.rate, 1), "zone_points": int(zmask.sum()),
                     "zone_cells": int(in_zone(cells, stop_len).sum()) if len(cells) else 0,
                     "state": res.output.state.value})
        fresh = [e for e in d.events[n_events[0]:] if e.get("event") == "stop"]
        n_events[0] = len(d.events)
        for ev in fresh:
            if ev["kind"] != "false":
                continue
            fr = res.inputs.stereo
            img = cv2.cvtColor(fr.left, cv2.COLOR_GRAY2BGR) if fr.left.ndim == 2 else \
                fr.left.copy()
            H, W = img.shape[:2]
            nres = pipe.last[0]
            m = nres.mask.astype(np.uint8)
            mm = cv2.resize(m, (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)
            img[mm] = (0.6 * img[mm] + 0.4 * np.array([255, 80, 0])).astype(np.uint8)
            for (u, v), inz in zip(np.asarray(kpx, float) * k, zmask):
                cv2.circle(img, (int(u), int(v)), 1, (0, 0, 255) if inz else (0, 255, 255), -1)
            cam = fr.calib.camera
            mount = fr.calib.mount
            # the level ground's horizon row: a level point 1 km ahead, projected
            R = mount.camera_to_vehicle()
            oc = R.T @ np.array([1000.0, 0.0, mount.z_m * 0.0])
            vh = cam.cy + cam.fy * oc[1] / oc[2] if oc[2] > 0 else None
            if vh is not None and 0 <= vh < H:
                cv2.line(img, (0, int(vh)), (W - 1, int(vh)), (255, 255, 0), 1)
            # top view: 0..20 m ahead, +-6 m, 20 px/m
            s = 20
            top = np.zeros((20 * s, 12 * s, 3), np.uint8)

            def tp(x, y):
                return int(6 * s - y * s), int(20 * s - (x - z.front_x_m + 1) * s)
            cv2.rectangle(top, tp(z.front_x_m + stop_len, z.half_width_m),
                          tp(z.front_x_m, -z.half_width_m), (0, 0, 160), 1)
            for (x, y) in kp[:, :2]:
                cv2.circle(top, tp(x, y), 1, (0, 200, 200), -1)
            for (x, y) in cells:
                cv2.circle(top, tp(x, y), 2, (0, 0, 255), -1)
            th = top.shape[0]
            top = cv2.resize(top, (int(top.shape[1] * H / th), H))
            pic = np.concatenate([img, top], axis=1)
            cv2.putText(pic, f"{a.kind} {a.seed} t={ev['t_s']} {ev['place']} {ev['cause'][:40]}",
                        (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
            cv2.imwrite(str(out / f"{a.kind}-{a.seed}-t{ev['t_s']:05.1f}.png"), pic)
            zp = kp[zmask]
            rows = kpx[zmask, 1] * k if len(zp) else np.zeros(0)
            rec = {**{k_: ev[k_] for k_ in ("t_s", "place", "cause", "reason", "stop_zone_m")},
                   "zone_points": int(zmask.sum()),
                   "zone_x_m": [round(float(v), 2) for v in np.percentile(zp[:, 0], [0, 50, 100])]
                   if len(zp) else None,
                   "zone_h_m": [round(float(v), 2) for v in np.percentile(kh[zmask], [0, 50, 100])]
                   if len(zp) else None,
                   "zone_rows_px": [int(v) for v in np.percentile(rows, [0, 50, 100])]
                   if len(zp) else None,
                   "horizon_row_px": None if vh is None else round(float(vh), 1),
                   "image_hw": [H, W],
                   "model_updates": int(pipe.novelty.model.updates),
                   "model_samples": int(pipe.novelty.model.size),
                   "novel_fraction": float(nres.mask.mean()),
                   "vehicle": {"speed": round(d.vehicle.speed, 2),
                               "pitch_deg": round(float(getattr(res.inputs.vehicle, "pitch_rad",
                                                                0.0) or 0.0) * 57.3, 2)
                               if res.inputs.vehicle is not None else None},
                   "before": list(hist)}
            log.write(json.dumps(rec) + "\n")
            if a.dump:
                cal = fr.calib
                arrs = {"fx": cal.camera.fx, "fy": cal.camera.fy, "cx": cal.camera.cx,
                        "cy": cal.camera.cy, "baseline_m": cal.baseline_m,
                        "mount_xyz": np.asarray(cal.mount.position),
                        "mount_R": cal.mount.camera_to_vehicle(),
                        "front_x_m": z.front_x_m, "half_width_m": z.half_width_m}
                for i, f_ in enumerate(reversed(frames)):
                    for key, v in f_.items():
                        arrs[f"c{i}_{key}"] = v
                np.savez_compressed(out / f"{a.kind}-{a.seed}-t{ev['t_s']:05.1f}.npz", **arrs)
            log.flush()

    return drive_and_write(a, d, out, after)


def drive_and_write(a, d, out: Path, after) -> int:
    """Run the drive with ``after`` on every cycle; print its stops and collisions, and write
    its whole result and events as the campaign does (result.json, events.json)."""
    d.daemon.loop.on_cycle.append(after)
    res = d.run()["result"]
    print(json.dumps({k_: res.get(k_) for k_ in ("false_stops", "true_stops", "missed_stops",
                                                 "collisions")}))
    (out / f"{a.kind}-{a.seed}-result.json").write_text(json.dumps(res, indent=1, default=str))
    (out / f"{a.kind}-{a.seed}-events.json").write_text(json.dumps(d.events, indent=1,
                                                                   default=str))
    return 0


def near_zone(cands, front_x_m: float, half_width_m: float, stop_len_m: float,
              margin_m: float) -> list[dict]:
    """The candidates whose footprint comes within ``margin_m`` of the stop zone (the front to
    ``stop_len_m`` ahead, ``half_width_m`` either side), nearest first, each as a dict:
    ``ahead_m`` (its near edge ahead of the front), ``y_m``, size, height, points, confidence,
    cues, ground contact and ``in_stop_zone`` (its footprint meets the zone: the box's own
    zone test, appliance.zones.footprint_meets)."""
    from appliance.zones import footprint_meets
    stop = {"x_min_m": front_x_m, "x_max_m": front_x_m + stop_len_m,
            "half_width_m": half_width_m}
    near = {"x_min_m": front_x_m - margin_m, "x_max_m": front_x_m + stop_len_m + margin_m,
            "half_width_m": half_width_m + margin_m}
    out = []
    for c in cands:
        if not footprint_meets(c.x_m, c.y_m, c.length_m, c.width_m, near):
            continue
        out.append({"ahead_m": round(c.x_m - c.length_m / 2 - front_x_m, 2),
                    "y_m": round(c.y_m, 2),
                    "length_m": round(c.length_m, 2), "width_m": round(c.width_m, 2),
                    "height_m": round(c.height_m, 2), "points": int(c.points),
                    "confidence": round(float(c.confidence), 2), "sources": list(c.sources),
                    "ground_contact": bool(c.ground_contact),
                    "in_stop_zone": footprint_meets(c.x_m, c.y_m, c.length_m, c.width_m, stop)})
    return sorted(out, key=lambda r: r["ahead_m"])


def rgbd_main(a, d, out: Path, log, at: list[float]) -> int:
    """The RGB-D drive's false stops (and the ``--at`` times): see the module's text."""
    import math
    z = d.zones
    hist: deque = deque(maxlen=6)
    n_events = [0]
    pending = list(at)

    def after(res):
        t = round(res.index / d.rate, 1)
        stop_len = res.verdict.stop_len_m if res.verdict is not None else z.min_stop_m
        det = res.detections.get("rgbd")
        cands = near_zone(det.candidates if det is not None else (), z.front_x_m,
                          z.half_width_m, stop_len, a.margin)
        yaw = d.vehicle.pose()[2]
        veh = res.inputs.vehicle
        hist.append({"t_s": t, "state": res.output.state.value,
                     "in_zone": [c["sources"] for c in cands if c["in_stop_zone"]]})
        fresh = [e for e in d.events[n_events[0]:] if e.get("event") == "stop"]
        n_events[0] = len(d.events)
        asked = []
        while pending and pending[0] <= t + 1e-6:
            asked.append({"t_s": t, "place": "-", "cause": "asked", "reason":
                          res.output.reason, "stop_zone_m": round(stop_len, 2)})
            pending.pop(0)
        for ev in [e for e in fresh if e["kind"] == "false"] + asked:
            rec = {**{k_: ev[k_] for k_ in ("t_s", "place", "cause", "reason", "stop_zone_m")},
                   "state": res.output.state.value,
                   "vehicle": {"speed_mps": round(d.vehicle.speed, 2),
                               "heading_deg": round(math.degrees(yaw), 1),
                               "yaw_rate_dps": None if veh is None else
                               round(math.degrees(veh.yaw_rate_radps), 1)},
                   "candidates": cands, "before": list(hist)[:-1]}
            log.write(json.dumps(rec) + "\n")
            log.flush()
            fr = res.inputs.rgbd
            if fr is not None:
                cv2.imwrite(str(out / f"{a.kind}-{a.seed}-t{ev['t_s']:05.1f}.png"),
                            rgbd_picture(fr.color, cands, z, stop_len,
                                         f"{a.kind} {a.seed} t={ev['t_s']} {ev['place']} "
                                         f"{ev['cause'][:40]}"))

    return drive_and_write(a, d, out, after)


def rgbd_picture(color: np.ndarray, cands: list[dict], z, stop_len: float,
                 title: str) -> np.ndarray:
    """The colour image beside a top view (0.5 m behind the front to 4 m ahead, +-2 m; 80 px
    a metre) of the zones (stop: red outline) and the candidates' footprints (red: in the stop
    zone, yellow: near it), each labelled with its cues' initials."""
    img = color if color.ndim == 3 else cv2.cvtColor(color, cv2.COLOR_GRAY2BGR)
    img = np.ascontiguousarray(img).copy()
    H = img.shape[0]
    s = 80
    top = np.zeros((int(4.5 * s), 4 * s, 3), np.uint8)

    def tp(ahead, y):
        return int(2 * s - y * s), int(4 * s - ahead * s)
    cv2.rectangle(top, tp(stop_len, z.half_width_m), tp(0.0, -z.half_width_m), (0, 0, 200), 1)
    cv2.line(top, tp(0.0, -2.0), tp(0.0, 2.0), (120, 120, 120), 1)       # the front
    for c in cands:
        col = (0, 0, 255) if c["in_stop_zone"] else (0, 220, 220)
        p0 = tp(c["ahead_m"], c["y_m"] + c["width_m"] / 2)
        p1 = tp(c["ahead_m"] + c["length_m"], c["y_m"] - c["width_m"] / 2)
        cv2.rectangle(top, p0, p1, col, -1)
        cv2.putText(top, "".join(x[0] for x in c["sources"]), (p1[0] + 3, p1[1]),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, col, 1)
    top = cv2.resize(top, (int(top.shape[1] * H / top.shape[0]), H))
    pic = np.concatenate([img, top], axis=1)
    cv2.rectangle(pic, (0, 0), (pic.shape[1] - 1, 21), (0, 0, 0), -1)   # legible on a sky
    cv2.putText(pic, title, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
    return pic


if __name__ == "__main__":
    raise SystemExit(main())
