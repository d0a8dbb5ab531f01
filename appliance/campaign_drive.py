"""One drive of a campaign: the real daemon in lock-step with the simulated field, scored on what
the vehicle was told.

A drive is one (scene kind, seed): the daemon is built in-process exactly as ``fieldguard run
--sim KIND --config F --fast`` builds it (``sim_config`` + ``Daemon(mode="sim", pace=0)``), the
simulated sensors and vehicle on one ManualClock; the gate's STOP / SLOW drive the simulated
vehicle, whose safety driver steers round real obstacles it was stopped for (detours) and
overrides a false stop after 10 s (overrides), so a drive of hours goes on.

Scored every cycle against the simulator's truth (:class:`Drive.on_cycle`):

- ``collisions``: the vehicle's footprint reached an obstacle's (the sim vehicle counts them);
- STOP episodes for an obstacle (the gate's reason names the stop zone) are ``true`` when a real
  obstacle's footprint lies in the box's own stop zone of that cycle (+- ``zone_tol_m`` along,
  ``lateral_tol_m`` across: the 0.1 m grid and the one-cycle latency of the two-hit rule), else
  ``false``, with a cause (the gate's reason with its numbers taken out, the pipelines whose
  points lay in the stop zone, ``early`` when a real obstacle was in the corridor just beyond)
  and a place (``near an obstacle``: a real one within ``near_m`` of the stop zone;
  ``headland``: off the lanes, in a turn; else ``lane``); episodes for a fault are ``fault``;
- missed stops: a real obstacle deep in the stop zone (``zone_tol_m`` / ``lateral_tol_m`` inside
  it) while the box did not say STOP, one per obstacle encounter;
- detection distance: for the obstacle of each true stop, how far ahead of the front it was when
  the box's occupied cells first lay on it (within ``hold_m``) in an unbroken run of cycles up to
  the stop; per class.

Reproducible: after each cycle the drive waits for the novelty model's update thread (on a
vehicle the update finishes well inside the 100 ms period; with ``pace=0`` it would race the
loop), OpenCV runs one thread, and every random draw is seeded by (kind, seed): the same drive
gives the same figures in any process on any machine.

Nothing here writes files: :meth:`Drive.run` returns the result, the per-cycle rows and the
events; the campaign (appliance/campaign.py) writes them, wherever the drive ran.
"""
from __future__ import annotations

import math
import os
import re
import time
from collections import deque

import numpy as np

from appliance.zones import PathBend, bend_of, same_bend, to_path_frame

# default pipelines per scene kind: today's pipelines for the kind's sensors
DEFAULT_PIPELINES = {"stubble-coverage": ("stereo-novelty",),
                     "stubble-coverage-night": ("stereo-novelty",),
                     "greenhouse-coverage": ("rgbd",)}
ROW_FIELDS = ("t_s", "x_m", "y_m", "yaw_deg", "speed_mps", "state", "reason", "nearest_m",
              "stop_zone_m", "cells", "real_nearest_m", "real_obstacle", "real_meets", "place",
              "collisions", "stops_true", "stops_false", "missed_stops", "detours", "overrides",
              "model_samples", "acquire_ms", "perception_ms", "fusion_ms", "gate_ms", "send_ms",
              "render_cpu_ms", "pipeline_cpu_ms")
STAGES = ("acquire", "perception", "fusion", "gate", "send")
_NUM = re.compile(r"-?\d+(\.\d+)?")


CONTACT_AHEAD_S = 3.0     # "front": the obstacle was in the path ahead this recently
BOOT_S = 10.0             # false stops this early in a drive are the boot's: reported apart (a
                          # 2-minute drive boots the box 30 times an hour; a field box, once)


def contact_part(p: np.ndarray, rear_m: float, came_from_ahead: bool,
                 tol_m: float = 0.05) -> str:
    """Where an obstacle met the vehicle: "front" when it ``came_from_ahead`` (some of its
    footprint was in the straight corridor ahead of the front line within the last
    :data:`CONTACT_AHEAD_S`: what a forward-looking box is there to see), else "rear" when
    its footprint ``p`` (level vehicle frame, at the collision) lies wholly behind the rear
    (``rear_m`` behind the origin), else "side": it came from beside the body, where a forward
    box has no view (a person stepping out beside it, a corner swept into something in a
    turn)."""
    if came_from_ahead:
        return "front"
    p = np.asarray(p, np.float64).reshape(-1, 2)
    if len(p) and float(p[:, 0].max()) <= -rear_m + tol_m:
        return "rear"
    return "side"


def rss_mb() -> float:
    """Resident set size of this process (Linux /proc), MB."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def pct(a, q) -> float | None:
    return None if len(a) == 0 else round(float(np.percentile(np.asarray(a, float), q)), 2)


def deep_merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else v
    return out


def to_toml(data: dict, prefix: str = "") -> str:
    """A small TOML writer for the config tables we build (scalars, lists, nested tables)."""
    import json

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)
    lines, tables = [], []
    for k, v in data.items():
        if isinstance(v, dict):
            tables.append((k, v))
        else:
            lines.append(f"{k} = {val(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        name = f"{prefix}.{k}" if prefix else k
        name_q = ".".join(json.dumps(p) if "-" in p else p for p in name.split("."))
        out += f"\n[{name_q}]\n" + to_toml(v, name)
    return out


def drive_config_data(kind: str, seed: int, *, stereo_scale: float = 0.25,
                      pipelines=None, matcher: str | None = "sgbm",
                      extra: dict | None = None) -> dict:
    """The config (as TOML data) a drive's daemon runs: the kind's pipelines, the box's zones
    from the simulated vehicle's front bumper, the sim table; ``extra`` (a --config file's
    tables) merged over it; the scene, seed and stereo scale always the drive's."""
    from drivers.sim.scenes import build_scene
    sc = build_scene(kind, seed)
    rear, length, _width = sc.footprint
    if pipelines is None:
        pipelines = DEFAULT_PIPELINES.get(
            kind, ("rgbd",) if sc.illumination == "greenhouse" else ("stereo-novelty",))
    zones = {"front_x_m": round(-rear + length, 3), "body_rear_m": round(rear, 3)}
    if sc.illumination == "greenhouse":
        # the sprayer's narrow zone between the bush rows, as `run --sim greenhouse` runs it
        # (with the default 1.25 m half width the rows beside the 0.8 m vehicle were in the
        # stop zone: every greenhouse phantom found on training drives was at a bush edge)
        from appliance.config import SCENE_ZONES
        zones["half_width_m"] = SCENE_ZONES["greenhouse"]["half_width_m"]
    data: dict = {
        "perception": {"pipelines": list(pipelines)},
        "zones": zones,
        "sim": {"scene": kind, "seed": int(seed), "stereo_scale": float(stereo_scale),
                "pace": 0.0},
    }
    if matcher and "stereo-novelty" in pipelines:
        data["perception"]["stereo-novelty"] = {"matcher": matcher}
    if extra:
        data = deep_merge(data, extra)
    data["sim"] = deep_merge(data.get("sim", {}), {"scene": kind, "seed": int(seed),
                                                   "stereo_scale": float(stereo_scale)})
    return data


def start_sim_daemon(data: dict, source: str):
    """(cfg, daemon, field): the daemon ``fieldguard run --sim KIND --config F --fast`` would
    build from the config data, started, lock-step with its simulated field (pace 0, no status
    socket)."""
    from appliance.config import parse_config
    from appliance.daemon import Daemon, sim_config
    cfg = sim_config(parse_config(data, source), data["sim"]["scene"])
    d = Daemon(cfg, mode="sim", pace=0.0, serve_status=False)
    d.start()
    return cfg, d, d.shared["sim_hub"].field


def meeting_time(p: np.ndarray, v_xy, speed_mps: float, z, rear_m: float,
                 zone_tol_m: float, lateral_tol_m: float, horizon_s: float) -> float | None:
    """The scorer's test for a walker (footprint points ``p`` in the level vehicle frame,
    velocity over ground ``v_xy`` in the vehicle's axes): going on at that velocity while the
    vehicle drives on straight at ``speed_mps``, when does any of it first come within the
    zones' width + ``lateral_tol_m`` between the vehicle's rear (``rear_m`` behind its origin)
    and the front + ``zone_tol_m``? Looked for in 0.1 s steps up to ``horizon_s``; None if not
    by then. Pure."""
    speed = max(0.0, float(speed_mps))
    rel = np.array([float(v_xy[0]) - speed, float(v_xy[1])])
    steps = np.arange(0.0, horizon_s + 1e-9, 0.1)
    q = np.asarray(p, np.float64).reshape(-1, 2)[None] + steps[:, None, None] * rel[None, None]
    inside = ((q[..., 0] >= -rear_m) & (q[..., 0] <= z.front_x_m + zone_tol_m) &
              (np.abs(q[..., 1]) <= z.half_width_m + lateral_tol_m)).any(axis=1)
    return float(steps[int(np.argmax(inside))]) if inside.any() else None


def rest_horizon_s(speed_mps: float, z) -> float:
    """The time the vehicle needs to come to rest if it brakes now ([zones] reaction_time_s +
    speed / decel_mps2) + 0.5 s: the reach within which a walker meeting it makes a STOP
    right (twice it: a SLOW)."""
    return z.reaction_time_s + max(0.0, float(speed_mps)) / z.decel_mps2 + 0.5


def meets_vehicle(p: np.ndarray, v_xy, speed_mps: float, z, rear_m: float,
                  zone_tol_m: float, lateral_tol_m: float, horizon_scale: float = 1.0) -> bool:
    """Does the walker meet the vehicle (:func:`meeting_time`) within ``horizon_scale`` x
    :func:`rest_horizon_s`?"""
    return meeting_time(p, v_xy, speed_mps, z, rear_m, zone_tol_m, lateral_tol_m,
                        rest_horizon_s(speed_mps, z) * horizon_scale) is not None


def stop_onset(is_stop: bool, obstacle_stop: bool, prev_state, episode_open: bool) -> bool:
    """Does a STOP episode begin this cycle: a change into STOP, or the boot STOP (never an
    episode) going on as a STOP for an obstacle -- a vehicle that never left its boot STOP
    because of something in the stop zone was stopped by it (a drive sat 12.8 s in such a
    STOP for nothing and scored 0 false stops). ``prev_state`` None: the first cycle."""
    from hal.types import GateState
    return is_stop and (prev_state not in (None, GateState.STOP) or (
        obstacle_stop and not episode_open and prev_state is not None))


def false_cause(truth: list) -> str:
    """A false stop's cause: a real obstacle in the slow zone just beyond, or nothing."""
    return ("early: real obstacle just beyond the stop zone" if any(o["in_slow"] for o in truth)
            else "phantom: nothing real in the stop or slow zone")


def cause_of(reason: str) -> str:
    """The gate's reason without its numbers: 'obstacle # m ahead in the stop zone (# m)'."""
    return _NUM.sub("#", reason).strip()


class Drive:
    """One closed-loop drive. ``build()`` starts the daemon; ``run()`` drives it for the
    configured time and returns ``{"result", "rows", "events"}``; tests may reach
    ``self.daemon`` / ``self.field`` between the two."""

    def __init__(self, kind: str, seed: int, minutes: float, *, config_data: dict | None = None,
                 stereo_scale: float = 0.25, every: int = 1, zone_tol_m: float = 0.5,
                 lateral_tol_m: float = 0.2, near_m: float = 3.0, hold_m: float = 0.3,
                 sync_updates: bool = True, progress=None, progress_every: int = 300,
                 shadow_config: dict | None = None):
        self.kind, self.seed = kind, int(seed)
        self.minutes = float(minutes)
        self.stereo_scale = float(stereo_scale)
        self.config_data = config_data if config_data is not None else drive_config_data(
            kind, seed, stereo_scale=stereo_scale)
        self.every = max(1, int(every))
        self.zone_tol_m, self.lateral_tol_m = float(zone_tol_m), float(lateral_tol_m)
        self.near_m, self.hold_m = float(near_m), float(hold_m)
        self.sync_updates = bool(sync_updates)
        self.progress, self.progress_every = progress, max(1, int(progress_every))
        # a second configuration's whole config data, judged on this drive's inputs
        # (appliance/campaign_shadow.py); it never drives
        self.shadow_config = shadow_config
        self.shadow = None
        self.daemon = None
        self.field = None
        self.events: list[dict] = []
        self.rows: list[dict] = []

    # ---- set-up ------------------------------------------------------------------------------
    def build(self) -> "Drive":
        data = deep_merge(self.config_data, {"sim": {"scene": self.kind, "seed": self.seed}})
        cfg, d, self.field = start_sim_daemon(data, f"<campaign {self.kind} {self.seed}>")
        self.cfg = cfg
        self.daemon = d
        if self.shadow_config is not None:
            from appliance.campaign_shadow import Shadow
            from appliance.config import parse_config
            from appliance.daemon import sim_config
            sdata = deep_merge(self.shadow_config, {"sim": {"scene": self.kind,
                                                            "seed": self.seed}})
            self.shadow = Shadow(sim_config(parse_config(sdata, f"<shadow {self.kind} "
                                                               f"{self.seed}>"), self.kind),
                                 primary_cfg=cfg)
            self._shadow_events: list[dict] = []
            self._shadow_counts = {"true": 0, "false": 0, "fault": 0}
            self._shadow_missed = 0
            self._shadow_missed_open: set[int] = set()
            self._shadow_prev = None
            self._shadow_episode = None
            self._stop_times = {"primary": [], "shadow": []}
        self.vehicle = self.field.vehicle
        self.scene = self.field.scene
        self.zones = cfg.zones
        self.rate = cfg.loop.rate_hz
        self.n_cycles = int(round(self.minutes * 60.0 * self.rate))
        self._pipe_cpu: list[float] = []
        self._render_cpu: list[float] = []
        for p in d.pipelines:
            p.process = self._timed(p.process, self._pipe_cpu)
        self.field.render = self._timed(self.field.render, self._render_cpu)
        self._novelty = [p.novelty for p in d.pipelines if hasattr(p, "novelty")]
        self._stage: dict[str, list[float]] = {s: [] for s in STAGES}
        self._cycle_ms: list[float] = []
        self.model_samples: list[int] = []
        self.model_bound = None
        self._rss: list[float] = []
        # accounting state
        self._prev_state = None
        self._episode = None            # the STOP episode in progress (its event dict)
        self.counts = {"true": 0, "false": 0, "fault": 0}
        self.missed = 0
        self._missed_open: set[int] = set()   # obstacles in the zone whose miss is counted
        self._streak: dict[int, float] = {}   # obstacle index -> ahead_m when the hold began
        self._streak_t: dict[int, float] = {}  # obstacle index -> t_s when the hold began
        self._first_held: dict[int, float] = {}  # obstacle index -> t_s first held at all
        self._boot_ahead: dict | None = None   # obstacle index -> ahead_m on the first cycle
        self._detected: set[int] = set()      # obstacles with a detection distance already
        self.detections: list[dict] = []
        self.false_stop_s = 0.0
        # seconds the box said SLOW with nothing real in its stop or slow zone and no walker
        # about to meet the vehicle (within the slow horizon): time a user loses that no false
        # stop counts
        self.slow_for_nothing_s = 0.0
        self._prev_collisions = 0
        self._ahead_t: dict[int, float] = {}  # obstacle index -> last time in the path ahead
        self._history = deque(maxlen=int(10 * self.rate))
        p = self.scene.path
        seg = np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))
        self._path_s = np.concatenate([[0.0], np.cumsum(seg)])
        heading = np.unwrap(np.arctan2(np.gradient(p[:, 1]), np.gradient(p[:, 0])))
        self._path_turn = np.abs(np.gradient(heading)) > 1e-3
        d.loop.on_cycle.append(self.on_cycle)
        return self

    @staticmethod
    def _timed(fn, cpu: list):
        def wrapper(*a, **k):
            c0 = time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                cpu.append((time.thread_time() - c0) * 1e3)
        return wrapper

    # ---- truth -------------------------------------------------------------------------------
    def headland(self) -> bool:
        """Off the lanes: the scene says so (``Scene.zone_at``), else the path is turning
        within 3 m of here (coverage U-turns)."""
        s = min(max(self.vehicle.s, 0.0), self.vehicle.path_length_m)
        f = getattr(self.scene, "zone_at", None)
        if callable(f):
            return f(s) == "headland"
        near = np.abs(self._path_s - s) <= 3.0
        return bool(np.any(self._path_turn[near]))

    def truth(self, stop_len_m: float, curvature_1pm=0.0) -> list[dict]:
        """Real obstacles near the vehicle (the simulator's world, hit ones included): per
        obstacle its index, id, class, ``ahead`` (nearest corridor point from the front, inf
        when none), ``d_zone`` (distance of its footprint to the stop zone rectangle), ``pts``
        (footprint in the zones' frame), ``in_stop`` (with the tolerances), ``deep`` (the
        tolerances inside the stop zone), ``pts_vehicle`` / ``ahead_straight`` (the footprint
        in the level vehicle frame, and ``ahead`` in the straight corridor: a collision's
        contact part and the box's cells are judged there). With a ``curvature_1pm`` (the box's zones
        bent along a turn, ``[zones] follow_turn``) all of it is judged in the path's frame
        (appliance/zones.to_path_frame): the corridor is the arc the vehicle drives; with a
        zones.PathBend (``follow_path``) the corridor of the route the vehicle really drives
        (``_driven``: not the box's planned path, which can be an autopilot's legs that cut a
        turn), and a walker's meeting is judged straight ahead, as the movers' decision
        judges it."""
        z = self.zones
        if isinstance(curvature_1pm, PathBend):
            curvature_1pm = self._driven(curvature_1pm)
        rear = self.scene.footprint[0]
        x, y, _ = self.vehicle.pose()
        out = []
        fx, hw = z.front_x_m, z.half_width_m

        def ahead_of(q):
            """How far ahead of the front the footprint ``q`` enters the corridor of its frame
            (inf: never)."""
            inside = (np.abs(q[:, 1]) <= hw + self.lateral_tol_m) & (q[:, 0] >= -rear)
            return float((q[inside, 0] - fx).min()) if inside.any() else math.inf

        for k, o in enumerate(self.field.world.obstacles):
            if math.hypot(o.x - x, o.y - y) > o.radius + fx + 45.0:
                continue
            p = self.vehicle.footprint_in_vehicle(k)
            if not len(p):
                continue
            p_vehicle = p
            if curvature_1pm:
                p = to_path_frame(p, curvature_1pm, fx)
            ay = np.abs(p[:, 1])
            ahead = ahead_of(p)
            # the straight corridor's, whatever the box's zones
            ahead_straight = ahead if p is p_vehicle else ahead_of(p_vehicle)
            dx = np.maximum(0.0, np.maximum(fx - p[:, 0], p[:, 0] - (fx + stop_len_m)))
            dy = np.maximum(0.0, ay - hw)
            deep = (ay <= hw - self.lateral_tol_m) & (p[:, 0] >= fx - 0.0) & \
                (p[:, 0] <= fx + stop_len_m - self.zone_tol_m)
            out.append({"k": k, "id": o.id, "cls": o.cls, "ahead": ahead, "pts": p,
                        "pts_vehicle": p_vehicle, "ahead_straight": ahead_straight,
                        "d_zone": float(np.hypot(dx, dy).min()),
                        **(self._meets(o, p_vehicle, rear, 0.0)
                           if isinstance(curvature_1pm, PathBend)
                           else self._meets(o, p, rear, curvature_1pm)),
                        "in_stop": ahead <= stop_len_m + self.zone_tol_m,
                        "in_slow": stop_len_m + self.zone_tol_m < ahead
                        <= stop_len_m + z.slow_extra_m + self.zone_tol_m,
                        "deep": bool(deep.any())})
        return out

    def _driven(self, bend: PathBend) -> PathBend:
        """The zones of ``bend`` (the box's, along its planned path) laid along the route the
        simulated vehicle will really drive, for judging what was in them. The box's path is
        the route itself with ``[sim] path = "route"`` (the same corridor), an autopilot's legs
        with ``"mission"`` (which go straight where the vehicle turns). Off the route (the
        driver's detour) the box's own corridor."""
        route = self.vehicle.planned_path(reach_m=bend.reach_m + 1.0)
        if len(route) < 2 or math.hypot(*route[0]) > self.zones.path_max_offset_m:
            return bend
        return PathBend(route, bend.front_x_m, bend.half_width_m, reach_m=bend.reach_m,
                        rear_m=bend.rear_m)

    def _meets(self, o, p: np.ndarray, rear: float, curvature_1pm: float) -> dict:
        """``meets`` / ``meets_slow``: a walker walking now that, going on at its true velocity
        while the vehicle drives on at its speed, meets the vehicle (within the zones' width +
        lateral_tol_m, from its rear to the front + zone_tol_m) within :func:`rest_horizon_s`
        (a STOP for it is a true stop, as for an obstacle in the stop zone) / within twice it
        (caution for it is right, cycles.csv ``real_meets``). Straight ahead: in a turn, not
        judged."""
        no = {"meets": False, "meets_slow": False}
        t_now = float(getattr(self.field.world, "time_s", 0.0))
        if curvature_1pm or not getattr(o, "moving", False):
            return no
        vx, vy = o.velocity_now(t_now)
        if vx == 0.0 and vy == 0.0:
            return no
        speed = max(0.0, float(self.vehicle.speed))
        _, _, yaw = self.vehicle.pose()
        c, s_ = math.cos(yaw), math.sin(yaw)
        h = rest_horizon_s(speed, self.zones)
        t = meeting_time(p, (vx * c + vy * s_, -vx * s_ + vy * c), speed, self.zones, rear,
                         self.zone_tol_m, self.lateral_tol_m, 2.0 * h)
        return {"meets": t is not None and t <= h + 1e-9, "meets_slow": t is not None}

    def _held(self, cells: np.ndarray, pts: np.ndarray) -> bool:
        """Do the box's occupied cells lie on this footprint (within hold_m)?"""
        if not len(cells):
            return False
        lo, hi = pts.min(0) - self.hold_m, pts.max(0) + self.hold_m
        c = cells[(cells[:, 0] >= lo[0]) & (cells[:, 0] <= hi[0]) &
                  (cells[:, 1] >= lo[1]) & (cells[:, 1] <= hi[1])]
        if not len(c):
            return False
        d2 = ((c[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
        return bool(d2.min() <= self.hold_m ** 2)

    def _pipelines_in_stop(self, res, stop_len: float, curvature_1pm=0.0,
                           detections: dict | None = None) -> list[str]:
        """The pipelines with a point in the stop zone this cycle (``detections``, or the
        drive's own in ``res``)."""
        z = self.zones
        names = []
        for n, det in (res.detections if detections is None else detections).items():
            if det is None:
                continue
            p = det.points_xy
            if len(p):
                p = to_path_frame(p, curvature_1pm, z.front_x_m)
                a = p[:, 0] - z.front_x_m
                if np.any((a >= 0) & (a <= stop_len) & (np.abs(p[:, 1]) <= z.half_width_m)):
                    names.append(n)
        return names

    # ---- per cycle ---------------------------------------------------------------------------
    def _shadow_cycle(self, res, t_s: float, truth: list, stop_len: float, kappa: float,
                      place: str) -> None:
        """The shadow configuration on this cycle's inputs, scored as the drive's own STOPs
        are (true / false / fault onsets, missed stops) against the same truth; its stop zone
        is its own verdict's (the truth is recomputed when that differs)."""
        from hal.types import GateState
        out, pic, faults = self.shadow.step(res)
        if self.sync_updates:
            self.shadow.wait_idle()
        verdict = None if pic is None else pic.verdict
        s_len = verdict.stop_len_m if verdict is not None else self.zones.min_stop_m
        s_kappa = bend_of(pic)
        if abs(s_len - stop_len) > 1e-9 or not same_bend(s_kappa, kappa):
            truth = self.truth(s_len, s_kappa)
        state = out.state
        is_stop = state is GateState.STOP
        obstacle_stop = is_stop and "stop zone" in out.reason
        in_stop = [o for o in truth if o["in_stop"] or o["meets"]]
        if is_stop:
            self._stop_times["shadow"].append(t_s)
        if stop_onset(is_stop, obstacle_stop, self._shadow_prev,
                      self._shadow_episode is not None):
            fault = not obstacle_stop and not out.reason.startswith("holding")
            kind = "fault" if fault and faults else ("true" if in_stop else "false")
            pipes = self._pipelines_in_stop(res, s_len, s_kappa, self.shadow.last_detections)
            cause = cause_of(out.reason)
            if kind == "false":                # named as the drive's own false stops are
                cause = false_cause(truth) + (f" [{'+'.join(pipes)}]" if pipes else "")
            ev = {"t_s": round(t_s, 1), "event": "stop", "kind": kind, "reason": out.reason,
                  "cause": cause, "place": place, "stop_zone_m": round(s_len, 2),
                  "pipelines": pipes,
                  "primary_state": res.output.state.value, "duration_s": None}
            self._shadow_counts[kind] += 1
            self._shadow_events.append(ev)
            self._shadow_episode = ev
        if not is_stop and self._shadow_episode is not None:
            self._shadow_episode["duration_s"] = round(t_s - self._shadow_episode["t_s"], 1)
            self._shadow_episode = None
        for o in truth:
            k = o["k"]
            if o["deep"] and not is_stop and k not in self._shadow_missed_open:
                self._shadow_missed_open.add(k)
                self._shadow_missed += 1
                self._shadow_events.append({"t_s": round(t_s, 1), "event": "missed",
                                            "kind": o["cls"], "reason": out.reason,
                                            "obstacle": f"{o['id']}/{o['cls']}",
                                            "primary_state": res.output.state.value})
            elif not o["in_stop"]:
                self._shadow_missed_open.discard(k)
        self._shadow_prev = state

    def shadow_result(self) -> dict | None:
        """The shadow's figures on this drive (None without one): its own stop counts, and
        the two sides' false and true stops that the other side did not share (no STOP of
        the other's within 0.5 s: campaign_shadow.paired)."""
        if self.shadow is None:
            return None
        from appliance.campaign_shadow import paired
        stops = [e for e in self._shadow_events if e["event"] == "stop"]
        own = [e for e in self.events if e["event"] == "stop"]
        return {"true_stops": self._shadow_counts["true"],
                "false_stops": self._shadow_counts["false"],
                "fault_stops": self._shadow_counts["fault"],
                "missed_stops": self._shadow_missed,
                # "shared": the drive's own detections (the same perception), "own": its own
                # pipelines run on the drive's inputs
                "perception": "shared" if self.shadow.shared else "own",
                **paired(own, stops, self._stop_times),
                "events": self._shadow_events}

    def on_cycle(self, res) -> None:
        from hal.types import GateState
        v = self.vehicle
        out = res.output
        state = out.state
        t_s = res.index / self.rate
        stop_len = res.verdict.stop_len_m if res.verdict is not None else self.zones.min_stop_m
        kappa = bend_of(res)                           # what the box laid its zones along
        truth = self.truth(stop_len, kappa)
        cells = np.asarray(res.cells_xy, np.float64).reshape(-1, 2)
        x, y, yaw = v.pose()
        is_stop = state is GateState.STOP
        obstacle_stop = is_stop and "stop zone" in out.reason
        # what a STOP is right for: an obstacle in the stop zone, or a walker about to meet the
        # vehicle ([tracking] movers stops for those before they are in the zone)
        in_stop = [o for o in truth if o["in_stop"] or o["meets"]]
        near = [o for o in truth if o["d_zone"] <= self.near_m]
        # detection streaks of the in-path obstacles ahead
        if self._boot_ahead is None:          # the first cycle: what stood where at the start
            self._boot_ahead = {o["k"]: (round(o["ahead"], 2) if math.isfinite(o["ahead"])
                                         else None) for o in truth}
        for o in truth:
            k = o["k"]
            # in the straight corridor ahead (a collision's contact: what a forward-looking
            # box is there to see, whatever its zones followed)
            if math.isfinite(o["ahead_straight"]) and o["ahead_straight"] >= 0.0:
                self._ahead_t[k] = t_s
            if math.isfinite(o["ahead"]) and o["ahead"] >= -0.5 and \
                    self._held(cells, o["pts_vehicle"]):     # the box's cells: vehicle frame
                self._streak.setdefault(k, o["ahead"])
                self._streak_t.setdefault(k, t_s)
                self._first_held.setdefault(k, t_s)
            else:
                self._streak.pop(k, None)
                self._streak_t.pop(k, None)
        place = "near an obstacle" if near else ("headland" if self.headland() else "lane")
        # STOP episodes (stop_onset)
        if stop_onset(is_stop, obstacle_stop, self._prev_state, self._episode is not None):
            fault = not obstacle_stop and not out.reason.startswith("holding")
            nearest = min(in_stop, key=lambda o: (not o["in_stop"], o["ahead"])) \
                if in_stop else None
            kind = "fault" if fault and res.faults else ("true" if nearest else "false")
            pipes = self._pipelines_in_stop(res, stop_len, kappa)
            cause = cause_of(out.reason)
            if kind == "false":
                cause = false_cause(truth) + (f" [{'+'.join(pipes)}]" if pipes else "")
            ev = {"t_s": round(t_s, 1), "event": "stop", "kind": kind, "x_m": round(x, 2),
                  "y_m": round(y, 2), "speed_mps": round(v.speed, 2),
                  "stop_zone_m": round(stop_len, 2), "reason": out.reason, "cause": cause,
                  "place": place, "pipelines": pipes,
                  "obstacle": f"{nearest['id']}/{nearest['cls']}" if nearest else "",
                  "real_nearest_m": None if nearest is None or not math.isfinite(
                      nearest["ahead"]) else round(nearest["ahead"], 2),
                  "duration_s": None}
            self.counts[kind] += 1
            self.events.append(ev)
            self._episode = ev
            if kind == "true" and nearest["k"] not in self._detected:
                self._detected.add(nearest["k"])
                start = self._streak.get(nearest["k"])
                self.detections.append({
                    "obstacle": nearest["id"], "cls": nearest["cls"],
                    "t_s": round(t_s, 1),
                    "distance_m": None if start is None else round(start, 2),
                    "held_from_s": None if start is None
                    else round(self._streak_t[nearest["k"]], 1),
                    "ahead_at_stop_m": round(nearest["ahead"], 2)
                    if math.isfinite(nearest["ahead"]) else None,
                    "speed_mps": round(v.speed, 2)})
        if not is_stop and self._episode is not None:
            self._episode["duration_s"] = round(t_s - self._episode["t_s"], 1)
            self._episode = None
        if obstacle_stop and not in_stop:
            self.false_stop_s += 1.0 / self.rate
        if state is GateState.SLOW and not any(
                o["in_stop"] or o["in_slow"] or o["meets"] or o.get("meets_slow")
                for o in truth):
            self.slow_for_nothing_s += 1.0 / self.rate
        # missed stops: a real obstacle deep in the stop zone and no STOP
        for o in truth:
            k = o["k"]
            if o["deep"] and not is_stop and k not in self._missed_open:
                self._missed_open.add(k)
                self.missed += 1
                self.events.append({"t_s": round(t_s, 1), "event": "missed", "kind": o["cls"],
                                    "x_m": round(x, 2), "y_m": round(y, 2),
                                    "speed_mps": round(v.speed, 2),
                                    "stop_zone_m": round(stop_len, 2), "reason": out.reason,
                                    "cause": f"box said {state.value}", "place": place,
                                    "obstacle": f"{o['id']}/{o['cls']}",
                                    "real_nearest_m": round(o["ahead"], 2)})
            elif not o["in_stop"]:
                self._missed_open.discard(k)
        # collisions (the sim vehicle counts them)
        if v.collisions > self._prev_collisions:
            rear = self.scene.footprint[0]
            for oid in v.obstacles_hit[self._prev_collisions:]:
                k, o = next((k, ob) for k, ob in enumerate(self.field.world.obstacles)
                            if ob.id == oid)
                seen_t = self._ahead_t.get(k)
                contact = contact_part(v.footprint_in_vehicle(k), rear, seen_t is not None and
                                       t_s - seen_t <= CONTACT_AHEAD_S + 1e-9)
                self.events.append({"t_s": round(t_s, 1), "event": "collision", "kind": o.cls,
                                    "contact": contact,
                                    "x_m": round(x, 2), "y_m": round(y, 2),
                                    "speed_mps": round(v.speed, 2),
                                    "stop_zone_m": round(stop_len, 2), "reason": out.reason,
                                    "cause": f"box said {state.value}", "place": place,
                                    "obstacle": f"{o.id}/{o.cls}", "real_nearest_m": 0.0})
            self._prev_collisions = v.collisions
        self._prev_state = state
        if self.shadow is not None:
            if is_stop:
                self._stop_times["primary"].append(t_s)
            self._shadow_cycle(res, t_s, truth, stop_len, kappa, place)
        # the model, memory and time
        samples = None
        for nd in self._novelty:
            u = nd.updater
            if self.sync_updates and u is not None and not u.wait_idle(600.0):
                # a wait that gave up would let the next frame see the old model: the drive
                # would no longer be reproducible (seen at load 50 with a 30 s wait)
                raise RuntimeError("the novelty model's update did not finish in 600 s")
            if self.model_bound is None:
                for det in res.detections.values():
                    if "grid" in det.debug:
                        r, c = det.debug["grid"]
                        self.model_bound = nd.model.max_size(r * c)
        if self._novelty:
            samples = int(self._novelty[0].model.size)
            self.model_samples.append(samples)
        for s in STAGES:
            self._stage[s].append(res.wall_ms.get(s, 0.0))
        self._cycle_ms.append(sum(res.wall_ms.values()))
        if res.index % self.every == 0:
            nearest_real = min((o["ahead"] for o in truth), default=math.inf)
            nr = min(truth, key=lambda o: o["ahead"]) if truth else None
            self.rows.append({
                "t_s": round(t_s, 1), "x_m": round(x, 2), "y_m": round(y, 2),
                "yaw_deg": round(math.degrees(yaw), 1), "speed_mps": round(v.speed, 2),
                "state": state.value, "reason": out.reason,
                "nearest_m": None if res.verdict is None or res.verdict.nearest_m is None
                else round(res.verdict.nearest_m, 2),
                "stop_zone_m": round(stop_len, 2), "cells": int(len(cells)),
                "real_nearest_m": None if not math.isfinite(nearest_real)
                else round(nearest_real, 2),
                "real_obstacle": "" if nr is None or not math.isfinite(nr["ahead"])
                else f"{nr['id']}/{nr['cls']}",
                # a walker that meets the vehicle within twice the time to rest + 0.5 s if
                # both go on (the movers' SLOW reach): caution for it is right
                "real_meets": " ".join(f"{o['id']}/{o['cls']}" for o in truth
                                       if o["meets_slow"]),
                "place": place, "collisions": v.collisions, "stops_true": self.counts["true"],
                "stops_false": self.counts["false"], "missed_stops": self.missed,
                "detours": v.detours, "overrides": v.overrides,
                "model_samples": samples,
                **{f"{s}_ms": round(res.wall_ms.get(s, 0.0), 2) for s in STAGES},
                "render_cpu_ms": round(self._render_cpu[-1], 2) if self._render_cpu else None,
                "pipeline_cpu_ms": round(self._pipe_cpu[-1], 2) if self._pipe_cpu else None})
        if res.index % self.progress_every == 0:
            self._rss.append(rss_mb())
            if self.progress is not None:
                self.progress(res.index, self.n_cycles)

    # ---- the drive ---------------------------------------------------------------------------
    def run(self) -> dict:
        import cv2
        if self.daemon is None:
            self.build()
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)          # one core per drive, and the same answer anywhere
        d = self.daemon
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            d.run(max_cycles=self.n_cycles)
        finally:
            wall_s, cpu_s = time.perf_counter() - w0, time.process_time() - c0
            if self._episode is not None:
                self._episode["duration_s"] = round(
                    d.loop.cycles / self.rate - self._episode["t_s"], 1)
            d.shutdown()
            if self.shadow is not None:
                self.shadow.close()
            cv2.setNumThreads(threads)
        return {"result": self.result(wall_s, cpu_s), "rows": self.rows,
                "events": self.events}

    def _at_boot(self) -> list[dict]:
        """What became of the obstacles standing in view when the box started (the scene's
        ``placement == "at-boot"``: stubble-boot): how far ahead of the front it stood at the
        start, when the box's cells first lay on it, its stop (``held_from_s``: the start of
        the unbroken hold that ended in it; ``held_from_first_s``: that hold began within the
        first second), and whether it was run into or missed."""
        out = []
        for k, o in enumerate(self.field.world.obstacles):
            if getattr(o, "placement", "") != "at-boot":
                continue
            tag = f"{o.id}/{o.cls}"
            det = next((d for d in self.detections if d["obstacle"] == o.id), None)
            held_from = None if det is None else det.get("held_from_s")
            out.append({
                "obstacle": tag, "cls": o.cls, "tone": getattr(o, "tone", ""),
                "ahead_at_start_m": (self._boot_ahead or {}).get(k),
                "first_held_s": None if k not in self._first_held
                else round(self._first_held[k], 1),
                "stopped": det is not None,
                "stop_t_s": None if det is None else det["t_s"],
                "held_from_s": held_from,
                "held_from_first_s": held_from is not None and held_from <= 1.0,
                "collision": o.id in self.vehicle.obstacles_hit,
                "missed": any(e["event"] == "missed" and e["obstacle"] == tag
                              for e in self.events)})
        return out

    def result(self, wall_s: float, cpu_s: float) -> dict:
        from appliance.zones import stop_length
        v = self.vehicle
        st = v.stats()
        cycles = self.daemon.loop.cycles
        sim_s = cycles / self.rate
        cal = getattr(self.field, "stereo_calibration", None)
        by_place: dict[str, int] = {}
        by_cause: dict[str, int] = {}
        by_contact: dict[str, int] = {}
        boot = 0
        for e in self.events:
            if e["event"] == "collision":
                by_contact[e["contact"]] = by_contact.get(e["contact"], 0) + 1
            if e["event"] == "stop" and e["kind"] == "false":
                by_place[e["place"]] = by_place.get(e["place"], 0) + 1
                by_cause[e["cause"]] = by_cause.get(e["cause"], 0) + 1
                boot += e["t_s"] < BOOT_S
        cruise = self.scene.cruise_mps
        bound = self.model_bound
        self._rss.append(rss_mb())
        return {
            "kind": self.kind, "seed": self.seed, "minutes": self.minutes,
            "stereo_scale": self.stereo_scale,
            "image_px": None if cal is None else [cal.camera.width, cal.camera.height],
            "pipelines": list(self.cfg.perception.pipelines),
            "cycles": cycles, "simulated_s": round(sim_s, 1),
            "distance_m": round(float(st["distance_m"]), 2),
            "finished_path": bool(st.get("finished", False)),
            "collisions": int(v.collisions),
            "collided_with": list(v.obstacles_hit),
            "collisions_by_contact": by_contact,
            "true_stops": self.counts["true"], "false_stops": self.counts["false"],
            "fault_stops": self.counts["fault"], "missed_stops": self.missed,
            "false_stops_boot": boot,
            "false_stop_s": round(self.false_stop_s, 1),
            "slow_for_nothing_s": round(self.slow_for_nothing_s, 1),
            "false_stops_by_place": by_place, "false_stops_by_cause": by_cause,
            "detours": int(v.detours), "overrides": int(v.overrides),
            "detections": self.detections,
            "at_boot": self._at_boot(),
            "cruise_mps": cruise,
            "stopping_distance_at_cruise_m": {
                "box_stop_zone": round(stop_length(cruise, self.zones), 2),
                "vehicle_braking": round(cruise * cruise / (2 * v.decel_mps2), 2)},
            "model": {"samples_max": max(self.model_samples, default=None),
                      "samples_last": self.model_samples[-1] if self.model_samples else None,
                      "bound": bound, "bytes_per_sample": 40,
                      "bytes_max": None if not self.model_samples else
                      40 * max(self.model_samples)},
            "timing": {
                "wall_s": round(wall_s, 1), "process_cpu_s": round(cpu_s, 1),
                "stage_wall_ms_p50": {s: pct(self._stage[s], 50) for s in STAGES},
                "stage_wall_ms_p99": {s: pct(self._stage[s], 99) for s in STAGES},
                "cycle_wall_ms_p50": pct(self._cycle_ms, 50),
                "pipeline_cpu_ms_p50": pct(self._pipe_cpu, 50),
                "render_cpu_ms_p50": pct(self._render_cpu, 50),
                "rss_mb_max": None if not self._rss else round(max(self._rss), 1),
                "rss_mb_last": None if not self._rss else round(self._rss[-1], 1),
                "overruns": self.daemon.loop.overruns,
            },
            **({} if self.shadow is None else {"shadow": self.shadow_result()}),
        }
