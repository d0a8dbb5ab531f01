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

import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from drivers.runfolder import RunInfo, RunReader, scored_zone_for
from hal.errors import ConfigError, RunFormatError

log = logging.getLogger("fieldguard.eval")

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


def _sync_model_updates(pipes, timeout_s: float = 600.0) -> None:
    """Wait for every novelty model's background update to finish (offline evaluation only:
    the box itself never waits). Without it a run's score depended on thread timing."""
    for p in pipes:
        nd = getattr(p, "novelty", None)
        u = getattr(nd, "updater", None) if nd is not None else None
        if u is not None and not u.wait_idle(timeout_s):
            raise RunFormatError(f"the novelty model's update did not finish in {timeout_s:.0f} s")


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


# the box's perception for each sensor when no pipeline is named and no config chooses
DEFAULT_PIPELINES = {"stereo": "stereo-novelty", "rgbd": "rgbd", "laser": "laser"}


def default_pipelines(info: RunInfo, cfg=None, configured: bool = False) -> list[str]:
    """What ``fieldguard eval RUN`` runs without ``--pipeline``: with a config file that sets
    ``[perception] pipelines`` (to anything but the built-in default, the laser alone), those
    of them the run has the sensors for; otherwise (or when none of them fits) the box's
    default perception for each sensor the run has: stereo-novelty for stereo, rgbd for RGB-D,
    laser for a laser."""
    from appliance.config import PerceptionConfig
    from appliance.perception import pipeline_class
    have = set(info.sensors) | {"vehicle"}
    if configured and cfg is not None and \
            tuple(cfg.perception.pipelines) != tuple(PerceptionConfig().pipelines):
        names = []
        for n in cfg.perception.pipelines:
            if n == "fused":
                continue
            if set(getattr(pipeline_class(n), "requires", ())) <= have:
                names.append(n)
        if names:
            return names
    names = [DEFAULT_PIPELINES[s] for s in ("stereo", "rgbd", "laser") if s in info.sensors]
    if not names:
        raise ConfigError(f"run {info.name!r} has no sensor a pipeline can use")
    return names


def _rect_intersects(ob: dict, rect: dict, curvature_1pm=0.0,
                     front_x_m: float = 0.0) -> bool:
    """Does the obstacle's footprint (length x width turned by yaw_deg) meet the zone rectangle
    {x_min_m, x_max_m, half_width_m}? (The box's own zone test, appliance/zones.py.) With a
    ``curvature_1pm`` the zone is bent along that arc from ``front_x_m`` (``[zones]
    follow_turn``), or a zones.PathBend (``follow_path``): the footprint is taken into the
    path's frame."""
    from appliance.zones import footprint_meets, heading_to_path_frame, to_path_frame
    xy = np.array([[float(ob["x_m"]), float(ob["y_m"])]])
    yaw = math.radians(float(ob.get("yaw_deg", 0.0)))
    if curvature_1pm:
        yaw = float(heading_to_path_frame(xy, yaw, curvature_1pm)[0])
        xy = to_path_frame(xy, curvature_1pm, front_x_m)
    return footprint_meets(float(xy[0, 0]), float(xy[0, 1]), float(ob["length_m"]),
                           float(ob["width_m"]), rect, yaw)


def decision_record(index: int, stamp_ns: int, out, picture, rects, cause: str) -> dict:
    """One line of ``fieldguard eval --out`` (docs/run-format.md "The box's decisions")."""
    cells = np.asarray(picture.cells_xy, dtype=np.float64).reshape(-1, 2)
    rec = {
        "index": int(index), "stamp_ns": int(stamp_ns),
        "cells": [[round(float(x), 3), round(float(y), 3)] for x, y in cells],
        "state": out.state.value, "reason": out.reason,
        "stop_zone": {k: round(float(v), 3) for k, v in rects[0].items()},
        "slow_zone": {k: round(float(v), 3) for k, v in rects[1].items()},
        "objects": [
            {"id": t.id, "x_m": round(t.x_m, 3), "y_m": round(t.y_m, 3),
             "length_m": round(t.length_m, 3), "width_m": round(t.width_m, 3),
             "height_m": round(t.height_m, 3), "vx_mps": round(t.vx_mps, 3),
             "vy_mps": round(t.vy_mps, 3), "confidence": round(t.confidence, 4),
             "sources": list(t.sources), "coasting": t.coasting}
            for t in picture.objects],
        # beyond the contract: what the state is for (boot, fault, no-picture, obstacle, clear)
        "cause": cause,
    }
    kappa = float(getattr(picture.verdict, "curvature_1pm", 0.0) or 0.0)
    if kappa:   # beyond the contract: the zones were bent along this arc ([zones] follow_turn)
        rec["path_curvature_1pm"] = round(kappa, 5)
    path = getattr(picture.verdict, "path", None)
    if path is not None:   # beyond the contract: the zones were laid along this planned path
        rec["path_xy"] = [[round(float(x), 3), round(float(y), 3)] for x, y in path.path_xy]
    return rec


class _StopTally:
    """false_stop_frames / missed_stop_frames over the scored frames (see evaluate_run)."""

    def __init__(self, hold_off_s: float):
        self.hold_off_ns = int(round(hold_off_s * 1e9))
        self.last_real_ns: int | None = None
        self.stop_frames = self.obstacle_stop_frames = self.fault_stop_frames = 0
        self.stop_zone_frames = 0
        self.false_stop = []
        self.missed_stop = []
        self.path_frames = self.path_detected = 0

    def add(self, index: int, stamp_ns: int, state: str, cause: str, truth, stop_rect,
            slow_rect=None, cells=None, curvature_1pm=0.0) -> None:
        if truth is None:
            return
        bend = (curvature_1pm, stop_rect["x_min_m"])    # the zones as the box bent them
        if slow_rect is not None:     # in the path: the stop and slow zones together
            path = dict(stop_rect, x_max_m=slow_rect["x_max_m"])
            for o in truth:
                if _rect_intersects(o, path, *bend):
                    self.path_frames += 1
                    if cells is not None and len(cells) and \
                            footprint_distance(cells, o).min() <= MATCH_M + 1e-9:
                        self.path_detected += 1
        real = [o for o in truth if _rect_intersects(o, stop_rect, *bend)]
        if real:
            self.last_real_ns = stamp_ns
            self.stop_zone_frames += 1
        stop = state == "STOP"
        if stop:
            self.stop_frames += 1
            if cause == "obstacle":
                self.obstacle_stop_frames += 1
            else:
                self.fault_stop_frames += 1
        if real and not stop:
            self.missed_stop.append(int(index))
        recent = (self.last_real_ns is not None
                  and stamp_ns - self.last_real_ns <= self.hold_off_ns)
        if stop and cause == "obstacle" and not real and not recent:
            self.false_stop.append(int(index))

    def result(self) -> dict:
        return {"false_stop_frames": len(self.false_stop),
                "false_stop_frame_indices": list(self.false_stop),
                "missed_stop_frames": len(self.missed_stop),
                "missed_stop_frame_indices": list(self.missed_stop),
                "stop_zone_frames": self.stop_zone_frames,
                "stop_frames": self.stop_frames,
                "obstacle_stop_frames": self.obstacle_stop_frames,
                "fault_stop_frames": self.fault_stop_frames,
                # obstacle-frames whose footprint meets the stop or slow zone, and of those
                # the detected ones (a cell within 0.5 m), whether the cameras see them or not
                "path_obstacle_frames": self.path_frames,
                "path_detected_obstacle_frames": self.path_detected,
                "path_recall": _ratio(self.path_detected, self.path_frames)}


def evaluate_run(path: str | os.PathLike, pipeline: str | None = None, config=None,
                 progress: Callable[[int, int], None] | None = None,
                 out: str | os.PathLike | None = None) -> dict:
    """Run ``pipeline`` over every frame of the run at ``path`` in order through the box's
    decision core (appliance/decision.py: fusion grid, tracks when ``[tracking] enabled``,
    zones, the safety gate) as the daemon does, and score the obstacle picture (occupied cells)
    of every frame with truth.

    ``pipeline``: a registry name, or None for :func:`default_pipelines`. ``config``: a Config,
    a path to a config file, or None for the defaults. A frame whose required sensor file is
    missing feeds the grid no points and is a fault for the gate (as a stale sensor is).

    The gate sees the run's ``speed_mps``. It boots in STOP and holds STOP for ``[gate]
    hold_off_s`` after the first cycle, as the box does after a start: those frames are STOP
    with cause "boot", which is not an obstacle stop. ``false_stop_frames``: scored frames
    where the gate says STOP for an obstacle (the obstacle verdict or the hold-off after one:
    cause "obstacle"; a boot or fault STOP is not counted) while no truth footprint meets the
    stop-zone rectangle, now or within the hold-off before (the hold-off after a real obstacle
    left is the gate working). ``missed_stop_frames``: scored frames where a truth footprint
    meets the stop-zone rectangle and the state is not STOP.

    ``out``: write one JSON line per frame (every frame, scored or not) as
    docs/run-format.md "The box's decisions" defines."""
    import json

    from appliance.config import default_config, load_config
    from appliance.decision import DecisionCore, decision_name
    from appliance.perception import SensorInputs, make_pipeline
    from appliance.zones import zone_rects

    reader = RunReader(path)
    info = reader.info
    configured = config is not None
    if config is None:
        cfg = default_config()
    elif isinstance(config, (str, os.PathLike)):
        cfg = load_config(config)
    else:
        cfg = config
    zone = zone_for_run(info)
    if pipeline is None:
        from appliance.perception.fused import FusedPipeline
        names = default_pipelines(info, cfg, configured and getattr(cfg, "source", "") not in
                                  ("<defaults>",))
        parts = [make_pipeline(n, cfg) for n in names]
        pipe = parts[0] if len(parts) == 1 else FusedPipeline(parts)
        label = names[0] if len(names) == 1 else "fused(" + "+".join(names) + ")"
    else:
        pipe = make_pipeline(pipeline, cfg)
        label = pipeline
    sink = None
    try:
        sensors = _check_sensors(pipe, label, info)
        core = DecisionCore(cfg)
        agg = Aggregate()
        stops = _StopTally(cfg.gate.hold_off_s)
        missing_input = 0
        lost: list[int] = []
        corrupt: list[tuple[int, str]] = []
        if out is not None:
            sink = open(out, "w", encoding="utf-8")
        n = len(reader)
        parts = getattr(pipe, "parts", None)
        for i in range(n):
            fr = reader.frames[i]
            vehicle = reader.vehicle(i)
            data, broken = {}, None
            for s in sensors:
                try:
                    data[s] = getattr(reader, s)(i)
                except RunFormatError as exc:   # a corrupt file: counted, named, not scored
                    data[s], broken = None, str(exc)
            # a frame with a sensor file missing or corrupt is never scored (the gate still
            # sees it: a fault, as a stale sensor is)
            damaged = broken is not None or any(v is None for v in data.values())
            if broken is not None:
                corrupt.append((fr.index, broken))
                log.warning("frame %d: %s: not scored", fr.index, broken)
            elif damaged:
                lost.append(fr.index)
                log.warning("frame %d: no %s file: not scored", fr.index,
                            "/".join(s for s, v in data.items() if v is None))
            inputs = SensorInputs(stamp_ns=fr.stamp_ns, vehicle=vehicle, **data)
            ms = None
            faults = []
            detections = {}
            absent = [s for s, v in data.items() if v is None]
            if pipe.missing(inputs) or (sensors and len(absent) == len(data)):
                missing_input += 1
                faults.append(f"pipeline {label}: no fresh {', '.join(absent) or 'input'} "
                              f"data")
            else:
                if absent:
                    faults.append(f"no fresh {', '.join(absent)} data")
                t0 = time.perf_counter_ns()
                if parts is not None:      # each part by name, as the loop runs them
                    for p in parts:
                        if not p.missing(inputs):
                            detections[p.name] = p.process(inputs)
                else:
                    detections[label] = pipe.process(inputs)
                ms = (time.perf_counter_ns() - t0) / 1e6
                # offline, the novelty model's background update finishes before the next
                # frame (not timed): the score does not depend on how busy the host was
                _sync_model_updates(parts if parts is not None else [pipe])
            picture = core.perceive(detections, vehicle, fr.stamp_ns)
            gate_out = core.decide(fr.stamp_ns, faults, picture)
            cells = picture.cells_xy
            truth = None if damaged else reader.truth(i)
            score = None if truth is None else score_frame(cells, truth, zone, cfg.grid.cell_m)
            agg.add(fr.index, score, ms)
            rects = zone_rects(vehicle.speed_mps if vehicle is not None else 0.0, cfg.zones)
            stops.add(fr.index, fr.stamp_ns, gate_out.state.value, core.gate.cause, truth,
                      rects[0], rects[1], np.asarray(cells, dtype=np.float64).reshape(-1, 2),
                      picture.verdict.bend)
            if sink is not None:
                sink.write(json.dumps(decision_record(fr.index, fr.stamp_ns, gate_out, picture,
                                                      rects, core.gate.cause),
                                      ensure_ascii=False) + "\n")
            if progress is not None:
                progress(i + 1, n)
        # what the pipelines say about themselves at the end (e.g. rgbd: its class model does
        # not explain the scene, so it decided on geometry alone)
        notes = pipe.notes() if hasattr(pipe, "notes") else {}
        geometry_frames = {p.name: p.geometry_frames for p in (parts or [pipe])
                           if hasattr(p, "geometry_frames")}
    finally:
        pipe.close()
        if sink is not None:
            sink.close()
    res = agg.result()
    res.update(stops.result())
    res.update({"run": info.name, "path": str(Path(path)), "pipeline": label,
                "decision": decision_name(cfg.tracking),
                "frames_total": n, "frames_missing_input": missing_input,
                # frames left out of the score: a sensor file missing, or corrupt (named)
                "frames_missing": len(lost), "frames_missing_indices": lost,
                "frames_corrupt": len(corrupt),
                "frames_corrupt_indices": [k for k, _ in corrupt],
                "frames_corrupt_errors": [e for _, e in corrupt[:20]],
                "run_warnings": list(reader.warnings),
                "pipeline_notes": notes,
                # frames a pipeline with a class model decided on geometry alone (rgbd)
                "geometry_only_frames": geometry_frames,
                "zone": zone.to_dict(), "config": getattr(cfg, "source", None)})
    return res


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
        for key, what in (("missing", "a sensor file missing"), ("corrupt", "a corrupt file")):
            idx = result.get(f"frames_{key}_indices") or []
            if idx:
                shown = ", ".join(map(str, idx[:10])) + (", ..." if len(idx) > 10 else "")
                head.append(f"not scored: {len(idx)} frame(s) with {what} (index {shown})")
        for w in result.get("run_warnings") or []:
            head.append(f"warning: {w}")
        notes = result.get("pipeline_notes") or {}
        if notes and not any(isinstance(v, dict) for v in notes.values()):
            notes = {result.get("pipeline", "?"): notes}        # one pipeline
        for name, d in notes.items():
            for k, v in (d.items() if isinstance(d, dict) else [("", d)]):
                if (k, v) != ("cue", "off"):
                    head.append(f"note: {name}: {v}")
        for name, k in (result.get("geometry_only_frames") or {}).items():
            if k:
                head.append(f"note: {name}: {k}/{result.get('frames_total', '?')} frames "
                            f"decided on geometry alone")
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
    if "false_stop_frames" in result:
        tail.insert(1, f"decision {result.get('decision', '?')}: false-stop frames "
                       f"{result['false_stop_frames']}  missed-stop frames "
                       f"{result['missed_stop_frames']} (of {result['stop_zone_frames']} with "
                       f"an obstacle in the stop zone)  path recall "
                       f"{_fmt(result.get('path_recall'), pct=True)}")
    return "\n".join(head + table + tail)
