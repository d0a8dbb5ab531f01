"""Scoring, as docs/run-format.md "Scoring" defines it, and a runner over a run folder.

- The scored zone: ``x_min_m <= x <= x_max_m`` (vehicle frame, :func:`drivers.runfolder.
  scored_zone_for`) and, laterally, inside the horizontal field of view of the run's stereo
  camera (else its RGB-D camera), a wedge from the camera's mount position along its yaw.
- An obstacle is in the zone when its footprint centre is; it is detected in a frame when at
  least one occupied cell centre lies within 0.5 m of its footprint (a rectangle length x width
  turned by yaw_deg, counter-clockwise from x).
- A false-positive cell is an occupied cell centre in the zone farther than 0.5 m from every
  obstacle's footprint (every truth obstacle, in the zone or not).
- Only frames with a truth file are scored; every frame's pipeline time is counted.

The scoring functions are pure; :func:`evaluate_run` runs a pipeline and the grid fusion over a
run in order, as the daemon does, and scores the occupied cells.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from drivers.runfolder import RunInfo, RunReader, scored_zone_for
from hal.errors import ConfigError, RunFormatError

__all__ = ["Zone", "ObstacleScore", "FrameScore", "Aggregate", "zone_for_run",
           "footprint_distance", "score_frame", "evaluate_run", "format_table", "MATCH_M"]

MATCH_M = 0.5        # the contract's 0.5 m, for detection and for false positives


# ---------------------------------------------------------------------------------------------
# zone
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Zone:
    x_min_m: float
    x_max_m: float
    half_fov_rad: float          # lateral: a wedge of +-half_fov about yaw_rad from the apex
    apex_x_m: float
    apex_y_m: float
    yaw_rad: float = 0.0         # the camera's yaw (0 = looking straight ahead)

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """Boolean mask of the points (N, 2) inside the zone."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        bearing = np.arctan2(y - self.apex_y_m, x - self.apex_x_m) - self.yaw_rad
        bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
        return (x >= self.x_min_m) & (x <= self.x_max_m) & (np.abs(bearing) <= self.half_fov_rad)

    def to_dict(self) -> dict:
        return {"x_min_m": self.x_min_m, "x_max_m": self.x_max_m,
                "half_fov_deg": round(math.degrees(self.half_fov_rad), 3),
                "apex_x_m": self.apex_x_m, "apex_y_m": self.apex_y_m,
                "yaw_deg": round(math.degrees(self.yaw_rad), 3)}


def zone_for_run(info: RunInfo) -> Zone:
    """The run's scored zone: its x range (run-format defaults) and its camera's FOV wedge.

    A run with no camera has no scored zone unless it gives ``[run] scored_zone``; then the
    laser's angular span stands in for the camera's field of view (a project extension)."""
    x_min, x_max = scored_zone_for(info)
    cal = info.stereo or info.rgbd
    if cal is not None:
        cam, mount = cal.camera, cal.mount
        half = math.atan(cam.width / (2.0 * cam.fx))
        return Zone(x_min, x_max, half, mount.x_m, mount.y_m, math.radians(mount.yaw_deg))
    geom = info.laser
    if geom is None:
        raise RunFormatError(f"{info.path / 'run.toml'}: run has no sensor to define the "
                             f"scored zone's lateral extent")
    span = abs(geom.angle_step_deg) * max(geom.beams - 1, 0)
    lo = min(geom.angle_min_deg, geom.angle_min_deg + geom.angle_step_deg * (geom.beams - 1))
    centre = lo + span / 2 + geom.mount.yaw_deg
    return Zone(x_min, x_max, math.radians(min(span / 2, 180.0)), geom.mount.x_m,
                geom.mount.y_m, math.radians(centre))


# ---------------------------------------------------------------------------------------------
# one frame
# ---------------------------------------------------------------------------------------------
def footprint_distance(points_xy: np.ndarray, obstacle: dict) -> np.ndarray:
    """Distance (N,) from each point to the obstacle's footprint rectangle (0 inside it)."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    yaw = math.radians(float(obstacle.get("yaw_deg", 0.0)))
    c, s = math.cos(yaw), math.sin(yaw)
    dx = p[:, 0] - float(obstacle["x_m"])
    dy = p[:, 1] - float(obstacle["y_m"])
    u = c * dx + s * dy                    # along the obstacle's length
    v = -s * dx + c * dy                   # along its width
    qu = np.maximum(np.abs(u) - float(obstacle["length_m"]) / 2.0, 0.0)
    qv = np.maximum(np.abs(v) - float(obstacle["width_m"]) / 2.0, 0.0)
    return np.hypot(qu, qv)


@dataclass(frozen=True)
class ObstacleScore:
    id: str
    cls: str
    in_zone: bool
    detected: bool               # only meaningful when in_zone
    nearest_cell_m: float | None  # distance from the footprint to the nearest occupied cell


@dataclass(frozen=True)
class FrameScore:
    obstacles: tuple[ObstacleScore, ...]
    occupied_cells: int          # all occupied cells given
    cells_in_zone: int
    fp_cells: int

    @property
    def scored_obstacles(self) -> tuple[ObstacleScore, ...]:
        return tuple(o for o in self.obstacles if o.in_zone)

    @property
    def false_positive(self) -> bool:
        return self.fp_cells > 0


def score_frame(cells_xy: np.ndarray, truth: list[dict], zone: Zone,
                cell_m: float = 0.1) -> FrameScore:
    """Score one frame's occupied cell centres (M, 2) against its truth obstacles.

    ``cell_m`` is the grid's cell size; cells are judged by their centres, as the contract
    says, so it does not change the result (kept for callers that report areas)."""
    cells = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
    cells = cells[np.all(np.isfinite(cells), axis=1)]
    in_zone_cells = zone.contains(cells)
    near_any = np.zeros(len(cells), dtype=bool)
    scores = []
    for ob in truth:
        d = footprint_distance(cells, ob)
        near = d <= MATCH_M + 1e-9
        near_any |= near
        centre_in = bool(zone.contains(np.array([[ob["x_m"], ob["y_m"]]]))[0])
        scores.append(ObstacleScore(
            id=str(ob["id"]), cls=str(ob["class"]), in_zone=centre_in,
            detected=bool(centre_in and near.any()),
            nearest_cell_m=float(d.min()) if len(d) else None))
    fp = int(np.count_nonzero(in_zone_cells & ~near_any))
    return FrameScore(obstacles=tuple(scores), occupied_cells=len(cells),
                      cells_in_zone=int(np.count_nonzero(in_zone_cells)), fp_cells=fp)


# ---------------------------------------------------------------------------------------------
# over a run
# ---------------------------------------------------------------------------------------------
def _ratio(a: int, b: int) -> float | None:
    return None if b == 0 else a / b


@dataclass
class _ClassTally:
    obstacle_frames: int = 0
    detected_obstacle_frames: int = 0
    seen: set = field(default_factory=set)
    detected: set = field(default_factory=set)

    def result(self) -> dict:
        return {"obstacle_frames": self.obstacle_frames,
                "detected_obstacle_frames": self.detected_obstacle_frames,
                "recall": _ratio(self.detected_obstacle_frames, self.obstacle_frames),
                "obstacles": len(self.seen), "obstacles_detected": len(self.detected)}


class Aggregate:
    """Adds up frame scores. ``add(i, None, ms)`` counts a frame's time but does not score it
    (a frame without truth); distinct obstacles are told apart by truth ``id``."""

    def __init__(self):
        self.frames = 0
        self.false_positive_frames = 0
        self.fp_cells = 0
        self.all = _ClassTally()
        self.per_class: dict[str, _ClassTally] = {}
        self.ms: list[float] = []
        self.missed: list[tuple[int, str]] = []     # (frame index, obstacle id) not detected
        self.fp_frame_indices: list[int] = []
        self.fp_frames_clear = 0      # FP frames with no obstacle in the zone: false stops

    def add(self, frame_index: int, score: FrameScore | None, ms: float | None = None) -> None:
        if ms is not None:
            self.ms.append(float(ms))
        if score is None:
            return
        self.frames += 1
        self.fp_cells += score.fp_cells
        self.false_positive_frames += int(score.false_positive)
        if score.false_positive:
            self.fp_frame_indices.append(int(frame_index))
            self.fp_frames_clear += int(not score.scored_obstacles)
        for ob in score.scored_obstacles:
            for t in (self.all, self.per_class.setdefault(ob.cls, _ClassTally())):
                t.obstacle_frames += 1
                t.seen.add(ob.id)
                if ob.detected:
                    t.detected_obstacle_frames += 1
                    t.detected.add(ob.id)
            if not ob.detected:
                self.missed.append((frame_index, ob.id))

    def result(self) -> dict:
        ms = np.asarray(self.ms, dtype=np.float64)
        timing = (lambda q: round(float(np.percentile(ms, q)), 3)) if ms.size else (lambda q: None)
        return {
            "frames": self.frames,
            **self.all.result(),
            "false_positive_frames": self.false_positive_frames,
            "false_positive_frame_indices": list(self.fp_frame_indices),
            # of those, frames with no obstacle in the zone at all (where a false positive
            # is a false stop; elsewhere it sits beside a real obstacle)
            "false_positive_frames_clear": self.fp_frames_clear,
            "fp_cells": self.fp_cells,
            "fp_cells_per_frame": _ratio(self.fp_cells, self.frames),
            "per_class": {c: t.result() for c, t in sorted(self.per_class.items())},
            "ms_per_frame": round(float(ms.mean()), 3) if ms.size else None,
            "ms_p50": timing(50),
            "ms_p99": timing(99),
            "timed_frames": int(ms.size),
        }


def _needs(pipe) -> tuple[list[tuple[str, ...]], bool]:
    """(alternatives, any): the sensor sets the pipeline can run on; any=True when one of them
    is enough (a fused pipeline), else all of the single set is required."""
    parts = getattr(pipe, "parts", None)
    if parts is not None:
        return [tuple(p.requires) for p in parts], True
    return [tuple(pipe.requires)], False


def _check_sensors(pipe, name: str, info: RunInfo) -> set[str]:
    """The run's sensors the pipeline will use; ConfigError when it cannot run on this run."""
    have = set(info.sensors) | {"vehicle"}
    alts, any_ = _needs(pipe)
    have_txt = ", ".join(info.sensors) or "no sensors"
    if any_:
        ok = [a for a in alts if set(a) <= have]
        if not ok:
            want = " or ".join("+".join(a) for a in alts) or "nothing (no parts configured)"
            raise ConfigError(f"pipeline {name!r} needs {want}, run {info.name!r} has only "
                              f"{have_txt}")
        return set().union(*map(set, ok)) - {"vehicle"}
    missing = [s for s in alts[0] if s not in have]
    if missing:
        raise ConfigError(f"pipeline {name!r} needs {', '.join(alts[0])}, run {info.name!r} "
                          f"has only {have_txt}")
    return set(alts[0]) - {"vehicle"}


def evaluate_run(path: str | os.PathLike, pipeline: str, config=None,
                 progress: Callable[[int, int], None] | None = None) -> dict:
    """Run ``pipeline`` over every frame of the run at ``path`` in order, fuse its points into
    the grid as the daemon does, and score the occupied cells of every frame with truth.

    ``config``: a Config, a path to a config file, or None for the defaults. A frame whose
    required sensor file is missing feeds the grid no points (as a stale sensor would)."""
    from appliance.config import default_config, load_config
    from appliance.fusion import GridFusion
    from appliance.perception import SensorInputs, make_pipeline

    reader = RunReader(path)
    info = reader.info
    if config is None:
        cfg = default_config()
    elif isinstance(config, (str, os.PathLike)):
        cfg = load_config(config)
    else:
        cfg = config
    zone = zone_for_run(info)
    pipe = make_pipeline(pipeline, cfg)
    try:
        sensors = _check_sensors(pipe, pipeline, info)
        fusion = GridFusion(cfg.grid)
        agg = Aggregate()
        missing_input = 0
        n = len(reader)
        for i in range(n):
            fr = reader.frames[i]
            vehicle = reader.vehicle(i)
            data = {s: getattr(reader, s)(i) for s in sensors}
            inputs = SensorInputs(stamp_ns=fr.stamp_ns, vehicle=vehicle, **data)
            ms = None
            if pipe.missing(inputs) or (sensors and all(v is None for v in data.values())):
                missing_input += 1
                points = np.zeros((0, 2), np.float32)
            else:
                t0 = time.perf_counter_ns()
                det = pipe.process(inputs)
                ms = (time.perf_counter_ns() - t0) / 1e6
                points = det.points_xy
            cells = fusion.update(points, vehicle, fr.stamp_ns)
            truth = reader.truth(i)
            score = None if truth is None else score_frame(cells, truth, zone, cfg.grid.cell_m)
            agg.add(fr.index, score, ms)
            if progress is not None:
                progress(i + 1, n)
    finally:
        pipe.close()
    out = agg.result()
    out.update({"run": info.name, "path": str(Path(path)), "pipeline": pipeline,
                "frames_total": n, "frames_missing_input": missing_input,
                "zone": zone.to_dict(), "config": getattr(cfg, "source", None)})
    return out


def _fmt(v, pct: bool = False) -> str:
    if v is None:
        return "-"
    if pct:
        return f"{100 * v:.1f}%"
    return f"{v:.2f}" if isinstance(v, float) else str(v)


def format_table(result: dict) -> str:
    """A human-readable per-class table of an :func:`evaluate_run` (or Aggregate) result."""
    head = []
    if "run" in result:
        head.append(f"run {result['run']}  pipeline {result.get('pipeline', '?')}  "
                    f"scored frames {result['frames']}/{result.get('frames_total', '?')}")
    cols = ("class", "obstacle-frames", "detected", "recall", "obstacles det/all")
    rows = []
    for cls, r in result.get("per_class", {}).items():
        rows.append((cls, str(r["obstacle_frames"]), str(r["detected_obstacle_frames"]),
                     _fmt(r["recall"], pct=True),
                     f"{r['obstacles_detected']}/{r['obstacles']}"))
    rows.append(("all", str(result["obstacle_frames"]), str(result["detected_obstacle_frames"]),
                 _fmt(result["recall"], pct=True),
                 f"{result['obstacles_detected']}/{result['obstacles']}"))
    widths = [max(len(c), *(len(r[k]) for r in rows)) for k, c in enumerate(cols)]
    line = lambda r: "  ".join(s.ljust(w) if k == 0 else s.rjust(w)  # noqa: E731
                               for k, (s, w) in enumerate(zip(r, widths)))
    table = [line(cols), "  ".join("-" * w for w in widths)]
    table += [line(r) for r in rows[:-1]]
    if len(rows) > 1:
        table.append("  ".join("-" * w for w in widths))
    table.append(line(rows[-1]))
    tail = [f"false-positive frames {result['false_positive_frames']}/{result['frames']}  "
            f"fp cells/frame {_fmt(result['fp_cells_per_frame'])}",
            f"time per frame {_fmt(result['ms_per_frame'])} ms  "
            f"(p50 {_fmt(result.get('ms_p50'))}, p99 {_fmt(result.get('ms_p99'))})"]
    return "\n".join(head + table + tail)
