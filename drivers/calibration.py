"""Calibration and mounting for the hardware drivers.

* ``MOUNT_SCHEMA`` / :func:`mount_from_options`: every hardware driver takes its mounting (where
  the sensor sits on the vehicle) from the same config keys.
* Stereo calibration from chessboard images (:func:`calibrate_stereo`), saved and loaded as JSON
  (:func:`save_stereo_calibration`, :func:`load_stereo_calibration`) and turned into rectification
  maps (:class:`Rectifier`). ``tools/calibrate_stereo.py`` is the command-line front end.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hal.errors import ConfigError
from hal.types import Mount, PinholeCalibration, StereoCalibration

MOUNT_SCHEMA = {"mount_x_m": float, "mount_y_m": float, "mount_z_m": float,
                "mount_roll_deg": float, "mount_pitch_deg": float, "mount_yaw_deg": float}


def mount_from_options(opts, default: Mount | None = None) -> Mount:
    """A Mount from ``mount_*`` option keys; keys not given keep ``default``'s values."""
    d = default or Mount()
    return Mount(x_m=float(opts.get("mount_x_m", d.x_m)), y_m=float(opts.get("mount_y_m", d.y_m)),
                 z_m=float(opts.get("mount_z_m", d.z_m)),
                 roll_deg=float(opts.get("mount_roll_deg", d.roll_deg)),
                 pitch_deg=float(opts.get("mount_pitch_deg", d.pitch_deg)),
                 yaw_deg=float(opts.get("mount_yaw_deg", d.yaw_deg)))


# ---------------------------------------------------------------------------------------------
# stereo calibration from chessboard images
@dataclass
class StereoCalibrationResult:
    """A calibrated (unrectified) pair: intrinsics and distortion of each camera, the pose of the
    right camera in the left camera's frame (x_r = R x_l + T, metres), and the fit's RMS error."""

    image_size: tuple[int, int]         # (width, height)
    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    rms_px: float = float("nan")
    pairs_used: int = 0

    def to_json(self) -> dict:
        return {"format": "fieldguard-stereo-calibration/1", "image_size": list(self.image_size),
                "K1": self.K1.tolist(), "D1": self.D1.ravel().tolist(),
                "K2": self.K2.tolist(), "D2": self.D2.ravel().tolist(),
                "R": self.R.tolist(), "T": self.T.ravel().tolist(),
                "rms_px": self.rms_px, "pairs_used": self.pairs_used}

    @classmethod
    def from_json(cls, d: dict) -> "StereoCalibrationResult":
        try:
            if d.get("format") != "fieldguard-stereo-calibration/1":
                raise ValueError(f"unknown format {d.get('format')!r}")
            w, h = (int(v) for v in d["image_size"])
            r = cls((w, h), np.array(d["K1"], float).reshape(3, 3),
                    np.array(d["D1"], float).ravel(), np.array(d["K2"], float).reshape(3, 3),
                    np.array(d["D2"], float).ravel(), np.array(d["R"], float).reshape(3, 3),
                    np.array(d["T"], float).reshape(3), float(d.get("rms_px", "nan")),
                    int(d.get("pairs_used", 0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a stereo calibration: {exc}") from None
        if not np.isfinite(r.K1).all() or r.K1[0, 0] <= 0 or np.linalg.norm(r.T) <= 0:
            raise ValueError("not a stereo calibration: bad intrinsics or zero baseline")
        return r


def find_chessboard(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner-corner positions (N,1,2) float32, or None if the board is not found."""
    import cv2
    ok, corners = cv2.findChessboardCorners(
        gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    return cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), crit)


def calibrate_stereo(pairs, pattern=(9, 6), square_m: float = 0.025,
                     log=lambda msg: None) -> StereoCalibrationResult:
    """Calibrate a stereo pair from ``pairs`` of (left, right) images (BGR or grey arrays) of a
    chessboard with ``pattern`` inner corners and ``square_m`` squares. Pairs where the board is
    not found in both images are skipped. Each camera is calibrated alone first, then the pair
    with the intrinsics fixed (OpenCV's recommended order)."""
    import cv2
    obj = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0:pattern[0], 0:pattern[1]].T.reshape(-1, 2) * square_m
    objs, pl, pr, size = [], [], [], None
    for i, (left, right) in enumerate(pairs):
        gl = left if left.ndim == 2 else cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
        gr = right if right.ndim == 2 else cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
        if gl.shape != gr.shape or (size is not None and size != gl.shape[::-1]):
            raise ValueError(f"pair {i}: image sizes differ")
        size = gl.shape[::-1]
        cl, cr = find_chessboard(gl, pattern), find_chessboard(gr, pattern)
        if cl is None or cr is None:
            log(f"pair {i}: chessboard not found in {'left' if cl is None else 'right'} image; "
                f"skipped")
            continue
        objs.append(obj)
        pl.append(cl)
        pr.append(cr)
    if len(objs) < 3:
        raise ValueError(f"the chessboard was found in only {len(objs)} pair(s); need 3 or more")
    _, K1, D1, _, _ = cv2.calibrateCamera(objs, pl, size, None, None)
    _, K2, D2, _, _ = cv2.calibrateCamera(objs, pr, size, None, None)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        objs, pl, pr, K1, D1, K2, D2, size, criteria=crit, flags=cv2.CALIB_FIX_INTRINSIC)
    return StereoCalibrationResult((int(size[0]), int(size[1])), K1, D1.ravel(), K2, D2.ravel(),
                                   R, T.ravel(), float(rms), len(objs))


def save_stereo_calibration(result: StereoCalibrationResult, path) -> None:
    Path(path).write_text(json.dumps(result.to_json(), indent=1) + "\n", encoding="utf-8")


def load_stereo_calibration(path) -> StereoCalibrationResult:
    p = Path(path)
    try:
        return StereoCalibrationResult.from_json(json.loads(p.read_text(encoding="utf-8")))
    except FileNotFoundError:
        raise ConfigError("calibration file not found", file=str(p)) from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot use calibration: {exc}", file=str(p)) from None


class Rectifier:
    """Rectification maps for a calibrated pair (cv2.stereoRectify, zero-disparity, alpha 0: only
    valid pixels), and the rectified pinhole model the HAL's StereoCalibration needs."""

    def __init__(self, cal: StereoCalibrationResult, mount: Mount):
        import cv2
        self.cal = cal
        size = cal.image_size
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(cal.K1, cal.D1.reshape(1, -1), cal.K2,
                                                   cal.D2.reshape(1, -1), size, cal.R,
                                                   cal.T.reshape(3, 1),
                                                   flags=cv2.CALIB_ZERO_DISPARITY,
                                                   alpha=0.0)
        self.P1, self.P2, self.Q = P1, P2, Q
        self.maps = [cv2.initUndistortRectifyMap(K, D, Rr, P, size, cv2.CV_16SC2)
                     for K, D, Rr, P in ((cal.K1, cal.D1, R1, P1), (cal.K2, cal.D2, R2, P2))]
        baseline = abs(P2[0, 3] / P2[0, 0])
        cam = PinholeCalibration(size[0], size[1], float(P1[0, 0]), float(P1[1, 1]),
                                 float(P1[0, 2]), float(P1[1, 2]))
        self.stereo_calibration = StereoCalibration(cam, float(baseline), mount)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import cv2
        (m1l, m2l), (m1r, m2r) = self.maps
        return (cv2.remap(left, m1l, m2l, cv2.INTER_LINEAR),
                cv2.remap(right, m1r, m2r, cv2.INTER_LINEAR))
