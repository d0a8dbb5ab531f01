#!/usr/bin/env python3
"""Calibrate the stereo pair from chessboard images and write the JSON the aravis driver loads
(``[devices.stereo] calibration = "..."``).

    .venv/bin/python tools/calibrate_stereo.py --left 'cal/left*.jpg' --right 'cal/right*.jpg' \\
        --pattern 9x6 --square-m 0.025 --out deploy/stereo-calibration.json

Left and right images are paired in sorted order (left01 with right01, ...). Prints the RMS
reprojection error, the baseline and the rectified focal length; a good calibration has an RMS
under about 0.5 px. With --check it also rectifies every pair and prints the mean vertical
offset of the chessboard corners between left and right (should be well under 1 px).
"""
from __future__ import annotations

import argparse
import glob
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    import cv2
    import numpy as np

    from drivers.calibration import (Rectifier, calibrate_stereo, find_chessboard,
                                     save_stereo_calibration)
    from hal.types import Mount
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--left", required=True, help="glob of left images")
    ap.add_argument("--right", required=True, help="glob of right images")
    ap.add_argument("--pattern", default="9x6", help="inner corners, COLSxROWS (default 9x6)")
    ap.add_argument("--square-m", type=float, required=True, help="chessboard square size, m")
    ap.add_argument("--out", required=True, help="calibration JSON to write")
    ap.add_argument("--check", action="store_true", help="report rectification quality")
    a = ap.parse_args(argv)
    lefts, rights = sorted(glob.glob(a.left)), sorted(glob.glob(a.right))
    if not lefts or len(lefts) != len(rights):
        print(f"calibrate_stereo: {len(lefts)} left and {len(rights)} right images; need the "
              f"same number, at least 3", file=sys.stderr)
        return 2
    cols, rows = (int(v) for v in a.pattern.lower().split("x"))
    pairs = [(cv2.imread(l), cv2.imread(r)) for l, r in zip(lefts, rights)]
    for (l, r), name in zip(pairs, lefts):
        if l is None or r is None:
            print(f"calibrate_stereo: cannot read {name} or its partner", file=sys.stderr)
            return 2
    try:
        res = calibrate_stereo(pairs, (cols, rows), a.square_m, log=print)
    except ValueError as exc:
        print(f"calibrate_stereo: {exc}", file=sys.stderr)
        return 1
    save_stereo_calibration(res, a.out)
    rect = Rectifier(res, Mount())
    sc = rect.stereo_calibration
    print(f"pairs used {res.pairs_used}/{len(pairs)}, RMS {res.rms_px:.3f} px, baseline "
          f"{sc.baseline_m * 1000:.1f} mm, rectified fx {sc.camera.fx:.1f} px, "
          f"image {res.image_size[0]}x{res.image_size[1]} -> {a.out}")
    if a.check:
        dys = []
        for l, r in pairs:
            rl, rr = rect.rectify(l, r)
            cl = find_chessboard(cv2.cvtColor(rl, cv2.COLOR_BGR2GRAY), (cols, rows))
            cr = find_chessboard(cv2.cvtColor(rr, cv2.COLOR_BGR2GRAY), (cols, rows))
            if cl is not None and cr is not None:
                dys.append(float(np.mean(np.abs(cl.reshape(-1, 2)[:, 1] - cr.reshape(-1, 2)[:, 1]))))
        print(f"rectified: mean |dy| of corners {np.mean(dys):.3f} px over {len(dys)} pairs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
