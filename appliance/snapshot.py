"""What the box sees now, in one picture: the camera image with the pipelines' masks and the
obstacle cells drawn on it, the depth (or slope) view, and the occupancy grid with the zones.
Confirmed tracks are drawn on both: footprint, id, distance and cues. Pure: arrays in, a BGR
image out (the daemon encodes it)."""
from __future__ import annotations

import math

import cv2
import numpy as np

from appliance.config import Config
from appliance.perception.view import pixels_of
from appliance.zones import bend_of, stop_length, zone_outline
from hal.types import GateState

STATE_BGR = {GateState.STOP: (40, 40, 220), GateState.SLOW: (0, 190, 230),
             GateState.CLEAR: (60, 180, 60)}
PANEL_H = 420


def draw_zones(img, px, z, stop_len_m: float, bend=0.0) -> None:
    """The slow and stop zones on a top view (``px(x, y)`` -> pixel), bent along the turn or
    laid along the planned path as the box laid them (``bend``: :func:`bend_of`)."""
    f, hw = z.front_x_m, z.half_width_m
    for x0, x1, state, thick in ((f + stop_len_m, f + stop_len_m + z.slow_extra_m,
                                  GateState.SLOW, 1), (f, f + stop_len_m, GateState.STOP, 2)):
        pts = np.array([px(x, y) for x, y in zone_outline(x0, x1, hw, bend, f)],
                       np.int32)
        cv2.polylines(img, [pts], True, STATE_BGR[state], thick)


def draw_held(img, px, res, g, x_max: float, half: float, ppm: float) -> np.ndarray:
    """The cells held out of the cameras' sight this cycle (``res.held_xy``, [grid]
    hold_blind) as magenta squares on a top view; returns them."""
    held = np.asarray(getattr(res, "held_xy", np.zeros((0, 2))), np.float64).reshape(-1, 2)
    r = max(2, int(round(ppm * g.cell_m * 0.75)))
    for x, y in held:
        if g.x_min_m <= x <= x_max and -half <= y <= half:
            u, v = px(x, y)
            cv2.rectangle(img, (u - r, v - r), (u + r, v + r), HELD_BGR, 2)
    return held


def _fit(img: np.ndarray, h: int) -> np.ndarray:
    s = h / img.shape[0]
    return cv2.resize(img, (max(1, int(round(img.shape[1] * s))), h),
                      interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST)


def _label(img, text, org, scale=0.55, color=(255, 255, 255), thick=1):
    """Text on a dark box (an outline drawn with a thicker stroke misaligns with OpenCV 5's
    fonts)."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    x, y = org
    x0, y0 = max(0, x - 2), max(0, y - h - 3)
    x1, y1 = min(img.shape[1], x + w + 2), min(img.shape[0], y + base + 1)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, thick, cv2.LINE_AA)


def _masks(debug: dict):
    """Boolean image masks the pipelines left in their debug output (any key ending in mask)."""
    for name, d in debug.items():
        if isinstance(d, dict):
            for k, v in d.items():
                if k.endswith("mask") and isinstance(v, np.ndarray) and v.ndim == 2:
                    yield f"{name}.{k}", v


def project_cells(cells_xy: np.ndarray, calib_camera, mount) -> np.ndarray:
    """Vehicle-frame ground cells -> pixel coordinates (N, 2), NaN where behind the camera."""
    if not len(cells_xy):
        return np.zeros((0, 2))
    return project_points(np.c_[cells_xy, np.zeros(len(cells_xy))], calib_camera, mount)


def project_points(pts: np.ndarray, calib_camera, mount) -> np.ndarray:
    """Vehicle-frame 3-D points (N, 3) -> pixel coordinates (N, 2), NaN behind the camera."""
    if not len(pts):
        return np.zeros((0, 2))
    u, v, front = pixels_of(pts, calib_camera.fx, calib_camera.fy, calib_camera.cx,
                            calib_camera.cy, mount.camera_to_vehicle(), mount.position, 0.1)
    uv = np.c_[u, v]
    uv[~front] = np.nan
    return uv


def camera_panel(res) -> np.ndarray | None:
    inp = res.inputs
    if inp is None:
        return None
    if inp.stereo is not None:
        img, cam, mount, what = (inp.stereo.left.copy(), inp.stereo.calib.camera,
                                 inp.stereo.calib.mount, "stereo left")
    elif inp.rgbd is not None:
        img, cam, mount, what = (inp.rgbd.color.copy(), inp.rgbd.calib.camera,
                                 inp.rgbd.calib.mount, "rgbd colour")
    else:
        return None
    debug = {k: d.debug for k, d in res.detections.items()}
    for name, m in _masks(debug):
        mm = m.astype(bool)
        if mm.shape != img.shape[:2]:
            mm = cv2.resize(mm.astype(np.uint8), (img.shape[1], img.shape[0]),
                            interpolation=cv2.INTER_NEAREST).astype(bool)
        tint = np.zeros_like(img)
        tint[:] = (0, 0, 255)
        img[mm] = (0.55 * img[mm] + 0.45 * tint[mm]).astype(np.uint8)
        cnts, _ = cv2.findContours(mm.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(img, cnts, -1, (0, 0, 255), 2)
    uv = project_cells(res.cells_xy, cam, mount)
    for u, v in uv:
        if np.isfinite(u) and 0 <= u < img.shape[1] and 0 <= v < img.shape[0]:
            cv2.circle(img, (int(u), int(v)), max(2, img.shape[1] // 320), (0, 255, 255), -1)
    tracks = [t for t in getattr(res, "tracks", ()) if t.confirmed]
    for t in tracks:
        draw_track_in_camera(img, t, cam, mount)
    out = _fit(img, PANEL_H)
    what_tracks = ", blue = tracks" if tracks else ""
    _label(out, f"{what}: red = pipeline masks, yellow = occupied cells{what_tracks}", (8, 20),
           0.5)
    return out


TRACK_BGR = (255, 160, 40)
HELD_BGR = (255, 60, 255)


def track_label(t) -> str:
    """id, distance and cues of a track, e.g. "#7 4.1 m laser+geometry"."""
    return f"#{t.id} {math.hypot(t.x_m, t.y_m):.1f} m {'+'.join(t.sources) or '?'}"


def draw_track_in_camera(img: np.ndarray, t, cam, mount) -> None:
    """The track's footprint box (ground to its height, 0.5 m when unknown) projected."""
    h = t.height_m if t.height_m > 0 else 0.5
    x0, x1 = t.x_m - t.length_m / 2, t.x_m + t.length_m / 2
    y0, y1 = t.y_m - t.width_m / 2, t.y_m + t.width_m / 2
    corners = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (0.0, h)])
    uv = project_points(corners, cam, mount)
    ok = np.all(np.isfinite(uv), axis=1)
    if ok.sum() < 2:
        return
    u0, v0 = uv[ok].min(axis=0)
    u1, v1 = uv[ok].max(axis=0)
    H, W = img.shape[:2]
    if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
        return
    p0 = (int(max(u0, 0)), int(max(v0, 0)))
    p1 = (int(min(u1, W - 1)), int(min(v1, H - 1)))
    cv2.rectangle(img, p0, p1, TRACK_BGR, max(2, W // 400))
    _label(img, track_label(t), (p0[0], max(p0[1] - 6, 14)), 0.5, TRACK_BGR)


def depth_panel(res) -> np.ndarray | None:
    inp = res.inputs
    if inp is None or inp.rgbd is None:
        return None
    debug = {k: d.debug for k, d in res.detections.items()}
    slope = None
    for d in debug.values():
        if isinstance(d, dict) and isinstance(d.get("slope_deg"), np.ndarray):
            slope = d["slope_deg"]
    if slope is not None:
        v = np.clip(np.nan_to_num(np.abs(slope)) / 90.0 * 255, 0, 255).astype(np.uint8)
        img, title = cv2.applyColorMap(v, cv2.COLORMAP_JET), "slope 0-90 deg"
    else:
        dm = inp.rgbd.depth_m
        v = np.clip(dm / max(inp.rgbd.calib.max_range_m, 0.1) * 255, 0, 255).astype(np.uint8)
        img = cv2.applyColorMap(v, cv2.COLORMAP_TURBO)
        img[dm <= 0] = 0
        title = f"depth 0-{inp.rgbd.calib.max_range_m:.0f} m (black = no reading)"
    out = _fit(img, PANEL_H)
    _label(out, title, (8, 20), 0.5)
    return out


def grid_panel(res, evidence: np.ndarray, cfg: Config) -> np.ndarray:
    """Top-down, x (forward) up the picture, y (left) to the left; 0.1 m cells."""
    g, z = cfg.grid, cfg.zones
    x_max = min(g.x_max_m, 25.0)
    half = 10.0
    ppm = PANEL_H / (x_max - g.x_min_m)
    w = int(2 * half * ppm)
    img = np.full((PANEL_H, w, 3), 30, np.uint8)

    def px(x, y):
        return int(round((half - y) * ppm)), int(round((x_max - x) * ppm))

    # evidence
    ev = np.clip(evidence / max(cfg.grid.occupied_at, 1e-6), 0, 1)
    nx, ny = ev.shape
    xs = g.x_min_m + (np.arange(nx) + 0.5) * g.cell_m
    ys = g.y_min_m + (np.arange(ny) + 0.5) * g.cell_m
    ix, iy = np.nonzero(ev > 0.05)
    for i, j in zip(ix, iy):
        x, y = xs[i], ys[j]
        if g.x_min_m <= x <= x_max and -half <= y <= half:
            c = px(x, y)
            occ = evidence[i, j] >= cfg.grid.occupied_at - 1e-6
            col = (0, 0, 255) if occ else (0, int(90 + 120 * ev[i, j]), int(90 + 120 * ev[i, j]))
            cv2.circle(img, c, max(1, int(ppm * g.cell_m / 2)), col, -1)
    # range rings
    for r in range(5, int(x_max) + 1, 5):
        cv2.ellipse(img, px(0, 0), (int(r * ppm), int(r * ppm)), 0, 180, 360, (70, 70, 70), 1)
        _label(img, f"{r} m", (px(r, 0)[0] + 3, px(r, 0)[1] + 12), 0.4, (150, 150, 150))
    # zones
    speed = res.inputs.vehicle.speed_mps if res.inputs and res.inputs.vehicle else 0.0
    stop = stop_length(speed, z)
    f = z.front_x_m
    draw_zones(img, px, z, stop, bend_of(res))
    for e in z.exclusion:
        cv2.rectangle(img, px(e.x_max_m, e.y_max_m), px(e.x_min_m, e.y_min_m), (200, 120, 0), 1)
    # tracks: footprint, id, distance, cues
    for t in getattr(res, "tracks", ()):
        if not t.confirmed:
            continue
        a = px(t.x_m + t.length_m / 2, t.y_m + t.width_m / 2)
        b = px(t.x_m - t.length_m / 2, t.y_m - t.width_m / 2)
        cv2.rectangle(img, a, b, TRACK_BGR, 1 if t.coasting else 2)
        if abs(t.vx_mps) + abs(t.vy_mps) > 0.3:
            end = px(t.x_m + t.vx_mps, t.y_m + t.vy_mps)
            cv2.arrowedLine(img, px(t.x_m, t.y_m), end, TRACK_BGR, 1, tipLength=0.3)
        _label(img, track_label(t), (b[0] + 4, a[1] + 4), 0.38, TRACK_BGR)
    held = draw_held(img, px, res, g, x_max, half, ppm)
    # vehicle
    cv2.rectangle(img, px(f, 0.75), px(min(0.0, f - 2.6), -0.75), (220, 220, 220), -1)
    _label(img, f"grid: stop zone {stop:.1f} m at {speed:.1f} m/s, slow +{z.slow_extra_m:.0f} m",
           (8, 20), 0.5)
    if len(held):
        _label(img, f"magenta: {len(held)} cells held out of the cameras' sight", (8, 40),
               0.45, HELD_BGR)
    return img


def info_panel(status: dict | None, res) -> np.ndarray:
    """Devices, loop timing and the last stops, as text."""
    img = np.full((PANEL_H, 420, 3), 45, np.uint8)
    y = 24
    _label(img, "devices", (10, y), 0.55, (200, 200, 200))
    for name, h in (status or {}).get("devices", {}).items():
        y += 22
        ok = h.get("state") == "ok"
        age = "-" if h.get("age_s") is None else f"{h['age_s']:.2f} s"
        _label(img, f"{name:8s} {h.get('state', '?'):8s} age {age}", (16, y), 0.5,
               (120, 230, 120) if ok else (80, 80, 255))
    t = (status or {}).get("timing_ms", {}).get("cycle", {})
    y += 34
    _label(img, f"loop p50 {t.get('p50')} ms  p99 {t.get('p99')} ms", (10, y), 0.5)
    y += 22
    _label(img, f"overruns {(status or {}).get('overruns')}", (10, y), 0.5)
    y += 34
    _label(img, "last stops", (10, y), 0.55, (200, 200, 200))
    for st in (status or {}).get("last_stops", [])[-6:]:
        y += 22
        _label(img, f"{st['stamp_s']:7.1f} s  {st['reason'][:40]}", (16, y), 0.45)
    return img


def compose(res, evidence: np.ndarray, cfg: Config, status: dict | None = None) -> np.ndarray:
    panels = [p for p in (camera_panel(res), depth_panel(res)) if p is not None]
    panels.append(grid_panel(res, evidence, cfg))
    panels.append(info_panel(status, res))
    body = np.concatenate(panels, axis=1)
    head = np.zeros((56, body.shape[1], 3), np.uint8)
    st = res.output.state
    head[:] = STATE_BGR[st]
    _label(head, f"{st.value}", (10, 38), 1.1, (255, 255, 255), 2)
    _label(head, res.output.reason[:110], (140, 24), 0.55)
    sub = f"cycle {res.index}   t = {res.stamp_ns / 1e9:.1f} s   {len(res.cells_xy)} occupied cells"
    if status and status.get("sim"):
        s = status["sim"]
        sub += (f"   sim: {s.get('distance_m', 0):.0f} m driven, {s.get('collisions', 0)} "
                f"collisions")
    _label(head, sub, (140, 46), 0.45, (235, 235, 235))
    return np.concatenate([head, body], axis=0)


def encode_png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()
