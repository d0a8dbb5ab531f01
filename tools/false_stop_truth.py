"""What was really where the box saw an obstacle? The points of a dumped false stop against
the simulator's world.

    python tools/false_stop_truth.py DIR/KIND-SEED-tNN.N.npz KIND SEED [--all]

Reads an ``.npz`` of ``tools/why_false_stops.py --dump`` (the stop cycle, c0, and the two
before) and, for the kept obstacle points near the stop zone of each cycle (every point with
``--all``, else about 12 a cycle):

- the measured point (vehicle frame x, y, its height above the pipeline's ground, its pixel);
- the ray through its pixel cast into the world (ground + stubble + obstacles, the vehicle on
  the ground at its pose, turned by the vehicle's roll and pitch when the dump has them, as
  the pipeline turns its points): what it hits first, how high that is above the local ground,
  and its material (0 ground, 1 stubble, >= 2 an obstacle);
- per cluster of stop-zone points: the tallest tuft within 0.25 m along / 0.2 m across of
  its median point, and the ground's rise there above the vehicle's.

A real tuft taller than the band's floor shows as the ray hitting stubble (mat 1) at the
measured range, and a tall tuft near the point; a mismatch as the ray hitting something at
another range.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("npz")
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("--all", action="store_true", help="every near-zone point, not ~12")
    a = ap.parse_args(argv)
    from drivers.sim.scenes import build_scene
    z = np.load(a.npz, allow_pickle=True)
    w = build_scene(a.kind, a.seed).world
    fx, fy, cx, cy = (float(z[k]) for k in ("fx", "fy", "cx", "cy"))
    R, o = z["mount_R"], z["mount_xyz"]
    front, hw = float(z["front_x_m"]), float(z["half_width_m"])
    for i in range(3):
        if f"c{i}_t_s" not in z.files:
            continue
        px_, py_, yaw, sp = (float(v) for v in z[f"c{i}_pose"])
        g0 = float(w.ground(np.float32(px_), np.float32(py_)))
        k = int(z[f"c{i}_k"])
        pts, px, h, keep = (z[f"c{i}_{n}"] for n in ("pts", "px", "h", "keep"))
        sl = float(z[f"c{i}_stop_len"])
        kp, kpx, kh = pts[keep], px[keep], h[keep]
        near = ((kp[:, 0] - front >= -0.2) & (kp[:, 0] - front <= sl + 1.0)
                & (np.abs(kp[:, 1]) <= hw + 0.3))
        inz = (kp[:, 0] - front >= 0) & (kp[:, 0] - front <= sl) & (np.abs(kp[:, 1]) <= hw)
        print(f"--- t={float(z[f'c{i}_t_s']):.1f} s pose ({px_:.2f}, {py_:.2f}, "
              f"{math.degrees(yaw):.1f} deg) {sp:.2f} m/s: {len(kp)} obstacle points, "
              f"{int(inz.sum())} in the stop zone ({sl:.2f} m), {int(near.sum())} near it")
        c, s = math.cos(yaw), math.sin(yaw)
        Rv = R
        if f"c{i}_att" in z.files:
            from hal.types import rotation_rpy
            roll, pitch = (float(v) for v in z[f"c{i}_att"])
            Rv = rotation_rpy(roll, pitch, 0.0) @ R
            print(f"    attitude: roll {math.degrees(roll):.2f} deg, pitch (nose down) "
                  f"{math.degrees(pitch):.2f} deg")
        else:
            print("    attitude not in the dump: the vehicle taken level")
        idx = np.flatnonzero(near)
        step = 1 if a.all else max(1, len(idx) // 12)
        for j in idx[::step]:
            u, v = kpx[j] * k
            dv = Rv @ np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
            ts = np.arange(0.5, 30.0, 0.005)
            P = o[None, :] + ts[:, None] * dv[None, :]
            X = (px_ + c * P[:, 0] - s * P[:, 1]).astype(np.float32)
            Y = (py_ + s * P[:, 0] + c * P[:, 1]).astype(np.float32)
            hh, mat = w.height(X, Y)
            hit = np.flatnonzero(hh - g0 >= P[:, 2])
            msg = (f"  measured x {kp[j, 0]:.2f} y {kp[j, 1]:.2f} h {kh[j]:.2f} px ({u:.0f}, "
                   f"{v:.0f}){' [stop zone]' if inz[j] else ''}")
            if len(hit) == 0:
                print(msg + " | the ray hits nothing within 30 m")
                continue
            q = hit[0]
            gq = float(w.ground(X[q:q + 1], Y[q:q + 1])[0])
            print(msg + f" | ray hits x {P[q, 0]:.2f} y {P[q, 1]:.2f} at {P[q, 2]:.2f} m, "
                        f"{P[q, 2] - (gq - g0):.2f} above its ground (rise {gq - g0:.2f}), "
                        f"mat {int(mat[q])}")
        if inz.any():
            mx, my = np.median(kp[inz, 0]), np.median(kp[inz, 1])
            xs = np.arange(px_ + mx - 0.25, px_ + mx + 0.25, 0.01, dtype=np.float32)
            best = (0.0, 0.0, 0.0, 0.0)
            for yy in np.arange(my - 0.2, my + 0.2, 0.01, dtype=np.float32):
                # the lane runs along the pose's heading: a point (mx + dx, yy) of the vehicle
                X = (px_ + c * (xs - px_) - s * yy).astype(np.float32)
                Y = (py_ + s * (xs - px_) + c * yy).astype(np.float32)
                tt, _ = w.terrain(X, Y)
                gg = w.ground(X, Y)
                t = tt - gg
                m = int(t.argmax())
                if t[m] > best[0]:
                    best = (float(t[m]), float(xs[m] - px_), float(yy), float(gg[m]) - g0)
            print(f"  tallest tuft within 0.25 m / 0.2 m of the stop-zone points' median "
                  f"({mx:.2f}, {my:.2f}): {best[0]:.2f} m at ({best[1]:.2f}, {best[2]:.2f}), "
                  f"on ground {best[3]:+.2f} m from the vehicle's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
