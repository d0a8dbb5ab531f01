"""Read and write run folders (docs/run-format.md, the contract).

The reader accepts any folder that follows the contract and nothing else: every departure raises
:class:`hal.RunFormatError` with a message that names the file (and the key, line or column) that
is wrong. Project extensions (extra ``run.toml`` keys and tables, extra ``frames.csv`` columns,
extra truth keys) are kept, never rejected.

A frame whose sensor file is *missing* returns None for that sensor (recordings drop frames); a
file that is present but unreadable, of the wrong type or of the wrong size is an error.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import shutil
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tomli_w

from hal import (DepthCalibration, DepthFrame, LaserGeometry, LaserScan, Mount,
                 PinholeCalibration, RunFormatError, StereoCalibration, StereoFrame, VehicleState)

log = logging.getLogger("fieldguard.runfolder")

__all__ = ["RunInfo", "FrameRecord", "RunReader", "RunWriter", "scored_zone_for",
           "FRAME_COLUMNS", "ILLUMINATIONS", "SENSORS"]

SENSORS = ("stereo", "rgbd", "laser")
ILLUMINATIONS = ("day", "night-strobe")
# frames.csv columns the contract names, in the order the writer puts them
FRAME_COLUMNS = ("index", "stamp_ns", "speed_mps", "yaw_rate_radps", "roll_rad", "pitch_rad",
                 "yaw_rad", "illumination")
_FLOAT_COLUMNS = ("speed_mps", "yaw_rate_radps", "roll_rad", "pitch_rad", "yaw_rad")
_MOUNT_KEYS = ("x_m", "y_m", "z_m", "roll_deg", "pitch_deg", "yaw_deg")
_MOUNT_REQUIRED = ("x_m", "y_m", "z_m")
_OBSTACLE_REQUIRED = ("id", "class", "x_m", "y_m", "length_m", "width_m")


def _name(i: int) -> str:
    return f"{int(i):06d}"


# ---------------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunInfo:
    path: Path
    name: str
    rate_hz: float
    stereo: StereoCalibration | None
    rgbd: DepthCalibration | None
    laser: LaserGeometry | None
    scored_zone: tuple[float, float] | None     # [run] scored_zone = {x_min_m, x_max_m}
    reference_point: str | None
    extra: dict = field(default_factory=dict)   # all of run.toml as parsed

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors this run holds, e.g. ("stereo", "laser")."""
        return tuple(s for s in SENSORS if getattr(self, s) is not None)


@dataclass(frozen=True)
class FrameRecord:
    index: int
    stamp_ns: int                     # from frames.csv, else index * 1e9 / rate_hz
    speed_mps: float | None = None
    yaw_rate_radps: float | None = None
    roll_rad: float | None = None
    pitch_rad: float | None = None
    yaw_rad: float | None = None
    illumination: str | None = None
    extra: dict = field(default_factory=dict)   # unknown columns, as strings


def scored_zone_for(info: RunInfo) -> tuple[float, float]:
    """(x_min_m, x_max_m) of the scored zone, with the run format's defaults: the run's own
    ``[run] scored_zone``; else 2-20 m for a run with stereo; else 0.5-5 m beyond the RGB-D
    camera. A run with neither camera nor scored_zone has no scored zone (RunFormatError)."""
    if info.scored_zone is not None:
        return info.scored_zone
    if info.stereo is not None:
        return (2.0, 20.0)
    if info.rgbd is not None:
        x = info.rgbd.mount.x_m
        return (x + 0.5, x + 5.0)
    raise RunFormatError(f"{info.path / 'run.toml'}: run has no camera and no "
                         f"[run] scored_zone, so it has no scored zone")


# ---------------------------------------------------------------------------------------------
# run.toml parsing
# ---------------------------------------------------------------------------------------------
class _Toml:
    """Typed access to one table of run.toml, with errors that name the file and key."""

    def __init__(self, file: Path, table: str, data: Any):
        self.file, self.table = file, table
        if not isinstance(data, dict):
            self.fail(f"[{table}] must be a table")
        self.data = data

    def fail(self, msg: str):
        raise RunFormatError(f"{self.file}: {msg}")

    def key(self, k: str) -> str:
        return f"[{self.table}] {k}"

    def number(self, k: str, default: float | None = None, *, positive: bool = False,
               required: bool = True) -> float | None:
        if k not in self.data:
            if default is not None or not required:
                return default
            self.fail(f"{self.key(k)} is missing")
        v = self.data[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(f"{self.key(k)} must be a finite number, got {v!r}")
        if positive and v <= 0:
            self.fail(f"{self.key(k)} must be > 0, got {v!r}")
        return float(v)

    def integer(self, k: str, *, positive: bool = True) -> int:
        if k not in self.data:
            self.fail(f"{self.key(k)} is missing")
        v = self.data[k]
        if isinstance(v, float) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(f"{self.key(k)} must be an integer, got {v!r}")
        if positive and v <= 0:
            self.fail(f"{self.key(k)} must be > 0, got {v!r}")
        return v

    def mount(self) -> Mount:
        if "mount" not in self.data:
            self.fail(f"{self.key('mount')} is missing (every sensor needs a mount "
                      f"{{ x_m, y_m, z_m, roll_deg, pitch_deg, yaw_deg }})")
        m = _Toml(self.file, f"{self.table}.mount", self.data["mount"])
        unknown = sorted(set(m.data) - set(_MOUNT_KEYS))
        if unknown:
            self.fail(f"{self.key('mount')} has unknown key(s) {unknown}; "
                      f"expected {list(_MOUNT_KEYS)}")
        vals = {k: m.number(k, required=k in _MOUNT_REQUIRED) for k in _MOUNT_KEYS}
        return Mount(**{k: (0.0 if v is None else v) for k, v in vals.items()})

    def pinhole(self) -> PinholeCalibration:
        return PinholeCalibration(width=self.integer("width"), height=self.integer("height"),
                                  fx=self.number("fx", positive=True),
                                  fy=self.number("fy", positive=True),
                                  cx=self.number("cx"), cy=self.number("cy"))


def _parse_run_toml(path: Path) -> RunInfo:
    file = path / "run.toml"
    if not path.is_dir():
        raise RunFormatError(f"{path}: not a run folder (no such directory)")
    if not file.is_file():
        raise RunFormatError(f"{file}: missing (every run folder needs run.toml)")
    try:
        with open(file, "rb") as f:
            doc = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise RunFormatError(f"{file}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RunFormatError(f"{file}: cannot read: {exc}") from None

    run = _Toml(file, "run", doc.get("run", {}))
    name = run.data.get("name", path.name)
    if not isinstance(name, str) or not name:
        run.fail(f"[run] name must be a non-empty string, got {name!r}")
    rate_hz = run.number("rate_hz", 10.0, positive=True)
    scored_zone = None
    if "scored_zone" in run.data:
        z = _Toml(file, "run.scored_zone", run.data["scored_zone"])
        lo, hi = z.number("x_min_m"), z.number("x_max_m")
        if not lo < hi:
            run.fail(f"[run] scored_zone needs x_min_m < x_max_m, got {lo} .. {hi}")
        scored_zone = (lo, hi)
    ref = run.data.get("reference_point")
    if ref is not None and not isinstance(ref, str):
        run.fail(f"[run] reference_point must be a string, got {ref!r}")

    stereo = rgbd = laser = None
    if "stereo" in doc:
        t = _Toml(file, "stereo", doc["stereo"])
        stereo = StereoCalibration(camera=t.pinhole(),
                                   baseline_m=t.number("baseline_m", positive=True),
                                   mount=t.mount())
    if "rgbd" in doc:
        t = _Toml(file, "rgbd", doc["rgbd"])
        rgbd = DepthCalibration(camera=t.pinhole(), mount=t.mount(),
                                depth_unit_m=t.number("depth_unit_m", 0.001, positive=True))
    if "laser" in doc:
        t = _Toml(file, "laser", doc["laser"])
        laser = LaserGeometry(angle_min_deg=t.number("angle_min_deg"),
                              angle_step_deg=t.number("angle_step_deg"),
                              beams=t.integer("beams"),
                              range_max_m=t.number("range_max_m", positive=True),
                              mount=t.mount())
    return RunInfo(path=path, name=name, rate_hz=rate_hz, stereo=stereo, rgbd=rgbd, laser=laser,
                   scored_zone=scored_zone, reference_point=ref, extra=doc)


# ---------------------------------------------------------------------------------------------
# frames.csv parsing
# ---------------------------------------------------------------------------------------------
def _parse_frames(info: RunInfo, warnings: list[str] | None = None) -> list[FrameRecord]:
    """frames.csv as records. A last line cut short (no end of line, and the file is valid
    without it: what a power cut during a write leaves) is dropped with a warning (logged and
    appended to ``warnings``); any other departure from the contract is an error."""
    file = info.path / "frames.csv"
    if not file.is_file():
        raise RunFormatError(f"{file}: missing (every run folder needs frames.csv)")
    try:
        raw = file.read_bytes()
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        # a write cut inside a multi-byte character is a torn last line too
        cut = raw.rfind(b"\n") + 1
        if not raw.endswith(b"\n") and exc.start >= cut > 0:
            text = raw[:cut].decode("utf-8-sig", errors="strict") + "\ufffd"
        else:
            raise RunFormatError(f"{file}: cannot read: {exc}") from None
    except OSError as exc:
        raise RunFormatError(f"{file}: cannot read: {exc}") from None
    try:
        return _parse_frames_text(file, text, info)
    except RunFormatError as exc:
        cut = text.rfind("\n") + 1
        if text.endswith(("\n", "\r")) or cut == 0 or not text[cut:].strip():
            raise
        try:
            frames = _parse_frames_text(file, text[:cut], info)
        except RunFormatError:
            raise exc from None
        line = text.count("\n") + 1
        msg = (f"{file}: line {line} is cut short (no end of line, as a write cut off by a "
               f"power cut leaves it): dropped it ({exc})")
        log.warning("%s", msg)
        if warnings is not None:
            warnings.append(msg)
        return frames


def _parse_frames_text(file: Path, text: str, info: RunInfo) -> list[FrameRecord]:
    try:
        rows = list(csv.reader(io.StringIO(text)))
    except csv.Error as exc:            # a bare CR inside a field (tests/fuzz/fuzz_runfolder.py)
        raise RunFormatError(f"{file}: not readable as CSV: {exc}") from None
    if not rows:
        raise RunFormatError(f"{file}: empty (needs a header row with an 'index' column)")
    header = [h.strip() for h in rows[0]]
    if "index" not in header:
        raise RunFormatError(f"{file}: header has no 'index' column (header: {header})")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise RunFormatError(f"{file}: duplicate column(s) {dup}")

    frames: list[FrameRecord] = []
    seen: dict[int, int] = {}
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue                      # blank line (e.g. at the end)
        if len(row) != len(header):
            raise RunFormatError(f"{file}: line {lineno} has {len(row)} fields, "
                                 f"header has {len(header)}")
        cells = {h: c.strip() for h, c in zip(header, row)}

        def bad(col: str, what: str):
            raise RunFormatError(f"{file}: line {lineno}, column '{col}': {what}, "
                                 f"got {cells[col]!r}")

        def as_int(col: str) -> int:
            s = cells[col]
            try:
                return int(s)
            except ValueError:
                try:
                    f = float(s)
                except ValueError:
                    f = math.nan
                if math.isfinite(f) and f.is_integer():
                    return int(f)
            bad(col, "expected an integer")

        idx = as_int("index")
        if not cells["index"] or idx < 0:
            bad("index", "expected an integer >= 0")
        if idx in seen:
            raise RunFormatError(f"{file}: line {lineno}: index {idx} repeats line {seen[idx]}")
        seen[idx] = lineno
        stamp = None
        if cells.get("stamp_ns"):
            stamp = as_int("stamp_ns")
        if stamp is None:
            stamp = int(round(idx * 1e9 / info.rate_hz))
        vals: dict[str, float | None] = {}
        for col in _FLOAT_COLUMNS:
            s = cells.get(col, "")
            if not s:
                vals[col] = None
                continue
            try:
                v = float(s)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                bad(col, "expected a finite number")
            vals[col] = v
        illum = cells.get("illumination") or None
        if illum is not None and illum not in ILLUMINATIONS:
            bad("illumination", f"expected one of {list(ILLUMINATIONS)}")
        extra = {h: c for h, c in cells.items() if h not in FRAME_COLUMNS}
        frames.append(FrameRecord(index=idx, stamp_ns=stamp, illumination=illum, extra=extra,
                                  **vals))
    frames.sort(key=lambda f: f.index)
    for a, b in zip(frames, frames[1:]):
        if b.stamp_ns < a.stamp_ns:
            raise RunFormatError(f"{file}: stamp_ns goes backwards from index {a.index} "
                                 f"({a.stamp_ns}) to index {b.index} ({b.stamp_ns})")
    return frames


# ---------------------------------------------------------------------------------------------
# per-frame files
# ---------------------------------------------------------------------------------------------
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_layout_error(data: bytes, w: int, h: int) -> str | None:
    """What is wrong with a PNG's chunk layout, checked before decoding: every chunk must fit
    in the file and the size must be the calibration's. (OpenCV spends ~16 s on a 94-byte PNG
    whose IDAT claims 3 GB, and allocates what a forged IHDR says: found by
    tests/fuzz/fuzz_runfolder.py.)"""
    if not data:
        return None                                  # "not a readable image" below
    if not data.startswith(_PNG_SIGNATURE):
        return "not a PNG file (the run format stores PNG images)"
    pos = len(_PNG_SIGNATURE)
    first = True
    while pos + 12 <= len(data):
        n = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        if n > len(data) - pos - 12:
            return f"corrupt PNG: {kind!r} chunk of {n} bytes runs past the end of the file"
        if first:
            if kind != b"IHDR" or n != 13:
                return "corrupt PNG: it does not start with an IHDR chunk"
            pw = int.from_bytes(data[pos + 8:pos + 12], "big")
            ph = int.from_bytes(data[pos + 12:pos + 16], "big")
            if (pw, ph) != (w, h):
                return f"image is {pw}x{ph}, run.toml says {w}x{h}"
            first = False
        if kind == b"IEND":
            return None
        pos += 12 + n
    return "corrupt PNG: cut short (no IEND chunk)"


def _read_png(file: Path, depth: bool, size: tuple[int, int]) -> np.ndarray | None:
    """A colour PNG as HxWx3 uint8 BGR, or a depth PNG as HxW uint16; None if the file is
    missing; RunFormatError if it is unreadable or of the wrong kind or size."""
    try:
        data = np.fromfile(file, dtype=np.uint8)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise RunFormatError(f"{file}: cannot read: {exc}") from None
    w, h = size
    bad = _png_layout_error(data.tobytes(), w, h)
    if bad:
        raise RunFormatError(f"{file}: {bad}")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise RunFormatError(f"{file}: not a readable image (corrupt or empty)")
    if depth:
        if img.ndim != 2 or img.dtype != np.uint16:
            raise RunFormatError(f"{file}: depth must be a 16-bit single-channel PNG, got "
                                 f"{img.dtype} with shape {img.shape}")
    else:
        if img.dtype != np.uint8:
            raise RunFormatError(f"{file}: colour image must be 8-bit, got {img.dtype}")
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        elif img.shape[2] != 3:
            raise RunFormatError(f"{file}: expected 1, 3 or 4 channels, got {img.shape[2]}")
    if img.shape[0] != h or img.shape[1] != w:
        raise RunFormatError(f"{file}: image is {img.shape[1]}x{img.shape[0]}, run.toml says "
                             f"{w}x{h}")
    return np.ascontiguousarray(img)


def _read_laser(file: Path, geom: LaserGeometry) -> np.ndarray | None:
    try:
        text = file.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise RunFormatError(f"{file}: cannot read: {exc}") from None
    lines = [ln.strip() for ln in text.split("\n")]
    if len(lines) == geom.beams + 1 and lines[-1] == "":
        lines.pop()                      # the final newline
    if len(lines) != geom.beams:
        n = text.count("\n") + (0 if not text or text.endswith("\n") else 1)
        raise RunFormatError(f"{file}: {n} lines, run.toml says {geom.beams} beams "
                             f"(one range per line, empty line = no return)")
    out = np.full(geom.beams, np.nan, dtype=np.float32)
    for i, s in enumerate(lines):
        if not s:
            continue
        try:
            v = float(s)
        except ValueError:
            raise RunFormatError(f"{file}: line {i + 1}: not a range in metres: {s!r}") from None
        if v < 0:
            raise RunFormatError(f"{file}: line {i + 1}: negative range {s!r}")
        out[i] = v if math.isfinite(v) else np.nan
    return out


def _read_truth(file: Path) -> list[dict] | None:
    try:
        text = file.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise RunFormatError(f"{file}: cannot read: {exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RunFormatError(f"{file}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("obstacles"), list):
        raise RunFormatError(f"{file}: must be an object with an 'obstacles' list")
    out = []
    for n, ob in enumerate(doc["obstacles"]):
        where = f"{file}: obstacles[{n}]"
        if not isinstance(ob, dict):
            raise RunFormatError(f"{where} must be an object")
        missing = [k for k in _OBSTACLE_REQUIRED if k not in ob]
        if missing:
            raise RunFormatError(f"{where} is missing {missing}")
        o = dict(ob)
        o["id"] = str(o["id"])
        if not isinstance(o["class"], str) or not o["class"]:
            raise RunFormatError(f"{where}: 'class' must be a non-empty string")
        o.setdefault("z_m", 0.0)
        o.setdefault("yaw_deg", 0.0)
        for k in ("x_m", "y_m", "z_m", "length_m", "width_m", "yaw_deg", "height_m"):
            if k not in o:
                continue
            v = o[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise RunFormatError(f"{where}: '{k}' must be a finite number, got {v!r}")
            if k in ("length_m", "width_m", "height_m") and v < 0:
                raise RunFormatError(f"{where}: '{k}' must be >= 0, got {v!r}")
            o[k] = float(v)
        out.append(o)
    return out


# ---------------------------------------------------------------------------------------------
# reader
# ---------------------------------------------------------------------------------------------
class RunReader:
    """A run folder, validated on open (run.toml and frames.csv); per-frame files are read and
    checked when asked for. ``i`` is a position in :attr:`frames`, not a file index."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.info: RunInfo = _parse_run_toml(self.path)
        self.warnings: list[str] = []       # what was forgiven (a torn last line)
        self.frames: list[FrameRecord] = _parse_frames(self.info, self.warnings)

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        return (f"RunReader({str(self.path)!r}: {self.info.name}, {len(self)} frames, "
                f"sensors {list(self.info.sensors)})")

    def _frame(self, i: int) -> FrameRecord:
        if not -len(self.frames) <= i < len(self.frames):
            raise IndexError(f"frame position {i} out of range (run has {len(self.frames)})")
        return self.frames[i]

    def file(self, i: int, sub: str, ext: str) -> Path:
        """Path of a per-frame file, e.g. ``file(i, 'stereo/left', 'png')``."""
        return self.path / sub / f"{_name(self._frame(i).index)}.{ext}"

    def stereo(self, i: int) -> StereoFrame | None:
        cal = self.info.stereo
        if cal is None:
            return None
        fr = self._frame(i)
        size = (cal.camera.width, cal.camera.height)
        left = _read_png(self.file(i, "stereo/left", "png"), False, size)
        right = _read_png(self.file(i, "stereo/right", "png"), False, size)
        if left is None or right is None:
            return None
        return StereoFrame(stamp_ns=fr.stamp_ns, seq=fr.index, left=left, right=right,
                           calib=cal, illumination=fr.illumination or "day")

    def rgbd(self, i: int) -> DepthFrame | None:
        cal = self.info.rgbd
        if cal is None:
            return None
        fr = self._frame(i)
        size = (cal.camera.width, cal.camera.height)
        color = _read_png(self.file(i, "rgbd/color", "png"), False, size)
        counts = _read_png(self.file(i, "rgbd/depth", "png"), True, size)
        if color is None or counts is None:
            return None
        depth = counts.astype(np.float32) * np.float32(cal.depth_unit_m)
        return DepthFrame(stamp_ns=fr.stamp_ns, seq=fr.index, color=color, depth_m=depth,
                          calib=cal)

    def laser(self, i: int) -> LaserScan | None:
        geom = self.info.laser
        if geom is None:
            return None
        fr = self._frame(i)
        ranges = _read_laser(self.file(i, "laser", "csv"), geom)
        if ranges is None:
            return None
        return LaserScan(stamp_ns=fr.stamp_ns, seq=fr.index, ranges_m=ranges, geometry=geom)

    def vehicle(self, i: int) -> VehicleState:
        fr = self._frame(i)
        z = lambda v: 0.0 if v is None else v  # noqa: E731
        return VehicleState(stamp_ns=fr.stamp_ns, seq=fr.index, speed_mps=z(fr.speed_mps),
                            yaw_rate_radps=z(fr.yaw_rate_radps), roll_rad=z(fr.roll_rad),
                            pitch_rad=z(fr.pitch_rad), yaw_rad=z(fr.yaw_rad))

    def truth(self, i: int) -> list[dict] | None:
        """The frame's obstacles (id and class as strings, numbers as floats, z_m and yaw_deg
        defaulted to 0), or None when the frame has no truth file (it is not scored)."""
        return _read_truth(self.file(i, "truth", "json"))

    def validate(self, progress=None) -> None:
        """Read every per-frame file once (raises RunFormatError on the first bad one)."""
        for i in range(len(self)):
            self.stereo(i), self.rgbd(i), self.laser(i), self.truth(i)
            if progress:
                progress(i + 1, len(self))


# ---------------------------------------------------------------------------------------------
# writer
# ---------------------------------------------------------------------------------------------
def _mount_dict(m: Mount) -> dict:
    return {k: float(getattr(m, k)) for k in _MOUNT_KEYS}


def _pinhole_dict(c: PinholeCalibration) -> dict:
    return {"width": int(c.width), "height": int(c.height), "fx": float(c.fx),
            "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy)}


_RUN_ENTRIES = ("run.toml", "frames.csv", "stereo", "rgbd", "laser", "truth")


class RunWriter:
    """Writes a run folder. ``run.toml`` is written at once; each :meth:`write_frame` writes the
    frame's files first and then appends and flushes its ``frames.csv`` row, so a crash loses at
    most the frame being written. ``extra_run`` keys go into the ``[run]`` table (for example
    ``{"scored_zone": {"x_min_m": 2, "x_max_m": 12}}``)."""

    def __init__(self, path: str | os.PathLike, name: str, rate_hz: float = 10.0,
                 stereo: StereoCalibration | None = None, rgbd: DepthCalibration | None = None,
                 laser: LaserGeometry | None = None, extra_run: dict | None = None,
                 overwrite: bool = False):
        self.path = Path(path)
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        if self.path.exists() and not self.path.is_dir():
            raise RunFormatError(f"{self.path}: exists and is not a folder")
        if self.path.is_dir() and any(self.path.iterdir()):
            if not overwrite:
                raise RunFormatError(f"{self.path}: folder is not empty; refusing to overwrite "
                                     f"(pass overwrite=True)")
            for entry in _RUN_ENTRIES:    # only what a run folder holds; nothing else is touched
                p = self.path / entry
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                elif p.exists() or p.is_symlink():
                    p.unlink()
        self.path.mkdir(parents=True, exist_ok=True)
        self.name, self.rate_hz = name, float(rate_hz)
        self.stereo_calib, self.rgbd_calib, self.laser_geom = stereo, rgbd, laser

        run: dict[str, Any] = {"name": name, "rate_hz": float(rate_hz)}
        run.update(extra_run or {})
        doc: dict[str, Any] = {"run": run}
        if stereo is not None:
            doc["stereo"] = {**_pinhole_dict(stereo.camera), "baseline_m": float(stereo.baseline_m),
                             "mount": _mount_dict(stereo.mount)}
            for sub in ("stereo/left", "stereo/right"):
                (self.path / sub).mkdir(parents=True, exist_ok=True)
        if rgbd is not None:
            doc["rgbd"] = {**_pinhole_dict(rgbd.camera), "depth_unit_m": float(rgbd.depth_unit_m),
                           "mount": _mount_dict(rgbd.mount)}
            for sub in ("rgbd/color", "rgbd/depth"):
                (self.path / sub).mkdir(parents=True, exist_ok=True)
        if laser is not None:
            doc["laser"] = {"angle_min_deg": float(laser.angle_min_deg),
                            "angle_step_deg": float(laser.angle_step_deg),
                            "beams": int(laser.beams), "range_max_m": float(laser.range_max_m),
                            "mount": _mount_dict(laser.mount)}
            (self.path / "laser").mkdir(exist_ok=True)
        with open(self.path / "run.toml", "wb") as f:
            tomli_w.dump(doc, f)
        self._columns: list[str] = list(FRAME_COLUMNS)
        self._rows: list[dict[str, str]] = []
        self._indices: set[int] = set()
        self._csv = open(self.path / "frames.csv", "w", newline="", encoding="utf-8")
        self._write_header()
        self._closed = False

    # -- frames.csv --------------------------------------------------------------------------
    def _write_header(self) -> None:
        csv.writer(self._csv).writerow(self._columns)
        self._csv.flush()

    def _rewrite_csv(self) -> None:
        """A new extra column appeared: rewrite the whole file with the wider header."""
        self._csv.close()
        tmp = self.path / "frames.csv.tmp"
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(self._columns)
            for r in self._rows:
                w.writerow([r.get(c, "") for c in self._columns])
        os.replace(tmp, self.path / "frames.csv")
        self._csv = open(self.path / "frames.csv", "a", newline="", encoding="utf-8")

    # -- files -------------------------------------------------------------------------------
    @staticmethod
    def _write_png(file: Path, img: np.ndarray) -> None:
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise ValueError(f"{file}: cv2 could not encode the image")
        buf.tofile(file)

    @staticmethod
    def _check_image(what: str, img: np.ndarray, cal: PinholeCalibration) -> None:
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 \
                or img.shape[2] != 3:
            raise ValueError(f"{what} must be HxWx3 uint8 BGR, got "
                             f"{getattr(img, 'dtype', type(img))} {getattr(img, 'shape', '')}")
        if img.shape[:2] != (cal.height, cal.width):
            raise ValueError(f"{what} is {img.shape[1]}x{img.shape[0]}, the run's calibration "
                             f"says {cal.width}x{cal.height}")

    def write_frame(self, index: int, stamp_ns: int, vehicle: VehicleState | None = None,
                    stereo: StereoFrame | None = None, rgbd: DepthFrame | None = None,
                    laser: LaserScan | None = None, truth: list[dict] | None = None,
                    illumination: str | None = None,
                    extra_columns: dict | None = None) -> None:
        if self._closed:
            raise ValueError("RunWriter is closed")
        index = int(index)
        if index < 0 or index in self._indices:
            raise ValueError(f"frame index {index} is negative or already written")
        if illumination is not None and illumination not in ILLUMINATIONS:
            raise ValueError(f"illumination must be one of {ILLUMINATIONS}, got {illumination!r}")
        if truth is not None:
            for k, o in enumerate(truth):
                missing = [key for key in _OBSTACLE_REQUIRED if not isinstance(o, dict)
                           or key not in o]
                if missing:
                    raise ValueError(f"truth[{k}] of frame {index} is missing {missing}")
        n = _name(index)
        if stereo is not None:
            if self.stereo_calib is None:
                raise ValueError("stereo frame given but the run was opened without stereo")
            cam = self.stereo_calib.camera
            self._check_image("stereo left", stereo.left, cam)
            self._check_image("stereo right", stereo.right, cam)
            self._write_png(self.path / "stereo/left" / f"{n}.png", stereo.left)
            self._write_png(self.path / "stereo/right" / f"{n}.png", stereo.right)
            if illumination is None and stereo.illumination != "day":
                illumination = stereo.illumination
        if rgbd is not None:
            if self.rgbd_calib is None:
                raise ValueError("rgbd frame given but the run was opened without rgbd")
            cam = self.rgbd_calib.camera
            self._check_image("rgbd color", rgbd.color, cam)
            d = np.asarray(rgbd.depth_m, dtype=np.float64)
            if d.shape != (cam.height, cam.width):
                raise ValueError(f"rgbd depth has shape {d.shape}, expected "
                                 f"{(cam.height, cam.width)}")
            counts = np.rint(np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)
                             / self.rgbd_calib.depth_unit_m)
            # no reading (0, NaN, negative) and depths the 16-bit PNG cannot hold become 0
            counts[(counts < 0) | (counts > 65535)] = 0
            self._write_png(self.path / "rgbd/color" / f"{n}.png", rgbd.color)
            self._write_png(self.path / "rgbd/depth" / f"{n}.png", counts.astype(np.uint16))
        if laser is not None:
            if self.laser_geom is None:
                raise ValueError("laser scan given but the run was opened without a laser")
            r = np.asarray(laser.ranges_m, dtype=np.float32).ravel()
            if r.size != self.laser_geom.beams:
                raise ValueError(f"laser scan has {r.size} beams, the run says "
                                 f"{self.laser_geom.beams}")
            lines = ["" if not np.isfinite(v) else str(v) for v in r]  # shortest exact float32
            (self.path / "laser" / f"{n}.csv").write_text("\n".join(lines) + "\n")
        if truth is not None:
            (self.path / "truth").mkdir(exist_ok=True)
            (self.path / "truth" / f"{n}.json").write_text(
                json.dumps({"obstacles": list(truth)}, indent=1))

        row = {"index": str(index), "stamp_ns": str(int(stamp_ns))}
        if vehicle is not None:
            for col in _FLOAT_COLUMNS:
                row[col] = repr(float(getattr(vehicle, col)))
        if illumination is not None:
            row["illumination"] = illumination
        for k, v in (extra_columns or {}).items():
            k = str(k)
            if k in FRAME_COLUMNS:
                raise ValueError(f"extra column {k!r} is a standard frames.csv column")
            row[k] = "" if v is None else str(v)
        new_cols = [k for k in row if k not in self._columns]
        self._rows.append(row)
        self._indices.add(index)
        if new_cols:
            self._columns.extend(new_cols)
            self._rewrite_csv()
        else:
            csv.writer(self._csv).writerow([row.get(c, "") for c in self._columns])
            self._csv.flush()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._csv.close()

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
