"""What did the box have on an obstacle it drove into? One closed-loop campaign drive replayed,
and per cycle of a time window what the stereo-novelty pipeline had on that obstacle.

    python tools/why_missed.py KIND SEED OBSTACLE T0 T1 [--minutes 2] [--stereo-scale 0.5] \
        [--config extra.toml] [--picture DIR]

Runs the drive exactly as ``fieldguard campaign`` does (appliance/campaign_drive.Drive, the
same config; pass the campaign's ``--minutes`` so the field is the same) and for every cycle
between T0 and T1 seconds prints: the box's state; where the obstacle is (ahead of the front,
to the side: the vehicle frame); whether both cameras see it (``pair``: inside the common view
of the left and right images at its depth, else ``left``/``right``/``none``); the dense points
within 0.5 m of its footprint (all, and those kept in the height band) and their heights; the
occupied cells near it; the novelty of its cells at 0.3 / 0.6 / 0.9 m up (1 novel, 0 not,
``-`` out of the image) and the novelty model's updates so far. ``--picture DIR`` writes the
left image with the novelty mask tinted (an RGB-D drive: the colour image), per cycle, into DIR.

OBSTACLE is the scene's obstacle id (``c1``...: the campaign's events name it, e.g.
``c1/person-crouching``). Training seeds only (< 1000): acceptance drives are scored, not
looked into.

An RGB-D drive (the greenhouse: `[perception] pipelines = ["rgbd"]`) prints instead, per cycle:
whether the obstacle is in the Kinect's view (``view``: its middle inside the image and within
the depth range; ``out`` otherwise, ``beside`` when it is behind the camera's image plane), the
depth points within 0.5 m of its footprint, the rgbd candidates there (points, cues), the
occupied cells near it, and the box's state and reason -- for collisions where nothing ever had
a pixel of it (an obstacle beside the body in a U-turn, a person stepping out of a bush row).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402


def seen_by(cal, pc: np.ndarray, width: int) -> str:
    """Which cameras of the pair see camera-frame point ``pc`` (left camera's frame)."""
    if pc[2] <= 0:
        return "none"
    u = cal.camera.cx + cal.camera.fx * pc[0] / pc[2]
    d = cal.camera.fx * cal.baseline_m / pc[2]           # its disparity: u in the right image
    in_left, in_right = 0 <= u < width, 0 <= u - d < width
    return {(True, True): "pair", (True, False): "left", (False, True): "right"}.get(
        (in_left, in_right), "none")


def kinect_view(cal, pc: np.ndarray) -> str:
    """Is camera-frame point ``pc`` in the RGB-D camera's view: ``view`` (inside the image and
    the depth range), ``out`` (in front of the camera but outside either), ``beside`` (at or
    behind its image plane)."""
    if pc[2] <= 0.05:
        return "beside"
    u = cal.camera.cx + cal.camera.fx * pc[0] / pc[2]
    v = cal.camera.cy + cal.camera.fy * pc[1] / pc[2]
    inside = 0 <= u < cal.camera.width and 0 <= v < cal.camera.height
    return "view" if inside and cal.min_range_m <= pc[2] <= cal.max_range_m else "out"


def rgbd_line(t: float, res, ob, pose, front_x_m: float) -> str:
    """One cycle of an RGB-D drive, on obstacle ``ob`` (see the module's text)."""
    x, y, yaw = pose
    dx, dy = ob.x - x, ob.y - y                          # the obstacle moves: read it now
    cy, sy = math.cos(yaw), math.sin(yaw)
    ox, oy = cy * dx + sy * dy, -sy * dx + cy * dy
    hx, hy = ob.length_m / 2 + 0.5, ob.width_m / 2 + 0.5

    def near(p):
        p = np.asarray(p, np.float64).reshape(-1, 2)
        return (np.abs(p[:, 0] - ox) <= hx) & (np.abs(p[:, 1] - oy) <= hy)
    fr = res.inputs.rgbd
    view = "-"
    if fr is not None:
        cal = fr.calib
        pc = cal.mount.camera_to_vehicle().T @ (np.array([ox, oy, ob.height_m / 2])
                                                - np.asarray(cal.mount.position))
        view = kinect_view(cal, pc)
    det = res.detections.get("rgbd")
    n_pts, cand = 0, "-"
    if det is not None:
        n_pts = int(near(det.points_xy).sum()) if len(det.points_xy) else 0
        cs = [c for c in det.candidates if abs(c.x_m - ox) <= hx and abs(c.y_m - oy) <= hy]
        if cs:
            cues = sorted({src for c in cs for src in c.sources})
            cand = f"{sum(c.points for c in cs)} ({','.join(cues)})"
    cells = np.asarray(res.cells_xy, float).reshape(-1, 2)
    n_cells = int(near(cells).sum()) if len(cells) else 0
    return (f"t={t:6.1f} {res.output.state.value:5s} ahead {ox - front_x_m:6.2f} m "
            f"side {oy:+5.2f} m  {view:6s}  points {n_pts:4d}  candidates {cand:20s}  "
            f"cells {n_cells:3d}  {res.output.reason[:60]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("obstacle", help="the scene's obstacle id, e.g. c1")
    ap.add_argument("t0", type=float)
    ap.add_argument("t1", type=float)
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--stereo-scale", type=float, default=0.5)
    ap.add_argument("--config", default=None)
    ap.add_argument("--picture", default=None, metavar="DIR")
    a = ap.parse_args(argv)
    if a.seed >= 1000:
        print("why_missed: error: training seeds only (< 1000): acceptance drives are scored, "
              "not looked into", file=sys.stderr)
        return 2
    if a.t1 < a.t0:
        print("why_missed: error: T1 must not be before T0", file=sys.stderr)
        return 2
    from appliance.campaign import load_extra_config, make_spec
    from appliance.campaign_drive import Drive
    extra = load_extra_config(a.config) if a.config else None
    spec = make_spec(a.kind, a.seed, a.minutes, a.stereo_scale, extra)
    d = Drive(a.kind, a.seed, a.minutes, config_data=spec["config"],
              stereo_scale=a.stereo_scale)
    d.build()
    d.n_cycles = min(d.n_cycles, int(math.ceil(a.t1 * d.rate)) + 1)   # the same drive, to T1
    pipe = next((p for p in d.daemon.pipelines if hasattr(p, "novelty")), None)
    rgbd = pipe is None and any(p.name == "rgbd" for p in d.daemon.pipelines)
    if pipe is None and not rgbd:
        runs = ", ".join(p.name for p in d.daemon.pipelines)
        print(f"why_missed: error: the drive runs {runs}, not stereo-novelty or rgbd (--config "
              "with [perception] pipelines = [\"stereo-novelty\"])", file=sys.stderr)
        return 2
    obs = {o.id: o for o in d.field.world.obstacles}
    if a.obstacle not in obs:
        print(f"why_missed: error: no obstacle {a.obstacle!r} in {a.kind} {a.seed}; it has "
              f"{', '.join(sorted(obs))}", file=sys.stderr)
        return 2
    ob = obs[a.obstacle]
    pic_dir = Path(a.picture) if a.picture else None
    if pic_dir is not None:
        pic_dir.mkdir(parents=True, exist_ok=True)
    print(f"{a.kind} {a.seed}: {ob.id} {ob.cls} ({ob.shape}, {ob.height_m:.2f} m tall, "
          f"{ob.length_m:.2f} x {ob.width_m:.2f} m)")

    def after(res):
        t = res.index / d.rate
        if t < a.t0 - 1e-9 or t > a.t1 + 1e-9:
            return
        if rgbd:
            print(rgbd_line(t, res, ob, d.vehicle.pose(), d.zones.front_x_m), flush=True)
            if pic_dir is not None and res.inputs.rgbd is not None:
                import cv2
                cv2.imwrite(str(pic_dir / f"{a.kind}-{a.seed}-{ob.id}-t{t:05.1f}.png"),
                            res.inputs.rgbd.color)
            return
        x, y, yaw = d.vehicle.pose()
        dx, dy = ob.x - x, ob.y - y                      # the obstacle moves: read it now
        cy, sy = math.cos(yaw), math.sin(yaw)
        ox, oy = cy * dx + sy * dy, -sy * dx + cy * dy
        near = lambda p: (np.abs(p[:, 0] - ox) <= ob.length_m / 2 + 0.5) & (  # noqa: E731
            np.abs(p[:, 1] - oy) <= ob.width_m / 2 + 0.5)
        pts, px, h, keep, k = pipe.last_points
        n_all = int(near(pts).sum()) if len(pts) else 0
        kn = near(pts[keep]) if len(pts) else np.zeros(0, bool)
        hs = "-" if not kn.any() else "/".join(
            f"{v:.2f}" for v in np.percentile(h[keep][kn], [10, 50, 90]))
        cells = np.asarray(res.cells_xy, float).reshape(-1, 2)
        n_cells = int(near(cells).sum()) if len(cells) else 0
        # every matched point near it (band or not): how high the stereo read it
        an = near(pts) if len(pts) else np.zeros(0, bool)
        hall = "-" if not an.any() else "/".join(
            f"{v:.2f}" for v in np.percentile(h[an], [10, 50, 90]))
        # the grid's largest evidence on it (its footprint + 0.5 m), after this cycle
        grid = d.daemon.loop.grid
        gx = grid.centres(*np.nonzero(grid.evidence > 0))
        ev = grid.evidence[grid.evidence > 0]
        gn = near(gx) if len(gx) else np.zeros(0, bool)
        evmax = float(ev[gn].max()) if gn.any() else 0.0
        fr = res.inputs.stereo
        cal = fr.calib
        R = cal.mount.camera_to_vehicle()
        pos = np.asarray(cal.mount.position)
        H, W = fr.left.shape[:2]
        nres = pipe.last[0]
        m = nres.mask
        nov, view = [], None
        for hz in (0.3, 0.6, 0.9):
            pc = R.T @ (np.array([ox, oy, min(hz, ob.height_m)]) - pos)
            if view is None:
                view = seen_by(cal, pc, W)
            if pc[2] <= 0:
                nov.append("-")
                continue
            u = cal.camera.cx + cal.camera.fx * pc[0] / pc[2]
            v = cal.camera.cy + cal.camera.fy * pc[1] / pc[2]
            mu, mv = int(u / W * m.shape[1]), int(v / H * m.shape[0])
            nov.append("-" if not (0 <= mu < m.shape[1] and 0 <= mv < m.shape[0])
                       else str(int(m[mv, mu])))
        print(f"t={t:6.1f} {res.output.state.value:5s} ahead {ox - d.zones.front_x_m:6.2f} m "
              f"side {oy:+5.2f} m  {view:5s}  points {n_all:4d} (band {int(kn.sum()):4d}, "
              f"h {hs}; all h {hall})  cells {n_cells:3d} (evidence {evmax:.2f})  "
              f"novel {'/'.join(nov)}  "
              f"updates {pipe.novelty.model.updates}  {res.output.reason[:60]}", flush=True)
        if pic_dir is not None:
            import cv2
            img = cv2.cvtColor(fr.left, cv2.COLOR_GRAY2BGR) if fr.left.ndim == 2 else \
                fr.left.copy()
            mm = cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0
            img[mm] = (0.5 * img[mm] + 0.5 * np.array([255, 80, 0])).astype(np.uint8)
            cv2.imwrite(str(pic_dir / f"{a.kind}-{a.seed}-{ob.id}-t{t:05.1f}.png"), img)

    d.daemon.loop.on_cycle.append(after)
    d.run()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
