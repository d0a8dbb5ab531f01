"""One TOML file, validated into frozen dataclasses.

An unknown key, a value of the wrong type or out of range, or an unknown device ``type`` stops
start-up with a :class:`hal.ConfigError` that names the file and the key. Every key has a
default, so an empty file (or no file) is a valid configuration for the simulated field.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from appliance.perception import pipeline_options  # noqa: F401 (the CLI reads options here)
from appliance.perception.laser import LaserPipelineConfig
from appliance.schema import _f
from hal.errors import ConfigError


@dataclass(frozen=True)
class LoopConfig:
    rate_hz: float = _f(10.0, lo=1.0, hi=100.0, doc="cycle rate of the loop")
    lag_cycles_fault: int = _f(3, lo=1, hi=100, doc="consecutive overrun cycles that are a fault")
    budget_acquire_ms: float = _f(10.0, lo=0.1)
    budget_perception_ms: float = _f(60.0, lo=0.1)
    budget_fusion_ms: float = _f(10.0, lo=0.1)
    budget_gate_ms: float = _f(5.0, lo=0.1)
    budget_send_ms: float = _f(10.0, lo=0.1)


@dataclass(frozen=True)
class GateConfig:
    hold_off_s: float = _f(1.0, lo=0.0, hi=60.0, doc="zone clear this long before a stop is released")
    required: tuple = _f((), doc="device names that must be fresh for CLEAR; empty = every device")


@dataclass(frozen=True)
class ExclusionZone:
    """A box in the vehicle frame that is never an obstacle (the vehicle's own implement)."""

    x_min_m: float = _f(0.0)
    x_max_m: float = _f(0.0)
    y_min_m: float = _f(0.0)
    y_max_m: float = _f(0.0)


@dataclass(frozen=True)
class ZonesConfig:
    front_x_m: float = _f(2.6, lo=-10, hi=20, doc="front of the vehicle, metres ahead of its origin")
    half_width_m: float = _f(1.25, lo=0.1, hi=20, doc="half the width of the swept path incl. margin")
    reaction_time_s: float = _f(0.5, lo=0.0, hi=5.0)
    decel_mps2: float = _f(2.0, lo=0.1, hi=10.0, doc="braking deceleration the vehicle can rely on")
    margin_m: float = _f(1.0, lo=0.0, hi=20.0)
    min_stop_m: float = _f(2.0, lo=0.0, hi=50.0, doc="shortest stop zone, at standstill")
    slow_extra_m: float = _f(5.0, lo=0.0, hi=50.0, doc="slow-down zone beyond the stop zone")
    slow_speed_mps: float = _f(1.0, lo=0.0, hi=20.0)
    exclusion: tuple = _f((), doc="list of {x_min_m, x_max_m, y_min_m, y_max_m}")
    follow_turn: bool = _f(False, doc="bend the stop and slow zones along the arc the vehicle "
                                      "drives at its present curvature (yaw rate / speed; the "
                                      "last one while it stands): what lies on the straight "
                                      "line out of a turn is not in the path (docs/zones.md)")
    max_curvature_1pm: float = _f(2.0, lo=0.0, hi=10.0,
                                  doc="follow_turn: curvatures beyond this (a radius under "
                                      "1/this) are taken as this")
    follow_path: bool = _f(False, doc="lay the stop and slow zones along the path the vehicle "
                                      "will drive, when its vehicle link hands one on (the "
                                      "MAVLink link's mission_path; the simulator: [sim] "
                                      "path); without a usable path this "
                                      "cycle, the zones are straight (or follow_turn's)")
    body_rear_m: float = _f(0.0, lo=0.0, hi=20.0,
                            doc="follow_path: how far the vehicle's body reaches behind its "
                                "origin (the zones are what the body sweeps along the path; "
                                "in a tight turn its tail swings out)")
    path_max_offset_m: float = _f(0.5, lo=0.0, hi=5.0,
                                  doc="follow_path: a path whose first point is further than "
                                      "this from the vehicle's origin (the vehicle is not on "
                                      "it) is not used")
    path_max_heading_deg: float = _f(45.0, lo=0.0, hi=180.0,
                                     doc="follow_path: a path whose first metre heads more "
                                         "than this off the vehicle's heading is not used "
                                         "(the vehicle is not driving it yet: an autopilot's "
                                         "next leg in the middle of its turn)")


@dataclass(frozen=True)
class GridConfig:
    cell_m: float = _f(0.1, lo=0.01, hi=1.0)
    x_min_m: float = _f(-2.0)
    x_max_m: float = _f(30.0)
    y_min_m: float = _f(-15.0)
    y_max_m: float = _f(15.0)
    decay: float = _f(0.5, lo=0.0, hi=0.99, doc="evidence kept from one cycle to the next")
    occupied_at: float = _f(1.4, lo=0.1, hi=100.0,
                            doc="evidence to call a cell occupied (1.0 = one frame is enough)")
    stop_at: float = _f(0.0, lo=0.0, hi=100.0,
                        doc="cell decision: evidence an occupied cell in the stop zone needs to "
                            "make a STOP (0 = occupied_at, the papers' rule); an occupied cell "
                            "there with less is a SLOW (docs/tracking.md, 'False stops')")
    stop_chain: int = _f(0, lo=0, hi=50,
                         doc="cell decision: a STOP needs an occupied cell in the stop zone at the "
                             "end of a chain of hits in this many cycles running, each within "
                             "stop_chain_radius_m of the last (an object that stays, or moves no "
                             "faster than the radius a cycle); a shorter chain is a SLOW "
                             "(0 = off; docs/tracking.md, 'Chains')")
    stop_chain_radius_m: float = _f(0.3, lo=0.0, hi=2.0,
                                    doc="how far a chain (or a recurrence) may move in one "
                                        "cycle (0.3 m = 3 m/s at 10 Hz)")
    stop_recur: float = _f(1.3, lo=0.0, hi=20.0,
                           doc="cell decision: a STOP needs an occupied stop-zone cell whose "
                               "recurrence reaches this: 1 for this cycle plus "
                               "stop_recur_decay^k for each earlier cycle k back in which a cell "
                               "within k x stop_chain_radius_m was occupied (tolerates flicker, "
                               "unlike stop_at and stop_chain); less is a SLOW (0 = off, "
                               "the papers' rule; docs/tracking.md 'stop_recur on the "
                               "acceptance seeds')")
    stop_recur_decay: float = _f(0.7, lo=0.0, hi=0.99)
    # Off (thirty-eighth session): 1.3 took a fifth to a quarter of the SLOW-for-nothing
    # time away but the phantoms a slowed vehicle had kept in its slow zone met a vehicle at
    # cruise in its stop zone: false stops 4 -> 7 (training), 19 -> 33 (acceptance)
    slow_recur: float = _f(0.0, lo=0.0, hi=20.0,
                           doc="cell decision: an occupied cell in the slow zone (beyond the "
                               "stop zone) makes a SLOW only when its recurrence (as "
                               "stop_recur's) reaches this; 0 = at once (as before). A stop-zone "
                               "cell not yet confirmed for a STOP is a SLOW either way "
                               "(docs/tracking.md 'SLOW for nothing, and [grid] slow_recur')")
    stop_recur_now: tuple = _f((),
                               doc="pipelines whose hits in a stop-zone cell make it a STOP at "
                                   "once, recurrent or not; [] = every pipeline waits for the "
                                   "recurrence (the laser too: a tuft top it grazes comes and "
                                   "goes; docs/proving-ground.md 'Tuft tops'); [\"laser\"] was "
                                   "the default before")
    confirm_points: int = _f(300, lo=0, hi=1_000_000,
                             doc="fewer frames when near and large (issue #14): the cells hit "
                                 "by the points of a candidate with at least this many points "
                                 "(of the pipelines in confirm_pipelines) are occupied at once, "
                                 "without the second look (a STOP still needs stop_recur); "
                                 "only beyond confirm_min_ahead_m of the front; 0 = off "
                                 "(docs/rgbd.md 'Large candidates at once')")
    confirm_pipelines: tuple = _f(("rgbd",),
                                  doc="confirm_points: the pipelines whose large candidates are "
                                      "believed at once")
    confirm_sources: tuple = _f((), doc="confirm_points: a candidate must also carry one of "
                                        "these cues (e.g. [\"colour\"]: not texture alone, "
                                        "which a near bush row raises); [] = any")
    confirm_min_ahead_m: float = _f(1.0, lo=0.0, hi=20.0,
                                    doc="confirm_points: only a candidate whose near edge is at "
                                        "least this far ahead of the front (zones.front_x_m) is "
                                        "believed at once; nearer ones wait for the second look "
                                        "(a bush row faced at an end bay, 0.6-0.8 m ahead); "
                                        "0 = anywhere (made the greenhouse's own phantoms at "
                                        "the end bays: docs/rgbd.md)")

    laser_confirm_by: tuple = _f((), doc="cell decision: a laser return inside a camera "
                                         "pipeline's view this cycle makes a STOP only where "
                                         "that camera confirms it by one of these: \"novelty\", "
                                         "\"learned\", \"depth\" (its masks at the return's "
                                         "place in the image), \"points\" (its obstacle points "
                                         "within laser_confirm_radius_m); an unconfirmed return "
                                         "still makes a SLOW. Returns outside every camera's "
                                         "view or range, and every return in a cycle without a "
                                         "camera, count as before. [] = off (docs/proving-"
                                         "ground.md 'The laser confirmed by the camera')")
    # On by default since the thirty-third session: on training seeds it turned 2 of 3
    # collisions into held stops, on the acceptance seeds it cost no stop and 1.37x the time
    # stood in false stops (the rule asked <= 1.5x; docs/tracking.md 'Out of sight')
    hold_blind: bool = _f(True, doc="an obstacle cell (with [tracking] enabled: a confirmed "
                                      "track) confirmed near the "
                                      "front that then lies where no camera pipeline can see "
                                      "it (under its view, or nearer than its stereo can "
                                      "range) is held as a confirmed obstacle while it stays "
                                      "there and ahead of the front, instead of fading: a box "
                                      "that stopped for a crate 1.5 m ahead must not call "
                                      "CLEAR because the crate went out of its sight (the "
                                      "vehicle drove into it). Needs a camera pipeline that "
                                      "gives a view (stereo-novelty); false = the papers' "
                                      "fading cells (docs/tracking.md 'Out of sight')")
    hold_blind_probe_m: float = _f(0.5, lo=0.0, hi=5.0,
                                   doc="hold_blind: a cell counts as seen when a point this "
                                       "high above it is observed (the band's floor: what "
                                       "is lower makes no obstacle point)")
    hold_blind_min_evidence: float = _f(1.75, lo=0.0, hi=100.0,
                                        doc="hold_blind, cell decision: only a confirmed "
                                            "cell whose grid "
                                            "evidence reached this in the cycle before it went "
                                            "out of sight is held (1.75: hit in three cycles "
                                            "running; a stubble blip at the near edge of the "
                                            "view is seen in one or two); 0 = any confirmed "
                                            "cell")
    # false by default since the thirty-fifth session (training 121-132: the same stops,
    # collisions and overrides, 1.4 s less stood in false stops; docs/tracking.md)
    hold_blind_laser: bool = _f(False, doc="hold_blind: also hold what only the laser saw (a "
                                           "cell no camera pipeline's points hit while it was "
                                           "confirmed; a track seen by no other source); "
                                           "false = the hold is for what a camera saw and "
                                           "then could not (the laser does not lose sight of "
                                           "what stands in its plane before the vehicle, and "
                                           "its returns beside the path, where no camera "
                                           "looks, are not kept). docs/tracking.md "
                                           "'Laser-only cells'")
    hold_blind_range_m: float = _f(3.0, lo=0.0, hi=30.0,
                                   doc="hold_blind: only cells at most this far ahead of the "
                                       "front (zones.front_x_m) are held (the near blind "
                                       "region; farther out, what leaves the view is beside "
                                       "the path)")
    hold_blind_look_frames: int = _f(0, lo=0, hi=1000,
                                     doc="hold_blind: a held cell is let go when a camera that "
                                         "keeps its frame's pair (stereo-novelty) has looked "
                                         "again and seen past it (nothing upright at its place "
                                         "from 0.5 to 1 m up: appliance/perception/look.py) in "
                                         "this many cycles running: a stubble phantom held at a "
                                         "standstill ends; a thing the camera sees, or cannot "
                                         "tell (too little texture, a flat match), stays held. "
                                         "0 = off (a hold ends only when the cell is back in "
                                         "the stereo's range or leaves the region)")
    laser_confirm_radius_m: float = _f(0.3, lo=0.05, hi=2.0,
                                       doc="laser_confirm_by \"points\": a camera point in the "
                                           "same or a neighbouring square of this side")


@dataclass(frozen=True)
class SourceWeights:
    """Log-odds each cue adds to a track per frame at full strength (docs/tracking.md)."""

    laser: float = _f(1.0, lo=0.0, hi=10.0)
    geometry: float = _f(0.7, lo=0.0, hi=10.0, doc="height above ground from stereo or depth")
    novelty: float = _f(0.5, lo=0.0, hi=10.0)
    cue: float = _f(0.5, lo=0.0, hi=10.0, doc="the learned cue")
    colour: float = _f(0.7, lo=0.0, hi=10.0, doc="RGB-D colour class")
    texture: float = _f(0.4, lo=0.0, hi=10.0)


@dataclass(frozen=True)
class TrackingConfig:
    """Obstacle tracks in the world (odometry) frame and the decision on them (docs/tracking.md).
    ``enabled = false`` is the cell-based decision of the papers' reproduction tables."""

    enabled: bool = _f(False, doc="decide on confirmed tracks (false: on occupied cells)")
    input: str = _f("occupied", choices=("occupied", "hits"),
                    doc="cluster the grid's occupied cells (hit in consecutive cycles) or "
                        "every cell hit this cycle")
    cluster_gap_m: float = _f(0.3, lo=0.0, hi=3.0, doc="cells this close join one candidate")
    min_cells: int = _f(1, lo=1, hi=1000, doc="smallest candidate, in cells")
    support_cells: float = _f(3.0, lo=0.1, hi=1000.0,
                              doc="cells at which a source's strength is 1 - 1/e")
    gate_m: float = _f(1.0, lo=0.05, hi=10.0, doc="association gate beyond the footprints")
    meas_noise_m: float = _f(0.15, lo=0.01, hi=5.0)
    accel_noise_mps2: float = _f(2.0, lo=0.01, hi=50.0)
    source_cap_frames: float = _f(3.0, lo=0.1, hi=100.0,
                                  doc="one source's log-odds are capped at weight x this")
    confirm_logodds: float = _f(2.0, lo=0.0, hi=100.0)
    release_logodds: float = _f(0.5, lo=0.0, hi=100.0, doc="a confirmed track below this ends")
    miss_logodds: float = _f(0.5, lo=0.0, hi=100.0, doc="taken from each source on a miss")
    confirm_frames_min: int = _f(2, lo=1, hi=100, doc="frames for a near, large candidate")
    confirm_frames_max: int = _f(4, lo=1, hi=100, doc="frames for a far, small candidate")
    near_m: float = _f(6.0, lo=0.0, hi=100.0)
    far_m: float = _f(18.0, lo=0.1, hi=100.0)
    large_m: float = _f(0.8, lo=0.01, hi=20.0, doc="footprint (longest side) counted as large")
    small_m: float = _f(0.2, lo=0.0, hi=20.0)
    coast_s: float = _f(0.5, lo=0.0, hi=10.0, doc="a confirmed track is kept this long unseen")
    tentative_coast_s: float = _f(0.15, lo=0.0, hi=10.0)
    max_speed_mps: float = _f(50.0, lo=0.0, hi=50.0,
                              doc="faster over ground: not an obstacle (50 = off: at 2.5 the "
                                  "noisy speed of stereo clusters unconfirmed real obstacles)")
    comoving_mps: float = _f(0.4, lo=0.0, hi=10.0,
                             doc="moving with the vehicle within this: an artefact, not confirmed")
    speed_check_frames: int = _f(4, lo=1, hi=100, doc="hits before the speed checks apply")
    predict_min_mps: float = _f(0.4, lo=0.0, hi=10.0,
                                doc="slower than this: not predicted (noise on a still object)")
    max_tracks: int = _f(300, lo=1, hi=100000)
    stop_zone_strength: float = _f(0.8, lo=0.0, hi=1.0,
                                   doc="a tentative track with a cell in the stop zone and a "
                                       "geometry or laser strength at least this confirms at "
                                       "once (0 = off)")
    coast_fused_s: float = _f(0.0, lo=0.0, hi=10.0,
                              doc="a confirmed, still track the laser and a camera cue both "
                                  "saw is held unseen this long, whatever its evidence (0 = off)")
    laser_fast: bool = _f(True, doc="a laser return cluster counts at full strength and "
                                     "confirms on the first frame it is seen")
    movers: bool = _f(True, doc="with the cell decision (enabled = false): also track what "
                                "the grid holds, and STOP for a mover that, going on as it "
                                "does while the vehicle drives on, meets the vehicle within "
                                "movers_horizon_s (SLOW within twice that): a person walking "
                                "in from the side, outside the zones until it is too late "
                                "(docs/tracking.md 'Movers'; the default since the "
                                "seventeenth session, false = the cells alone)")
    movers_input: str = _f("hits", choices=("occupied", "hits"),
                           doc="movers: what their tracker clusters (a walker's cells move: "
                               "they are rarely hit twice running, so rarely 'occupied')")
    movers_min_run: int = _f(5, lo=3, hi=10,
                             doc="movers: frames in a row a track is seen in before its "
                                 "motion is judged (a line is fitted through its centres)")
    movers_max_rms_m: float = _f(0.08, lo=0.0, hi=5.0,
                                 doc="movers: the centres stray from a straight line at "
                                     "constant speed by at most this (rms): a thing that "
                                     "walks does not hop between stubble tufts")
    movers_min_mps: float = _f(0.5, lo=0.0, hi=50.0,
                               doc="movers: slower over ground than this is not a mover")
    movers_max_mps: float = _f(5.0, lo=0.0, hi=50.0,
                               doc="movers: faster than this is not a walker (a laser scan "
                                   "line sweeping the stubble as the vehicle pitches)")
    movers_max_size_m: float = _f(2.5, lo=0.1, hi=50.0,
                                  doc="movers: a candidate longer or wider than this is not one "
                                      "walker (clusters of stubble hits joined)")
    movers_range_m: float = _f(15.0, lo=1.0, hi=100.0,
                               doc="movers: only what is within this of the front, ahead and "
                                   "to either side, is tracked for them (a walker farther away "
                                   "cannot meet the vehicle within twice the horizon at field "
                                   "speeds; the far stubble hits cost time)")
    movers_horizon_s: float = _f(0.0, lo=0.0, hi=10.0,
                                 doc="movers: how far ahead a meeting is looked for (0 = the "
                                     "time the vehicle needs to come to rest from its present "
                                     "speed, [zones] reaction_time_s + speed / decel_mps2, and "
                                     "0.5 s for the velocity's lag)")
    movers_body_m: float = _f(3.0, lo=0.0, hi=50.0,
                              doc="movers: the vehicle's length behind [zones] front_x_m (a "
                                  "mover walking into its side is met too)")
    weights: SourceWeights = field(default_factory=SourceWeights)


@dataclass(frozen=True)
class PerceptionConfig:
    pipelines: tuple = _f(("laser",), doc="pipelines the daemon runs (registry names)")
    optional: tuple = _f((), doc="pipelines that may be skipped when the budget is short")
    laser: LaserPipelineConfig = field(default_factory=LaserPipelineConfig)
    extra: Mapping = field(default_factory=dict)   # tables of pipelines registered later


@dataclass(frozen=True)
class DeviceConfig:
    name: str
    kind: str
    type: str
    timeout_s: float
    required: bool
    options: Mapping


@dataclass(frozen=True)
class StatusConfig:
    socket: str = _f("", doc="status socket path; empty = $RUNTIME_DIRECTORY or /tmp")
    incident_dir: str = _f("", doc="where incident recordings go; empty = none")
    incident_seconds: float = _f(2.0, lo=0.1, hi=30.0, doc="seconds kept before each STOP")
    incident_max: int = _f(20, lo=1, hi=10000, doc="incidents kept on disk (oldest removed)")
    incident_max_mb: float = _f(2000.0, lo=1.0, doc="disk the incidents may take, MB (oldest "
                                                    "removed first)")
    malloc_trim_s: float = _f(60.0, lo=0.0, hi=3600.0,
                              doc="seconds between giving the heap's free pages back to the "
                                  "system (glibc malloc_trim); 0 = never")


@dataclass(frozen=True)
class SimConfig:
    scene: str = _f("stubble-day")
    seed: int = _f(0, lo=0)
    stereo_scale: float = _f(0.5, lo=0.1, hi=1.0)
    pace: float = _f(1.0, lo=0.0, hi=100.0, doc="1 = real time, 0 = as fast as possible")
    path: str = _f("route", choices=("route", "mission", "none"),
                   doc="the planned path the simulated vehicle hands the box ([zones] "
                       "follow_path): its route ahead (the best a path can be), the legs "
                       "between its lanes' ends as the box builds them from an autopilot's "
                       "mission (drivers/mission_path.py), or none")
    mission_wp_radius_m: float = _f(2.0, lo=0.1, hi=20.0,
                                    doc="path = \"mission\": how near the vehicle comes to a "
                                        "waypoint before the autopilot heads for the next "
                                        "(ArduPilot Rover's WP_RADIUS)")


@dataclass(frozen=True)
class ConsoleConfig:
    listen: str = _f("127.0.0.1:8080", doc="web console HOST:PORT (read-only); \"\" = off. "
                                           "Another address than loopback only when set here")
    rate_hz: float = _f(2.0, lo=0.1, hi=10.0, doc="pictures handed to the console per second")


@dataclass(frozen=True)
class FoxgloveConfig:
    listen: str = _f("", doc="Foxglove WebSocket server HOST:PORT (live view in Foxglove); "
                             "\"\" = off (default)")


def parse_listen(value: str, key: str, file: str) -> tuple[str, int] | None:
    """``HOST:PORT`` -> (host, port); "" -> None (off). Port 0 = any free port (tests)."""
    if value == "":
        return None
    host, sep, port = value.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"must be HOST:PORT (e.g. \"127.0.0.1:8080\") or \"\" for off; got "
                          f"{value!r}", file=file, key=key)
    if any(c.isspace() for c in host) or "/" in host:
        raise ConfigError(f"not a host name or address: {host!r}", file=file, key=key)
    return host, int(port)


@dataclass(frozen=True)
class Config:
    source: str = "<defaults>"
    loop: LoopConfig = field(default_factory=LoopConfig)
    gate: GateConfig = field(default_factory=GateConfig)
    zones: ZonesConfig = field(default_factory=ZonesConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    devices: tuple = ()                      # tuple[DeviceConfig, ...]
    status: StatusConfig = field(default_factory=StatusConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    console: ConsoleConfig = field(default_factory=ConsoleConfig)
    foxglove: FoxgloveConfig = field(default_factory=FoxgloveConfig)

    def device(self, name: str) -> DeviceConfig | None:
        for d in self.devices:
            if d.name == name:
                return d
        return None


DEVICE_KINDS = ("stereo", "rgbd", "laser", "trigger", "link")
_DEVICE_COMMON = {"type", "timeout_s", "required"}


# ------------------------------------------------------------------------------------------------
def _check_value(value, ftype, meta, key, file):
    origin = typing.get_origin(ftype)
    if ftype is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"must be a number, got {value!r}", file=file, key=key)
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"must be finite, got {value!r}", file=file, key=key)
    elif ftype is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"must be a whole number, got {value!r}", file=file, key=key)
    elif ftype is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"must be true or false, got {value!r}", file=file, key=key)
    elif ftype is str:
        if not isinstance(value, str):
            raise ConfigError(f"must be a string, got {value!r}", file=file, key=key)
    elif ftype is tuple or origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"must be a list, got {value!r}", file=file, key=key)
        value = tuple(value)
    lo, hi, choices = meta.get("lo"), meta.get("hi"), meta.get("choices")
    if lo is not None and value < lo:
        raise ConfigError(f"must be >= {lo}, got {value!r}", file=file, key=key)
    if hi is not None and value > hi:
        raise ConfigError(f"must be <= {hi}, got {value!r}", file=file, key=key)
    if choices is not None and value not in choices:
        raise ConfigError(f"must be one of {', '.join(map(str, choices))}; got {value!r}",
                          file=file, key=key)
    return value


def build_section(cls, data: Mapping[str, Any], key: str, file: str, skip=()):
    """Build frozen dataclass ``cls`` from a TOML table, naming file and key on any error."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"must be a table, got {data!r}", file=file, key=key)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in data.items():
        full = f"{key}.{k}" if key else k
        if k in skip:
            continue
        if k not in fields or k in ("source", "extra"):
            known = ", ".join(n for n in fields if n not in ("source", "extra"))
            raise ConfigError(f"unknown key (known keys here: {known})", file=file, key=full)
        ftype = hints[k]
        if dataclasses.is_dataclass(ftype):
            kwargs[k] = build_section(ftype, v, full, file)
        else:
            kwargs[k] = _check_value(v, ftype, fields[k].metadata, full, file)
    return cls(**kwargs)


def _parse_exclusions(items, file):
    out = []
    for i, item in enumerate(items):
        z = build_section(ExclusionZone, item, f"zones.exclusion[{i}]", file)
        if z.x_max_m <= z.x_min_m or z.y_max_m <= z.y_min_m:
            raise ConfigError("needs x_max_m > x_min_m and y_max_m > y_min_m", file=file,
                              key=f"zones.exclusion[{i}]")
        out.append(z)
    return tuple(out)


def _parse_devices(data, file) -> tuple[DeviceConfig, ...]:
    from drivers.registry import driver_class, known_types  # lazy: validation needs the schema
    if not isinstance(data, Mapping):
        raise ConfigError("must be a table of devices", file=file, key="devices")
    out = []
    for name, table in data.items():
        key = f"devices.{name}"
        if not isinstance(table, Mapping):
            raise ConfigError("must be a table", file=file, key=key)
        kind = table.get("kind", name)
        if kind not in DEVICE_KINDS:
            raise ConfigError(f"unknown device kind {kind!r}: name the table one of "
                              f"{', '.join(DEVICE_KINDS)} or give kind = ...", file=file, key=key)
        if "type" not in table:
            raise ConfigError(f"needs a type (one of {', '.join(known_types(kind))})",
                              file=file, key=key)
        dtype = table["type"]
        try:
            if not isinstance(dtype, str):      # type = [] raised TypeError (fuzz_config.py)
                raise KeyError(dtype)
            cls = driver_class(kind, dtype)
        except KeyError:
            raise ConfigError(f"unknown type {dtype!r} for a {kind} device; known types: "
                              f"{', '.join(known_types(kind))}", file=file, key=f"{key}.type")
        schema = dict(getattr(cls, "options_schema", {}))
        opts = {}
        for k, v in table.items():
            if k in _DEVICE_COMMON or k == "kind":
                continue
            if k not in schema:
                known = ", ".join(sorted(set(schema) | _DEVICE_COMMON)) or "none"
                raise ConfigError(f"unknown key for a {dtype!r} {kind} (known: {known})",
                                  file=file, key=f"{key}.{k}")
            opts[k] = _check_value(v, schema[k], {}, f"{key}.{k}", file)
        # what the driver would refuse on open (a connection string it cannot parse, a DBC
        # it cannot load) is refused here, so `config check` and `run` agree
        check = getattr(cls, "check_options", None)
        if check is not None:
            problem = check(opts)
            if problem:
                bad_key, msg = problem
                raise ConfigError(msg, file=file, key=f"{key}.{bad_key}" if bad_key else key)
        timeout = _check_value(table.get("timeout_s", getattr(cls, "default_timeout_s", 0.25)),
                               float, {"lo": 0.001, "hi": 60.0}, f"{key}.timeout_s", file)
        required = _check_value(table.get("required", True), bool, {}, f"{key}.required", file)
        out.append(DeviceConfig(name=name, kind=kind, type=dtype, timeout_s=timeout,
                                required=required, options=types.MappingProxyType(opts)))
    return tuple(out)


def parse_config(data: Mapping[str, Any], file: str = "<config>") -> Config:
    data = dict(data)
    sections = {}
    known = {f.name for f in dataclasses.fields(Config)} - {"source"}
    for k in data:
        if k not in known:
            raise ConfigError(f"unknown section (known: {', '.join(sorted(known))})",
                              file=file, key=k)
    for name, cls in (("loop", LoopConfig), ("gate", GateConfig), ("grid", GridConfig),
                      ("status", StatusConfig), ("sim", SimConfig),
                      ("tracking", TrackingConfig),
                      ("console", ConsoleConfig), ("foxglove", FoxgloveConfig)):
        if name in data:
            sections[name] = build_section(cls, data[name], name, file)
    if "zones" in data:
        z = dict(data["zones"]) if isinstance(data["zones"], Mapping) else data["zones"]
        excl = z.pop("exclusion", []) if isinstance(z, dict) else []
        zc = build_section(ZonesConfig, z, "zones", file)
        sections["zones"] = dataclasses.replace(zc, exclusion=_parse_exclusions(excl, file))
    if "perception" in data:
        sections["perception"] = _parse_perception(data["perception"], file)
    if "devices" in data:
        sections["devices"] = _parse_devices(data["devices"], file)
    cfg = Config(source=file, **sections)
    _cross_check(cfg, file)
    return cfg


def _parse_perception(data, file) -> PerceptionConfig:
    from appliance.perception import known_pipelines, pipeline_config_class
    if not isinstance(data, Mapping):
        raise ConfigError("must be a table", file=file, key="perception")
    names = known_pipelines()
    base = {k: v for k, v in data.items() if k in ("pipelines", "optional", "laser")}
    pc = build_section(PerceptionConfig, base, "perception", file)
    extra = {}
    for k, v in data.items():
        if k in base:
            continue
        cls = pipeline_config_class(k)
        if cls is None:
            raise ConfigError(f"unknown key (known: pipelines, optional, "
                              f"{', '.join(names)})", file=file, key=f"perception.{k}")
        extra[k] = build_section(cls, v, f"perception.{k}", file)
    for p in tuple(pc.pipelines) + tuple(pc.optional):
        if p not in names:
            raise ConfigError(f"unknown pipeline {p!r}; known: {', '.join(names)}",
                              file=file, key="perception.pipelines")
    return dataclasses.replace(pc, extra=types.MappingProxyType(extra))


def check_scene(name: str, *, file: str | None = None, key: str | None = None) -> str:
    """``name`` if it is a simulated scene, else ConfigError with a did-you-mean."""
    import difflib

    from drivers.sim.scenes import SCENES       # lazy: the scene list is the simulator's
    if name in SCENES:
        return name
    close = difflib.get_close_matches(name, list(SCENES), n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ConfigError(f"unknown scene {name!r}{hint}; known scenes: "
                      f"{', '.join(sorted(SCENES))}", file=file, key=key)


def _cross_check(cfg: Config, file: str) -> None:
    check_scene(cfg.sim.scene, file=file, key="sim.scene")
    parse_listen(cfg.console.listen, "console.listen", file)
    parse_listen(cfg.foxglove.listen, "foxglove.listen", file)
    g = cfg.grid
    if g.x_max_m <= g.x_min_m or g.y_max_m <= g.y_min_m:
        raise ConfigError("needs x_max_m > x_min_m and y_max_m > y_min_m", file=file, key="grid")
    from appliance.perception import known_pipelines
    for key in ("stop_recur_now", "confirm_pipelines"):
        bad = [p for p in getattr(g, key) if p not in known_pipelines()]
        if bad:
            raise ConfigError(f"unknown pipeline {bad[0]!r}; known: "
                              f"{', '.join(known_pipelines())}", file=file, key=f"grid.{key}")
    if g.slow_recur > 0 and g.stop_recur <= 0:
        raise ConfigError("slow_recur needs the recurrence memory of stop_recur (> 0)",
                          file=file, key="grid.slow_recur")
    from appliance.perception.view import CONFIRM_NAMES
    bad = [n for n in g.laser_confirm_by if n not in CONFIRM_NAMES]
    if bad:
        raise ConfigError(f"unknown camera evidence {bad[0]!r}; known: "
                          f"{', '.join(CONFIRM_NAMES)}", file=file, key="grid.laser_confirm_by")
    if g.laser_confirm_by and cfg.tracking.enabled:
        raise ConfigError("laser_confirm_by works with the cell decision only (tracking.enabled "
                          "= false)", file=file, key="grid.laser_confirm_by")
    t = cfg.tracking
    if t.far_m <= t.near_m or t.large_m <= t.small_m:
        raise ConfigError("needs far_m > near_m and large_m > small_m", file=file, key="tracking")
    if t.confirm_frames_max < t.confirm_frames_min:
        raise ConfigError("confirm_frames_max must be >= confirm_frames_min", file=file,
                          key="tracking")
    if t.release_logodds > t.confirm_logodds:
        raise ConfigError("release_logodds must not exceed confirm_logodds", file=file,
                          key="tracking")
    if t.movers_max_mps <= t.movers_min_mps:
        raise ConfigError("movers_max_mps must exceed movers_min_mps (nothing would be a "
                          "mover)", file=file, key="tracking")
    if cfg.perception.laser.max_range_m <= cfg.perception.laser.min_range_m:
        raise ConfigError("max_range_m must exceed min_range_m", file=file,
                          key="perception.laser")
    names = {d.name for d in cfg.devices}
    for r in cfg.gate.required:
        if cfg.devices and r not in names:
            raise ConfigError(f"names device {r!r}, which is not configured "
                              f"(configured: {', '.join(sorted(names))})", file=file,
                              key="gate.required")
    sn = cfg.perception.extra.get("stereo-novelty")
    if sn is not None and sn.near_view and sn.near_min_depth_m <= 0:
        raise ConfigError("near_view needs the near search (near_min_depth_m > 0): without it "
                          "the pipeline ranges nothing nearer than min_depth_m", file=file,
                          key="perception.stereo-novelty.near_view")
    if not set(cfg.perception.optional) <= set(cfg.perception.pipelines):
        raise ConfigError("every optional pipeline must also be listed in pipelines",
                          file=file, key="perception.optional")


def load_config(path: str | Path) -> Config:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("file not found", file=str(p))
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", file=str(p))
    except UnicodeDecodeError as exc:     # found by tests/fuzz/fuzz_config.py
        raise ConfigError(f"not UTF-8 text (byte {exc.start}): TOML files are UTF-8",
                          file=str(p)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML: {exc}", file=str(p))
    return parse_config(data, str(p))


def default_config() -> Config:
    return Config()


# Scenes whose vehicle and sensors the defaults do not fit (the greenhouse sprayer: an RGB-D
# camera, 1.2 m long, 0.8 m wide between bush rows 1.2 m apart; with the default 2.5 m wide
# zones the bushes are in the stop zone: docs/rgbd.md). `run --sim SCENE` without a --config
# and the campaign's drives run these, so the two measure the same box.
SCENE_PIPELINES = {"greenhouse": ("rgbd",)}
SCENE_ZONES = {"greenhouse": {"front_x_m": 1.1, "half_width_m": 0.5, "body_rear_m": 0.1}}
