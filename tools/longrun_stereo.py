"""Issue #3's long run: the stereo-novelty pipeline in the daemon's loop, closed loop, on a
simulated field driven lane by lane, for 20+ simulated minutes.

    python tools/longrun_stereo.py --out /tmp/longrun [--minutes 20] [--scene stubble-coverage]
        [--seed 0] [--stereo-scale 0.25] [--matcher sgbm] [--config extra.toml] [--every 50]
    python tools/longrun_stereo.py --replot /tmp/longrun        # the PNG again from the CSV

The daemon is built in-process exactly as ``fieldguard run --sim SCENE --config F --fast``
builds it (``sim_config`` + ``Daemon(mode="sim", pace=0)``): simulated stereo pair and vehicle
link on one ManualClock, the 10 Hz loop, the grid, the safety gate. The gate's STOP/SLOW drive
the simulated vehicle, whose safety driver steers round real obstacles it was stopped for
(detours) and overrides a false stop after 10 s (overrides); see drivers/sim/vehicle.py.

Accounting, every cycle, against the simulator's truth (all obstacles, hit ones included):

- collision: the vehicle's footprint reached an obstacle's (counted by the sim vehicle, once
  per obstacle);
- STOP event: a change of the gate's output into STOP. ``true`` when a real obstacle's
  footprint lies in the box's own stop zone of that cycle (from the vehicle's front for the
  zone length the box used, +- ``--zone-tol`` m along and ``--lateral-tol`` m across, which
  covers the 0.1 m grid and the one-cycle latency of the two-hit rule; a footprint overlapping
  the vehicle counts); ``false`` when nothing real is in that zone (``early`` marks the false
  ones with a real obstacle in the corridor within the slow zone beyond); ``fault`` when the
  reason is a fault, not an obstacle. The boot STOP is not an event.
- false-stop time: cycles in STOP (for an obstacle) with nothing real in the stop zone.

Reproducible: after each cycle the tool waits for the novelty model's update thread (on a
vehicle the update finishes well inside the 100 ms period; with ``--fast`` it would race the
loop and make every run different). ``--free-running`` skips the wait.

Writes to ``--out``: ``longrun.csv`` (one row every ``--every`` cycles), ``events.csv`` (every
STOP event and collision), ``summary.json``, ``longrun.png`` (cv2 drawing), ``config.toml``
(the config the daemon ran). Times: the loop's stages are timed in wall time (inflated on a
shared machine) and the pipeline and the renderer also in thread CPU time.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

# the closed-loop driving is the campaign's (fieldguard campaign): the same config, the same
# daemon start; this tool keeps its own accounting and plot for one long run
from appliance.campaign_drive import deep_merge as _deep_merge  # noqa: E402,F401
from appliance.campaign_drive import drive_config_data, rss_mb, start_sim_daemon  # noqa: E402
from appliance.campaign_drive import to_toml as _toml  # noqa: E402
from appliance.campaign_report import nice_ticks as _nice_ticks  # noqa: E402

CSV_FIELDS = ("t_s", "cycles", "distance_m", "lane", "x_m", "y_m", "speed_mps", "state",
              "collisions", "stops_true", "stops_false", "stops_early", "stops_fault",
              "false_stop_s", "stopped_s", "detours", "overrides", "model_samples",
              "model_updates", "updates_skipped", "rss_mb", "pipeline_ms_p50", "pipeline_ms_p99",
              "pipeline_cpu_ms", "render_ms", "render_cpu_ms", "cycle_ms_p50", "cycle_ms_p99",
              "novel_fraction", "stereo_px_fraction")
EVENT_FIELDS = ("t_s", "event", "kind", "x_m", "y_m", "lane", "speed_mps", "stop_zone_m",
                "real_nearest_m", "obstacle", "seen_frames_10s", "last_seen_s_before",
                "last_seen_ahead_m", "reason")
HISTORY_S = 10.0            # what the box saw, kept to explain a collision


def _pct(a, q) -> float | None:
    return None if len(a) == 0 else round(float(np.percentile(np.asarray(a, float), q)), 2)


class LongRun:
    """One closed-loop long run. ``build()`` starts the daemon; ``run()`` drives it for the
    configured time and writes the files; tests may reach ``self.daemon`` / ``self.field``
    between the two."""

    def __init__(self, out_dir, *, scene: str = "stubble-coverage", seed: int = 0,
                 minutes: float = 20.0, stereo_scale: float = 0.25,
                 pipelines=("stereo-novelty",), matcher: str | None = "sgbm",
                 config_file: str | None = None, overrides: dict | None = None,
                 every: int = 50, zone_tol_m: float = 0.5, lateral_tol_m: float = 0.2,
                 plot: bool = True, progress: bool = True, command: str = "",
                 sync_updates: bool = True):
        self.out = Path(out_dir)
        self.scene, self.seed = scene, int(seed)
        self.minutes = float(minutes)
        self.stereo_scale = float(stereo_scale)
        self.pipeline_names = tuple(pipelines)
        self.matcher = matcher
        self.config_file = config_file
        self.overrides = overrides or {}
        self.every = max(1, int(every))
        self.zone_tol_m, self.lateral_tol_m = float(zone_tol_m), float(lateral_tol_m)
        self.plot, self.progress = plot, progress
        self.command = command
        self.sync_updates = bool(sync_updates)
        self.daemon = None
        self.field = None
        self.events: list[dict] = []
        self.rows: list[dict] = []

    # ---- set-up ------------------------------------------------------------------------------
    def config_data(self) -> dict:
        extra: dict = {}
        if self.config_file:
            import tomllib
            extra = tomllib.loads(Path(self.config_file).read_text("utf-8"))
        return drive_config_data(self.scene, self.seed, stereo_scale=self.stereo_scale,
                                 pipelines=self.pipeline_names, matcher=self.matcher,
                                 extra=_deep_merge(extra, self.overrides))

    def build(self) -> "LongRun":
        self.out.mkdir(parents=True, exist_ok=True)
        data = self.config_data()
        (self.out / "config.toml").write_text(_toml(data), encoding="utf-8")
        cfg, d, self.field = start_sim_daemon(data, str(self.out / "config.toml"))
        self.cfg = cfg
        self.daemon = d
        self.vehicle = self.field.vehicle
        self.zones = cfg.zones
        self.n_cycles = int(round(self.minutes * 60.0 * cfg.loop.rate_hz))
        # timing wrappers: wall and thread-CPU time of each pipeline and of the renderer
        self._pipe_wall: list[float] = []
        self._pipe_cpu: list[float] = []
        self._render_wall: list[float] = []
        self._render_cpu: list[float] = []
        for p in d.pipelines:
            p.process = self._timed(p.process, self._pipe_wall, self._pipe_cpu)
        self.field.render = self._timed(self.field.render, self._render_wall, self._render_cpu)
        self._novelty = [p.novelty for p in d.pipelines if hasattr(p, "novelty")]
        self.model_bound = None
        self._update_s: list[float] = []
        self._updates_seen = 0
        # accounting state
        self._prev_state = None
        self._prev_collisions = 0
        self.counts = {"true": 0, "false": 0, "early": 0, "fault": 0}
        self.false_stop_s = 0.0
        self._cycle_wall: list[float] = []
        self._win = {"cycle": [], "novel": [], "stereo_px": []}
        self.grid_cells = None
        from collections import deque
        self._history = deque(maxlen=int(HISTORY_S * cfg.loop.rate_hz))
        self._path_s = self.vehicle._s
        self._spacing = 6.0
        if self.scene == "stubble-coverage":
            from drivers.sim.scenes import COVERAGE_LANES
            self._spacing = COVERAGE_LANES[1]
        d.loop.on_cycle.append(self.on_cycle)
        return self

    @staticmethod
    def _timed(fn, wall: list, cpu: list):
        def wrapper(*a, **k):
            w0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                cpu.append((time.thread_time() - c0) * 1e3)
                wall.append((time.perf_counter() - w0) * 1e3)
        return wrapper

    # ---- truth -------------------------------------------------------------------------------
    def lane(self) -> int:
        p = self.field.scene.path
        y = float(np.interp(min(max(self.vehicle.s, 0.0), self.vehicle.path_length_m),
                            self._path_s, p[:, 1]))
        return int(round(y / self._spacing))

    def real_ahead(self, stop_len_m: float) -> tuple[bool, float, str, bool]:
        """(a real obstacle in the stop zone, nearest real obstacle in the corridor ahead
        [m from the front, inf if none], its id/class, one in the slow zone beyond)."""
        z = self.zones
        rear = self.field.scene.footprint[0]
        x, y, _ = self.vehicle.pose()
        in_stop, in_slow, nearest, name = False, False, math.inf, ""
        reach = stop_len_m + z.slow_extra_m + self.zone_tol_m
        for k, o in enumerate(self.field.world.obstacles):
            if math.hypot(o.x - x, o.y - y) > o.radius + z.front_x_m + 40.0:
                continue
            p = self.vehicle.footprint_in_vehicle(k)
            if not len(p):
                continue
            corridor = (np.abs(p[:, 1]) <= z.half_width_m + self.lateral_tol_m) & (p[:, 0] >= -rear)
            if not corridor.any():
                continue
            ahead = float((p[corridor, 0] - z.front_x_m).min())
            if ahead < nearest:
                nearest, name = ahead, f"{o.id}/{o.cls}"
            if ahead <= stop_len_m + self.zone_tol_m:
                in_stop = True
            elif ahead <= reach:
                in_slow = True
        return in_stop, nearest, name, in_slow

    # ---- what the box saw (collision forensics) ------------------------------------------------
    def _remember(self, res, t_s: float) -> None:
        """Keep the last HISTORY_S of the pipelines' points in world x, y (level vehicle), with
        the front bumper's world position, to tell after a collision whether the box ever saw
        the obstacle it hit."""
        pts = [d.points_xy for d in res.detections.values() if len(d.points_xy)]
        x, y, yaw = self.vehicle.pose()
        c, s = math.cos(yaw), math.sin(yaw)
        if pts:
            p = np.concatenate(pts).astype(np.float64)
            w = np.stack([x + p[:, 0] * c - p[:, 1] * s, y + p[:, 0] * s + p[:, 1] * c], 1)
        else:
            w = np.zeros((0, 2))
        fx = self.zones.front_x_m
        self._history.append((t_s, w.astype(np.float32), (x + fx * c, y + fx * s)))

    def seen_before(self, o, t_s: float) -> dict:
        """Frames of the last HISTORY_S with a box point within the obstacle's radius + 0.3 m
        of its centre, when it was last seen and how far ahead of the front it was then."""
        n, last, ahead = 0, None, None
        for t, w, front in self._history:
            if len(w) and np.any(np.hypot(w[:, 0] - o.x, w[:, 1] - o.y) <= o.radius + 0.3):
                n += 1
                last, ahead = t, math.hypot(o.x - front[0], o.y - front[1]) - o.radius
        return {"seen_frames_10s": f"{n}/{len(self._history)}",
                "last_seen_s_before": None if last is None else round(t_s - last, 1),
                "last_seen_ahead_m": None if ahead is None else round(ahead, 2)}

    # ---- per cycle ---------------------------------------------------------------------------
    def on_cycle(self, res) -> None:
        from hal.types import GateState
        v = self.vehicle
        state = res.output.state
        t_s = res.index / self.cfg.loop.rate_hz
        dt = 1.0 / self.cfg.loop.rate_hz
        stop_len = res.verdict.stop_len_m if res.verdict is not None else self.zones.min_stop_m
        obstacle_stop = state is GateState.STOP and "stop zone" in res.output.reason
        fault_reason = state is GateState.STOP and not obstacle_stop and \
            not res.output.reason.startswith("holding")
        info = None
        if state is GateState.STOP:
            info = self.real_ahead(stop_len)
        if state is GateState.STOP and self._prev_state not in (None, GateState.STOP):
            x, y, _ = v.pose()
            in_stop, nearest, name, in_slow = info
            if fault_reason and res.faults:
                kind = "fault"
            elif in_stop:
                kind = "true"
            else:
                kind = "false"
                if in_slow:
                    self.counts["early"] += 1
            self.counts[kind] += 1
            self.events.append({"t_s": round(t_s, 1), "event": "stop", "kind": kind,
                                "x_m": round(x, 2), "y_m": round(y, 2), "lane": self.lane(),
                                "speed_mps": round(v.speed, 2), "stop_zone_m": round(stop_len, 2),
                                "real_nearest_m": None if not math.isfinite(nearest)
                                else round(nearest, 2),
                                "obstacle": name, "reason": res.output.reason,
                                "early": kind == "false" and in_slow})
        if obstacle_stop and info is not None and not info[0]:
            self.false_stop_s += dt
        if v.collisions > self._prev_collisions:
            x, y, _ = v.pose()
            for oid in v.obstacles_hit[self._prev_collisions:]:
                o = next(ob for ob in self.field.world.obstacles if ob.id == oid)
                seen = self.seen_before(o, t_s)
                self.events.append({"t_s": round(t_s, 1), "event": "collision", "kind": o.cls,
                                    "x_m": round(x, 2), "y_m": round(y, 2), "lane": self.lane(),
                                    "speed_mps": None, "stop_zone_m": round(stop_len, 2),
                                    "real_nearest_m": 0.0, "obstacle": f"{o.id}/{o.cls}",
                                    **seen,
                                    "reason": f"box said {state.value}: {res.output.reason}"})
            self._prev_collisions = v.collisions
        self._prev_state = state
        self._remember(res, t_s)
        # figures
        cyc = sum(res.wall_ms.values())
        self._cycle_wall.append(cyc)
        w = self._win
        w["cycle"].append(cyc)
        samples = None
        for det in res.detections.values():
            dbg = det.debug
            if "model_samples" in dbg:
                samples = int(dbg["model_samples"])
                w["novel"].append(float(dbg.get("novel_fraction", 0.0)))
                w["stereo_px"].append(float(dbg.get("stereo_px_fraction", 0.0)))
                if self.model_bound is None and "grid" in dbg:
                    rows, cols = dbg["grid"]
                    self.grid_cells = rows * cols
                    self.model_bound = self._novelty[0].model.max_size(rows * cols) \
                        if self._novelty else None
        for nd in self._novelty:
            u = nd.updater
            if self.sync_updates and u is not None:
                # real time gives the update thread the rest of the 100 ms period (an update
                # takes ~10 ms); --fast does not: wait here, outside the loop's cycle, so the
                # new model is in place by the next frame, as on a vehicle, and the run is
                # reproducible
                u.wait_idle(30.0)
            if u is not None and u.done > self._updates_seen:
                self._updates_seen = u.done
                self._update_s.append(u.last_update_s)
        if self.sync_updates and self._novelty and samples is not None:
            samples = self._novelty[0].model.size       # after the wait: not racy
        if res.index % self.every == 0:
            self._row(res, samples)
        if self.progress and res.index % 10 == 0:
            self._prog(min(res.index, self.n_cycles), self.n_cycles)

    def _row(self, res, samples) -> None:
        v = self.vehicle
        st = v.stats()
        x, y, _ = v.pose()
        w = self._win
        pw, pc = self._pipe_wall[self._pw0:], self._pipe_cpu[self._pw0:]
        rw, rc = self._render_wall[self._rw0:], self._render_cpu[self._rw0:]
        self._pw0, self._rw0 = len(self._pipe_wall), len(self._render_wall)
        nd = self._novelty[0] if self._novelty else None
        row = {
            "t_s": round(res.index / self.cfg.loop.rate_hz, 1), "cycles": res.index,
            "distance_m": round(v.distance_m, 1), "lane": self.lane(), "x_m": round(x, 1),
            "y_m": round(y, 1), "speed_mps": round(v.speed, 2), "state": res.output.state.value,
            "collisions": v.collisions, "stops_true": self.counts["true"],
            "stops_false": self.counts["false"], "stops_early": self.counts["early"],
            "stops_fault": self.counts["fault"], "false_stop_s": round(self.false_stop_s, 1),
            "stopped_s": st["stopped_s"], "detours": v.detours, "overrides": v.overrides,
            "model_samples": "" if samples is None else samples,
            "model_updates": "" if nd is None else nd.model.updates,
            "updates_skipped": "" if nd is None or nd.updater is None else nd.updater.skipped,
            "rss_mb": round(rss_mb(), 1),
            "pipeline_ms_p50": _pct(pw, 50), "pipeline_ms_p99": _pct(pw, 99),
            "pipeline_cpu_ms": None if not pc else round(float(np.mean(pc)), 2),
            "render_ms": None if not rw else round(float(np.mean(rw)), 2),
            "render_cpu_ms": None if not rc else round(float(np.mean(rc)), 2),
            "cycle_ms_p50": _pct(w["cycle"], 50), "cycle_ms_p99": _pct(w["cycle"], 99),
            "novel_fraction": None if not w["novel"] else round(float(np.mean(w["novel"])), 4),
            "stereo_px_fraction": None if not w["stereo_px"]
            else round(float(np.mean(w["stereo_px"])), 4),
        }
        for k in w:
            w[k] = []
        self.rows.append(row)
        self._csv.writerow({k: ("" if row[k] is None else row[k]) for k in CSV_FIELDS})
        self._csv_file.flush()

    # ---- the run -----------------------------------------------------------------------------
    def run(self) -> dict:
        from appliance.progress import Progress
        if self.daemon is None:
            self.build()
        d = self.daemon
        self._prog = Progress(f"longrun {self.scene} {self.minutes:g} min", self.n_cycles)
        self._pw0 = self._rw0 = 0
        self._csv_file = open(self.out / "longrun.csv", "w", newline="", encoding="utf-8")
        self._csv = csv.DictWriter(self._csv_file, CSV_FIELDS)
        self._csv.writeheader()
        load0 = os.getloadavg()
        w0, c0 = time.perf_counter(), time.process_time()
        self.rss_start_mb = rss_mb()
        try:
            d.run(max_cycles=self.n_cycles)
        finally:
            wall_s, cpu_s = time.perf_counter() - w0, time.process_time() - c0
            d.shutdown()
            self._csv_file.close()
        summary = self.summary(wall_s, cpu_s, load0, os.getloadavg())
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
        with open(self.out / "events.csv", "w", newline="", encoding="utf-8") as f:
            wr = csv.DictWriter(f, EVENT_FIELDS, extrasaction="ignore")
            wr.writeheader()
            for e in self.events:
                wr.writerow({k: ("" if e.get(k) is None else e.get(k)) for k in EVENT_FIELDS})
        if self.plot:
            plot(self.out)
        return summary

    def summary(self, wall_s: float, cpu_s: float, load0, load1) -> dict:
        v = self.vehicle
        st = v.stats()
        cycles = self.daemon.loop.cycles
        hours = cycles / self.cfg.loop.rate_hz / 3600.0
        ver = verdicts(self.rows, self.model_bound)
        hits = [e for e in self.events if e["event"] == "collision"]
        n_frames = max(1, len(self._pipe_wall))
        return {
            "command": self.command,
            "scene": self.scene, "seed": self.seed, "stereo_scale": self.stereo_scale,
            "image_px": None if self.field.stereo_calibration is None else
            [self.field.stereo_calibration.camera.width,
             self.field.stereo_calibration.camera.height],
            "pipelines": list(self.pipeline_names),
            "sync_updates": self.sync_updates,
            "simulated_s": round(cycles / self.cfg.loop.rate_hz, 1), "cycles": cycles,
            "distance_m": st["distance_m"], "lanes_reached": self.lane() + 1,
            "path_length_m": st["path_length_m"], "finished_path": st["finished"],
            "stopped_s": st["stopped_s"],
            "collisions": v.collisions,
            "collided_with": [e["obstacle"] for e in hits],
            "stops": dict(self.counts),
            "stops_total": self.counts["true"] + self.counts["false"] + self.counts["fault"],
            "false_stops_per_hour": round(self.counts["false"] / hours, 1) if hours else None,
            "false_stop_s": round(self.false_stop_s, 1),
            "detours": v.detours, "overrides": v.overrides,
            "overrides_per_hour": round(v.overrides / hours, 1) if hours else None,
            "tolerances_m": {"along": self.zone_tol_m, "across": self.lateral_tol_m},
            "model": {"samples": ver["model"], "bound": self.model_bound,
                      "bytes_per_sample": 8 * 4 + 8,
                      "grid_cells": self.grid_cells,
                      "updates": None if not self._novelty else self._novelty[0].model.updates,
                      "updates_skipped": None if not self._novelty or
                      self._novelty[0].updater is None else self._novelty[0].updater.skipped,
                      "update_ms_p50": _pct([1e3 * s for s in self._update_s], 50),
                      "update_ms_max": None if not self._update_s else
                      round(1e3 * max(self._update_s), 1)},
            "rss_mb": {"verdict": ver["rss"], "before_run": round(self.rss_start_mb, 1),
                       "end": self.rows[-1]["rss_mb"] if self.rows else None,
                       "max": max((r["rss_mb"] for r in self.rows), default=None)},
            "csv_row_every_s": ver["row_every_s"],
            "timing_ms": {
                "pipeline_wall_p50": _pct(self._pipe_wall, 50),
                "pipeline_wall_p99": _pct(self._pipe_wall, 99),
                "pipeline_cpu_p50": _pct(self._pipe_cpu, 50),
                "pipeline_cpu_p99": _pct(self._pipe_cpu, 99),
                "render_wall_p50": _pct(self._render_wall, 50),
                "render_cpu_p50": _pct(self._render_cpu, 50),
                "cycle_wall_p50": _pct(self._cycle_wall, 50),
                "cycle_wall_p99": _pct(self._cycle_wall, 99),
            },
            "overruns": self.daemon.loop.overruns,
            "wall_s": round(wall_s, 1), "process_cpu_s": round(cpu_s, 1),
            "process_cpu_ms_per_frame": round(1e3 * cpu_s / n_frames, 1),
            "loadavg_start_end": [round(load0[0], 2), round(load1[0], 2)],
            "events": self.events,
        }


def plateau_verdict(samples, bound: int | None = None) -> dict:
    """Does a size (the model's samples, or the process RSS) plateau over the run? The series
    is split in quarters. It plateaus when the highest value of the last quarter is within
    5 % of the highest value of the second quarter (the envelope stopped growing after the
    warm-up) and, when a ``bound`` is given, never exceeds it in the second half. (Means of
    quarters are reported too, but dips - many cells excluded near obstacles for a while -
    make them a poor test of growth.)"""
    x = np.asarray([v for v in samples if v is not None and np.isfinite(v)], float)
    n = len(x)
    if n < 8:
        return {"plateau": None, "first": None, "max": None, "last": None}
    q = [x[i * n // 4:(i + 1) * n // 4] for i in range(4)]
    env2, env4 = float(q[1].max()), float(q[3].max())
    within = bound is None or bound < 0 or float(x[n // 2:].max()) <= bound
    flat = env4 <= 1.05 * env2
    reach = np.nonzero(x >= 0.95 * float(q[3].mean()))[0]
    return {"plateau": bool(within and flat), "first": round(float(x[0]), 1),
            "max": round(float(x.max()), 1), "last": round(float(x[-1]), 1),
            "q2_max": round(env2, 1), "q4_max": round(env4, 1),
            "q4_max_vs_q2_max": round(env4 / env2 - 1.0, 4) if env2 else None,
            "q3_mean": round(float(q[2].mean()), 1), "q4_mean": round(float(q[3].mean()), 1),
            "points_to_95pct_of_q4_mean": int(reach[0]) + 1 if len(reach) else None,
            "points": n}


def verdicts(rows: list[dict], bound: int | None) -> dict:
    """Plateau verdicts for the model size and the RSS from the CSV rows."""
    def series(k):
        return [float(r[k]) if r.get(k) not in ("", None) else float("nan") for r in rows]
    dt = float(rows[1]["t_s"]) - float(rows[0]["t_s"]) if len(rows) > 1 else None
    return {"model": plateau_verdict(series("model_samples"), bound),
            "rss": plateau_verdict(series("rss_mb")), "row_every_s": dt}


# ---------------------------------------------------------------------------------------------
# the plot (cv2 drawing; matplotlib is not a dependency)
# ---------------------------------------------------------------------------------------------
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _fmt(v: float) -> str:
    if abs(v) >= 1000:
        return f"{v / 1000:g}k"
    return f"{v:g}"


def _panel(img, rect, x, series, title, ylo=None, yhi=None, step=False):
    """series: list of (label, values, BGR colour, dashed)."""
    x0, y0, w, h = rect
    L, R, T, B = 62, 12, 24, 26
    ax0, ay0, aw, ah = x0 + L, y0 + T, w - L - R, h - T - B
    cv2.rectangle(img, (ax0, ay0), (ax0 + aw, ay0 + ah), (0, 0, 0), 1)
    cv2.putText(img, title, (ax0, y0 + 16), _FONT, 0.48, (0, 0, 0), 1, cv2.LINE_AA)
    vals = [np.asarray(s[1], float) for s in series]
    finite = np.concatenate([v[np.isfinite(v)] for v in vals] + [np.zeros(0)])
    lo = ylo if ylo is not None else (float(finite.min()) if len(finite) else 0.0)
    hi = yhi if yhi is not None else (float(finite.max()) if len(finite) else 1.0)
    if hi - lo < 1e-9:
        hi = lo + 1.0
    hi += 0.05 * (hi - lo)
    xs = np.asarray(x, float)
    xlo, xhi = (float(xs.min()), float(xs.max())) if len(xs) else (0.0, 1.0)
    if xhi <= xlo:
        xhi = xlo + 1.0

    def px(xv, yv):
        return (int(round(ax0 + (xv - xlo) / (xhi - xlo) * aw)),
                int(round(ay0 + ah - (yv - lo) / (hi - lo) * ah)))
    for t in _nice_ticks(lo, hi, 4):
        if lo <= t <= hi:
            p = px(xlo, t)
            cv2.line(img, (ax0, p[1]), (ax0 + aw, p[1]), (225, 225, 225), 1)
            cv2.putText(img, _fmt(t), (x0 + 4, p[1] + 4), _FONT, 0.38, (60, 60, 60), 1,
                        cv2.LINE_AA)
    for t in _nice_ticks(xlo, xhi, 10):
        p = px(t, lo)
        cv2.line(img, (p[0], ay0 + ah), (p[0], ay0 + ah + 4), (0, 0, 0), 1)
        cv2.putText(img, _fmt(t), (p[0] - 8, ay0 + ah + 17), _FONT, 0.38, (60, 60, 60), 1,
                    cv2.LINE_AA)
    lx = ax0 + 8
    for (label, _v, col, dashed), v in zip(series, vals):
        ok = np.isfinite(v) & np.isfinite(xs[:len(v)])
        pts = [px(a, b) for a, b in zip(xs[:len(v)][ok], v[ok])]
        if step and len(pts) > 1:
            stepped = [pts[0]]
            for p in pts[1:]:
                stepped += [(p[0], stepped[-1][1]), p]
            pts = stepped
        if len(pts) > 1:
            if dashed:
                for i in range(0, len(pts) - 1, 2):
                    cv2.line(img, pts[i], pts[i + 1], col, 1, cv2.LINE_AA)
            else:
                cv2.polylines(img, [np.array(pts, np.int32)], False, col, 2, cv2.LINE_AA)
        cv2.line(img, (lx, ay0 + 10), (lx + 18, ay0 + 10), col, 2)
        last = "" if not ok.any() else f" ({_fmt(round(float(v[ok][-1]), 1))})"
        text = f"{label}{last}"
        cv2.putText(img, text, (lx + 22, ay0 + 14), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        lx += 30 + cv2.getTextSize(text, _FONT, 0.4, 1)[0][0]


def _route_map(img, rect, rows, events, summary, obstacles, path):
    x0, y0, w, h = rect
    cv2.putText(img, "route (grey: planned, blue: driven), obstacles, events", (x0 + 8, y0 + 16),
                _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    pts = np.asarray(path, float) if path is not None and len(path) else \
        np.array([[r["x_m"], r["y_m"]] for r in rows], float)
    if not len(pts):
        return
    xlo, xhi = pts[:, 0].min() - 5, pts[:, 0].max() + 5
    ylo, yhi = pts[:, 1].min() - 5, pts[:, 1].max() + 5
    s = min((w - 20) / (xhi - xlo), (h - 60) / (yhi - ylo))

    def px(a, b):
        return (int(round(x0 + 10 + (a - xlo) * s)), int(round(y0 + h - 30 - (b - ylo) * s)))
    if path is not None:
        cv2.polylines(img, [np.array([px(a, b) for a, b in path], np.int32)], False,
                      (200, 200, 200), 1, cv2.LINE_AA)
    drv = [px(float(r["x_m"]), float(r["y_m"])) for r in rows]
    if len(drv) > 1:
        cv2.polylines(img, [np.array(drv, np.int32)], False, (200, 120, 40), 2, cv2.LINE_AA)
    for o in obstacles or []:
        cv2.circle(img, px(o["x"], o["y"]), 3, (60, 60, 60), -1)
    colours = {"true": (0, 160, 0), "false": (0, 140, 255), "fault": (200, 0, 200)}
    for e in events:
        if e["event"] == "collision":
            c = px(float(e["x_m"]), float(e["y_m"]))
            cv2.drawMarker(img, c, (0, 0, 230), cv2.MARKER_TILTED_CROSS, 12, 2)
        else:
            cv2.circle(img, px(float(e["x_m"]), float(e["y_m"])), 4,
                       colours.get(e["kind"], (0, 0, 0)), 1, cv2.LINE_AA)
    ly = y0 + h - 10
    lx = x0 + 10
    for label, col in (("true stop", colours["true"]), ("false stop", colours["false"]),
                       ("fault stop", colours["fault"])):
        cv2.circle(img, (lx + 4, ly - 4), 4, col, 1, cv2.LINE_AA)
        cv2.putText(img, label, (lx + 12, ly), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        lx += 100
    cv2.drawMarker(img, (lx + 4, ly - 4), (0, 0, 230), cv2.MARKER_TILTED_CROSS, 10, 2)
    cv2.putText(img, "collision", (lx + 12, ly), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    lx += 90
    cv2.circle(img, (lx + 4, ly - 4), 3, (60, 60, 60), -1)
    cv2.putText(img, "obstacle", (lx + 12, ly), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)


def _num(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def refresh_summary(out_dir) -> dict:
    """Recompute the plateau verdicts of ``out_dir/summary.json`` from its CSV (after a
    change to the verdict rule, without running again)."""
    out = Path(out_dir)
    with open(out / "longrun.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    s = json.loads((out / "summary.json").read_text("utf-8"))
    bound = s.get("model", {}).get("bound")
    ver = verdicts(rows, bound)
    m = s.setdefault("model", {})
    for k in [k for k in m if k.startswith("samples_") and k != "samples"] + \
            ["plateau", "q4_vs_q3", "frames_to_95pct_of_final"]:
        m.pop(k, None)
    m["samples"] = ver["model"]
    m.setdefault("bytes_per_sample", 8 * 4 + 8)
    r = s.setdefault("rss_mb", {})
    if "start" in r:
        r["before_run"] = r.pop("start")
    r.pop("half", None)
    r["verdict"] = ver["rss"]
    s["csv_row_every_s"] = ver["row_every_s"]
    (out / "summary.json").write_text(json.dumps(s, indent=2), encoding="utf-8")
    return s


def plot(out_dir, png: str | None = None) -> Path:
    """Draw longrun.png from longrun.csv, events.csv and summary.json in ``out_dir``."""
    out = Path(out_dir)
    with open(out / "longrun.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    summary = json.loads((out / "summary.json").read_text("utf-8")) \
        if (out / "summary.json").exists() else {}
    events = summary.get("events", [])
    tmin = [_num(r["t_s"]) / 60.0 for r in rows]
    col = lambda k: [_num(r[k]) for r in rows]  # noqa: E731
    W, PH = 1500, 200
    img = np.full((4 * PH + 40, W, 3), 255, np.uint8)
    left = 900
    m = summary.get("model", {})
    bound = m.get("bound")
    ser = [("model samples", col("model_samples"), (180, 60, 0), False)]
    if bound and bound > 0:
        ser.append((f"pruning bound {bound}", [bound] * len(rows), (0, 0, 200), True))
    _panel(img, (0, 30, left, PH), tmin, ser, "novelty model samples (Parzen window) vs "
           "simulated minutes", ylo=0)
    _panel(img, (0, 30 + PH, left, PH), tmin, [("process RSS MB", col("rss_mb"), (120, 0, 120),
                                                False)], "process resident memory, MB")
    _panel(img, (0, 30 + 2 * PH, left, PH), tmin,
           [("collisions", col("collisions"), (0, 0, 230), False),
            ("true stops", col("stops_true"), (0, 160, 0), False),
            ("false stops", col("stops_false"), (0, 140, 255), False),
            ("overrides", col("overrides"), (200, 0, 200), False),
            ("detours", col("detours"), (140, 140, 0), False)],
           "cumulative events", ylo=0, step=True)
    _panel(img, (0, 30 + 3 * PH, left, PH), tmin,
           [("pipeline wall p50", col("pipeline_ms_p50"), (180, 60, 0), False),
            ("p99", col("pipeline_ms_p99"), (0, 0, 200), False),
            ("pipeline CPU mean", col("pipeline_cpu_ms"), (0, 140, 0), False),
            ("render wall", col("render_ms"), (120, 120, 120), True)],
           "ms per frame (wall time inflated by other users of the machine)", ylo=0)
    obstacles, path = None, None
    try:
        from drivers.sim.scenes import build_scene
        sc = build_scene(summary.get("scene", "stubble-coverage"), int(summary.get("seed", 0)))
        obstacles = [{"x": o.x, "y": o.y} for o in sc.world.obstacles]
        path = sc.path
    except Exception:           # noqa: BLE001 - a map without the plan is still a map
        pass
    _route_map(img, (left + 10, 30, W - left - 20, 2 * PH + 40), rows, events, summary,
               obstacles, path)
    # the headline figures
    tx, ty = left + 20, 30 + 2 * PH + 90
    st = summary.get("stops", {})
    ms = m.get("samples", {})
    rs = summary.get("rss_mb", {}).get("verdict", {})
    lines = [
        f"{summary.get('scene', '?')} seed {summary.get('seed', '?')}, stereo "
        f"{summary.get('image_px', '?')} (scale {summary.get('stereo_scale', '?')})",
        f"{summary.get('simulated_s', 0) / 60:.1f} simulated min, "
        f"{summary.get('distance_m', 0):.0f} m driven, {summary.get('lanes_reached', '?')} lanes",
        f"collisions {summary.get('collisions', '?')}  {', '.join(summary.get('collided_with', []))}",
        f"stops: true {st.get('true', '?')}, false {st.get('false', '?')} "
        f"(early {st.get('early', '?')}), fault {st.get('fault', '?')}",
        f"false stops per hour {summary.get('false_stops_per_hour', '?')}, "
        f"overrides {summary.get('overrides', '?')}, detours {summary.get('detours', '?')}",
        f"model samples: max {ms.get('max', '?')}, last {ms.get('last', '?')}, bound "
        f"{bound}, plateau {ms.get('plateau', '?')}",
        f"RSS MB: max {rs.get('max', '?')}, last {rs.get('last', '?')}, plateau "
        f"{rs.get('plateau', '?')}",
    ]
    for i, t in enumerate(lines):
        cv2.putText(img, t, (tx, ty + 22 * i), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "fieldguard long run: stereo-novelty, closed loop, coverage driving",
                (10, 20), _FONT, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    path_png = Path(png) if png else out / "longrun.png"
    cv2.imwrite(str(path_png), img)
    return path_png


# ---------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="output folder (CSV, events, summary, PNG, config)")
    ap.add_argument("--minutes", type=float, default=20.0, help="simulated minutes (default 20)")
    ap.add_argument("--scene", default="stubble-coverage")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stereo-scale", type=float, default=0.25,
                    help="stereo at this fraction of 1280x1024 (0.25: 320x256, 8-px cells = "
                         "the paper's 40x32 grid)")
    ap.add_argument("--matcher", default="sgbm", choices=("bm", "sgbm"))
    ap.add_argument("--pipelines", default="stereo-novelty", help="comma list of pipelines")
    ap.add_argument("--config", help="extra TOML merged over the run's config")
    ap.add_argument("--every", type=int, default=50, help="cycles per CSV row (default 50)")
    ap.add_argument("--zone-tol", type=float, default=0.5, help="m along the stop zone")
    ap.add_argument("--lateral-tol", type=float, default=0.2, help="m across the stop zone")
    ap.add_argument("--free-running", action="store_true",
                    help="do not wait for the novelty model's update thread after each cycle "
                         "(as fast as the CPU allows; the run is then not reproducible)")
    ap.add_argument("--replot", metavar="DIR", help="only draw DIR/longrun.png again")
    a = ap.parse_args(argv)
    if a.replot:
        refresh_summary(a.replot)
        print(plot(a.replot))
        return 0
    if not a.out:
        ap.error("--out is required")
    from hal.errors import FieldguardError
    try:
        return _run_main(a, argv)
    except (FieldguardError, OSError, ValueError) as exc:
        print(f"longrun: error: {exc}", file=sys.stderr)
        return 2


def _run_main(a, argv) -> int:
    lr = LongRun(a.out, scene=a.scene, seed=a.seed, minutes=a.minutes,
                 stereo_scale=a.stereo_scale, pipelines=tuple(a.pipelines.split(",")),
                 matcher=a.matcher, config_file=a.config, every=a.every,
                 zone_tol_m=a.zone_tol, lateral_tol_m=a.lateral_tol,
                 sync_updates=not a.free_running,
                 command="python tools/longrun_stereo.py " + " ".join(
                     sys.argv[1:] if argv is None else argv))
    lr.build()
    lr.daemon.install_signal_handlers()          # SIGTERM/^C: stop, still write the summary
    s = lr.run()
    brief = {k: s[k] for k in ("simulated_s", "distance_m", "lanes_reached", "collisions",
                               "collided_with", "stops", "false_stops_per_hour", "detours",
                               "overrides", "timing_ms", "wall_s", "process_cpu_s")}
    brief["model"] = {"bound": s["model"]["bound"], **s["model"]["samples"]}
    brief["rss_mb"] = s["rss_mb"]["verdict"]
    print(json.dumps(brief, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
