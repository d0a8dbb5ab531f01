"""The console's pictures: the camera view with detections and tracks drawn, and the grid with
the zones and tracks. Pure: a cycle's result and a copy of the grid's evidence in, BGR images
out (the console's encoder thread encodes them, never the loop)."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from appliance.snapshot import (HELD_BGR, _label, bend_of, camera_panel, draw_held, draw_zones,
                                project_cells)
from appliance.zones import stop_length

GRID_PX = 480           # height of the grid picture
TRACK_BGR = (255, 160, 40)


def track_dicts(tracks) -> list[dict]:
    """Tracks as plain dicts, whatever the tracker hands over (dataclasses, objects or dicts).
    Keys used: id, x_m, y_m, and if present length_m, width_m, height_m, label/class."""
    out = []
    for t in tracks or ():
        if isinstance(t, dict):
            d = dict(t)
        elif dataclasses.is_dataclass(t):
            d = dataclasses.asdict(t)
        else:
            d = {k: getattr(t, k) for k in dir(t) if not k.startswith("_")
                 and not callable(getattr(t, k, None))}
        try:
            d["x_m"], d["y_m"] = float(d["x_m"]), float(d["y_m"])
        except (KeyError, TypeError, ValueError):
            continue
        out.append(d)
    return out


def _track_label(t: dict) -> str:
    name = t.get("label") or t.get("class") or t.get("cls") or ""
    tid = t.get("id", t.get("track_id", ""))
    return f"#{tid} {name}".strip()


def _track_style(t: dict):
    """Confirmed tracks (the obstacles the box holds) bold and labelled; tentative ones thin."""
    confirmed = t.get("confirmed", True)
    return (TRACK_BGR, 2, True) if confirmed else ((150, 110, 60), 1, False)


def camera_view(res, tracks=()) -> np.ndarray | None:
    """The camera image (stereo left, else RGB-D colour) with the pipelines' masks, the
    occupied cells (yellow) and each track's footprint box (blue; confirmed ones labelled,
    tentative ones thin). None without a camera in the cycle's inputs."""
    img = camera_panel(res)
    inp = res.inputs
    if img is None or inp is None:
        return img
    src = inp.stereo if inp.stereo is not None else inp.rgbd
    cam, mount = src.calib.camera, src.calib.mount
    s = img.shape[0] / cam.height
    # the snapshot's camera panel already draws the cycle's confirmed tracks (labelled with
    # distance and cues); the others (tentative ones, or tracks handed in) are drawn here
    drawn = {t.id for t in getattr(res, "tracks", None) or () if getattr(t, "confirmed", False)}
    for t in track_dicts(tracks):
        if t.get("id") in drawn:
            continue
        hl = max(0.2, float(t.get("length_m") or 0.5)) / 2
        hw = max(0.2, float(t.get("width_m") or 0.5)) / 2
        x, y = t["x_m"], t["y_m"]
        corners = np.array([[x - hl, y - hw], [x + hl, y - hw], [x + hl, y + hw],
                            [x - hl, y + hw]])
        uv = project_cells(corners, cam, mount) * s
        if not np.isfinite(uv).all() or np.abs(uv).max() > 1e5:
            continue
        col, thick, label = _track_style(t)
        cv2.polylines(img, [uv.astype(np.int32)], True, col, thick, cv2.LINE_AA)
        u, v = uv[:, 0].min(), uv[:, 1].min()
        if label and 0 <= u < img.shape[1] and 0 <= v < img.shape[0]:
            _label(img, _track_label(t), (int(u), max(12, int(v) - 4)), 0.45, TRACK_BGR)
    return img


def grid_view(res, evidence: np.ndarray, cfg, tracks=(), height_px: int = GRID_PX,
              x_max_m: float = 25.0, half_width_m: float = 10.0) -> np.ndarray:
    """Top-down grid, x forward up the picture, y left to the left: evidence (grey to yellow,
    red = occupied), the stop zone (red) and slow zone (amber) at the vehicle's speed, the
    exclusion boxes (blue), tracks (labelled boxes) and the vehicle. Vectorised: no Python loop
    over cells, so the picture costs the same however busy the field is."""
    g, z = cfg.grid, cfg.zones
    x_max = min(g.x_max_m, x_max_m)
    half = half_width_m
    ppm = height_px / (x_max - g.x_min_m)
    # evidence as an image: rows = x (far at the top), columns = y (left at the left)
    nx, ny = evidence.shape
    i0 = 0
    i1 = min(nx, int(round((x_max - g.x_min_m) / g.cell_m)))
    j0 = max(0, int(round((-half - g.y_min_m) / g.cell_m)))
    j1 = min(ny, int(round((half - g.y_min_m) / g.cell_m)))
    ev = evidence[i0:i1, j0:j1][::-1, ::-1]
    occ = ev >= g.occupied_at - 1e-6
    lvl = np.clip(ev / max(g.occupied_at, 1e-6), 0, 1)
    small = np.full(ev.shape + (3,), 30, np.uint8)
    seen = lvl > 0.05
    small[seen, 1] = (90 + 120 * lvl[seen]).astype(np.uint8)
    small[seen, 2] = (90 + 120 * lvl[seen]).astype(np.uint8)
    small[seen, 0] = 30
    small[occ] = (0, 0, 255)
    w = int(round(2 * half * ppm))
    img = cv2.resize(small, (w, height_px), interpolation=cv2.INTER_NEAREST)

    def px(x, y):
        return int(round((half - y) * ppm)), int(round((x_max - x) * ppm))

    for r in range(5, int(x_max) + 1, 5):
        cv2.ellipse(img, px(0, 0), (int(r * ppm), int(r * ppm)), 0, 180, 360, (70, 70, 70), 1)
        _label(img, f"{r} m", (px(r, 0)[0] + 3, px(r, 0)[1] + 12), 0.4, (160, 160, 160))
    veh = res.inputs.vehicle if res is not None and res.inputs is not None else None
    speed = veh.speed_mps if veh is not None else 0.0
    stop = stop_length(speed, z)
    f = z.front_x_m
    draw_zones(img, px, z, stop, bend_of(res))
    for e in z.exclusion:
        cv2.rectangle(img, px(e.x_max_m, e.y_max_m), px(e.x_min_m, e.y_min_m), (200, 120, 0), 1)
    cv2.rectangle(img, px(f, 0.75), px(min(0.0, f - 2.6), -0.75), (220, 220, 220), -1)
    held = draw_held(img, px, res, g, x_max, half, ppm)    # [grid] hold_blind
    for t in track_dicts(tracks):
        hl = max(0.2, float(t.get("length_m") or 0.5)) / 2
        tw = max(0.2, float(t.get("width_m") or 0.5)) / 2
        a, b = px(t["x_m"] + hl, t["y_m"] + tw), px(t["x_m"] - hl, t["y_m"] - tw)
        col, thick, label = _track_style(t)
        cv2.rectangle(img, a, b, col, thick)
        if label:
            _label(img, _track_label(t), (a[0], max(12, a[1] - 3)), 0.4, col)
    _label(img, f"stop zone {stop:.1f} m at {speed:.1f} m/s, slow +{z.slow_extra_m:.0f} m",
           (8, 18), 0.45)
    if len(held):
        _label(img, f"magenta: {len(held)} cells held out of the cameras' sight", (8, 36),
               0.42, HELD_BGR)
    return img


def encode_jpeg(img: np.ndarray, quality: int = 80) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()
