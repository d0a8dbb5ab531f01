"""The box's data in Foxglove's own schemas, through the foxglove-sdk: live on its WebSocket
server (``[foxglove] listen``, off by default) and into MCAP files (``fieldguard export``,
``fieldguard record --mcap``; appliance/mcap_export.py).

Topics (frame ``vehicle``: x forward, y left, z up, origin under the rear axle):

| topic | schema | what |
|---|---|---|
| /camera/image | foxglove.CompressedImage | the camera (stereo left, else RGB-D colour), JPEG |
| /camera/annotated | foxglove.CompressedImage | the console's view: masks, cells, tracks |
| /camera/depth | foxglove.RawImage | RGB-D depth, 32FC1 metres |
| /grid | foxglove.Grid | the evidence grid (fields evidence float32, occupied uint8) |
| /scene | foxglove.SceneUpdate | stop and slow zones, the vehicle, tracks (cubes + labels) |
| /laser | foxglove.LaserScan | the laser's ranges, posed at its mount |
| /state | JSON (schema fieldguard.State) | the gate's state, reason, faults, nearest obstacle |
| /vehicle | JSON (schema fieldguard.Vehicle) | speed, yaw rate, attitude |
| /log | foxglove.Log | one line on every change of state |

A recording adds /truth (foxglove.SceneUpdate, the run's ground truth) and /recording/state
(JSON: the state the box had when it recorded the frame).
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np

log = logging.getLogger("fieldguard.foxglove")

STATE_SCHEMA = {
    "title": "fieldguard.State", "type": "object",
    "properties": {"state": {"type": "string", "enum": ["STOP", "SLOW", "CLEAR"]},
                   "reason": {"type": "string"}, "seq": {"type": "integer"},
                   "cycle": {"type": "integer"},
                   "nearest_m": {"type": ["number", "null"]},
                   "speed_limit_mps": {"type": ["number", "null"]},
                   "faults": {"type": "array", "items": {"type": "string"}},
                   "occupied_cells": {"type": "integer"},
                   "held_cells": {"type": "integer"},
                   "tracks": {"type": "integer"}}}
VEHICLE_SCHEMA = {
    "title": "fieldguard.Vehicle", "type": "object",
    "properties": {k: {"type": "number"} for k in ("speed_mps", "yaw_rate_radps", "roll_rad",
                                                   "pitch_rad", "yaw_rad")}}
RECORDED_STATE_SCHEMA = {
    "title": "fieldguard.RecordedState", "type": "object",
    "properties": {"state": {"type": "string"}, "reason": {"type": "string"},
                   "index": {"type": "integer"}}}


def _ts(ns: int):
    from foxglove.messages import Timestamp
    ns = int(ns)
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _quat_rpy(roll: float, pitch: float, yaw: float):
    from foxglove.messages import Quaternion
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return Quaternion(x=sr * cp * cy - cr * sp * sy, y=cr * sp * cy + sr * cp * sy,
                      z=cr * cp * sy - sr * sp * cy, w=cr * cp * cy + sr * sp * sy)


def _pose(x=0.0, y=0.0, z=0.0, roll=0.0, pitch=0.0, yaw=0.0):
    from foxglove.messages import Pose, Vector3
    return Pose(position=Vector3(x=float(x), y=float(y), z=float(z)),
                orientation=_quat_rpy(roll, pitch, yaw))


def _color(r, g, b, a=1.0):
    from foxglove.messages import Color
    return Color(r=r, g=g, b=b, a=a)


class FoxgloveChannels:
    """One set of channels on a foxglove Context; ``log_cycle`` writes one cycle to whatever
    sinks the context has (a WebSocket server, an MCAP file)."""

    def __init__(self, context, cfg, recording: bool = False):
        import foxglove
        from foxglove.channels import (CompressedImageChannel, GridChannel, LaserScanChannel,
                                       LogChannel, RawImageChannel, SceneUpdateChannel)
        self.cfg = cfg
        c = context
        self.image = CompressedImageChannel("/camera/image", context=c)
        self.annotated = CompressedImageChannel("/camera/annotated", context=c)
        self.depth = RawImageChannel("/camera/depth", context=c)
        self.grid = GridChannel("/grid", context=c)
        self.scene = SceneUpdateChannel("/scene", context=c)
        self.laser = LaserScanChannel("/laser", context=c)
        self.state = foxglove.Channel("/state", schema=STATE_SCHEMA, context=c)
        self.vehicle = foxglove.Channel("/vehicle", schema=VEHICLE_SCHEMA, context=c)
        self.log = LogChannel("/log", context=c)
        self.truth = self.recorded = None
        if recording:
            self.truth = SceneUpdateChannel("/truth", context=c)
            self.recorded = foxglove.Channel("/recording/state", schema=RECORDED_STATE_SCHEMA,
                                             context=c)
        self._last_state = None
        self._last_seq: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def _new(self, what: str, sample) -> bool:
        """A sample is written once: the loop sees the same (still fresh) sample again when a
        sensor is slower than the loop."""
        key = (sample.seq, sample.stamp_ns)
        if self._last_seq.get(what) == key:
            return False
        self._last_seq[what] = key
        return True

    def _count(self, topic: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1

    # ----------------------------------------------------------------------------------------
    def log_cycle(self, res, evidence: np.ndarray, tracks, t_ns: int, *,
                  camera_jpeg: bytes | None = None, annotated_jpeg: bytes | None = None,
                  encode_camera: bool = True, jpeg_quality: int = 85) -> None:
        """Write one cycle. ``t_ns`` is the log time (and the messages' timestamp).
        ``camera_jpeg``: the camera image already encoded; else it is encoded here when
        ``encode_camera``."""
        inp = res.inputs
        ts = _ts(t_ns)
        if inp is not None:
            self._camera(inp, ts, t_ns, camera_jpeg, encode_camera, jpeg_quality)
            if inp.laser is not None and self._new("laser", inp.laser):
                self._laser(inp.laser, ts, t_ns)
            if inp.vehicle is not None and self._new("vehicle", inp.vehicle):
                v = inp.vehicle
                self.vehicle.log({"speed_mps": v.speed_mps, "yaw_rate_radps": v.yaw_rate_radps,
                                  "roll_rad": v.roll_rad, "pitch_rad": v.pitch_rad,
                                  "yaw_rad": v.yaw_rad}, log_time=t_ns)
                self._count("/vehicle")
        if annotated_jpeg:
            from foxglove.messages import CompressedImage
            self.annotated.log(CompressedImage(timestamp=ts, frame_id="camera",
                                               data=annotated_jpeg, format="jpeg"), log_time=t_ns)
            self._count("/camera/annotated")
        self._grid(evidence, ts, t_ns)
        self._scene(res, tracks, ts, t_ns)
        out = res.output
        self.state.log({"state": out.state.value, "reason": out.reason, "seq": out.seq,
                        "cycle": res.index, "nearest_m": out.nearest_m,
                        "speed_limit_mps": out.speed_limit_mps, "faults": list(res.faults),
                        "occupied_cells": int(len(res.cells_xy)),
                        "held_cells": int(len(getattr(res, "held_xy", ()))),
                        "tracks": sum(1 for t in tracks if t.get("confirmed", True))},
                       log_time=t_ns)
        self._count("/state")
        if out.state is not self._last_state:
            from foxglove.messages import Log, LogLevel
            lvl = {"STOP": LogLevel.Warning, "SLOW": LogLevel.Info}.get(out.state.value,
                                                                          LogLevel.Info)
            self.log.log(Log(timestamp=ts, level=lvl, message=f"{out.state.value}: {out.reason}",
                             name="fieldguard.gate"), log_time=t_ns)
            self._count("/log")
            self._last_state = out.state

    def _camera(self, inp, ts, t_ns, jpeg, encode, quality) -> None:
        from foxglove.messages import CompressedImage, RawImage
        src = inp.stereo if inp.stereo is not None else inp.rgbd
        img = None if src is None else (src.left if src is inp.stereo else src.color)
        if img is not None and (jpeg is not None or encode) and self._new("camera", src):
            if jpeg is None:
                import cv2
                ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
                jpeg = buf.tobytes() if ok else None
            if jpeg:
                self.image.log(CompressedImage(timestamp=ts, frame_id="camera", data=jpeg,
                                               format="jpeg"), log_time=t_ns)
                self._count("/camera/image")
        if inp.rgbd is not None and self._new("depth", inp.rgbd):
            d = np.ascontiguousarray(inp.rgbd.depth_m, np.float32)
            self.depth.log(RawImage(timestamp=ts, frame_id="camera", width=d.shape[1],
                                    height=d.shape[0], encoding="32FC1", step=d.shape[1] * 4,
                                    data=d.tobytes()), log_time=t_ns)
            self._count("/camera/depth")

    def _laser(self, scan, ts, t_ns) -> None:
        from foxglove.messages import LaserScan
        g = scan.geometry
        m = g.mount
        a0 = math.radians(g.angle_min_deg)
        a1 = math.radians(g.angle_min_deg + g.angle_step_deg * (g.beams - 1))
        r = np.nan_to_num(np.asarray(scan.ranges_m, np.float64), nan=0.0)
        self.laser.log(LaserScan(timestamp=ts, frame_id="vehicle",
                                 pose=_pose(m.x_m, m.y_m, m.z_m, math.radians(m.roll_deg),
                                            math.radians(m.pitch_deg),  # + = nose down
                                            math.radians(m.yaw_deg)),
                                 start_angle=a0, end_angle=a1, ranges=r.tolist()),
                       log_time=t_ns)
        self._count("/laser")

    def _grid(self, evidence, ts, t_ns) -> None:
        from foxglove.messages import (Grid, PackedElementField, PackedElementFieldNumericType,
                                       Vector2)
        g = self.cfg.grid
        nx, ny = evidence.shape
        cells = np.zeros((ny, nx), dtype=[("evidence", "<f4"), ("occupied", "u1")])
        cells["evidence"] = evidence.T
        cells["occupied"] = evidence.T >= g.occupied_at - 1e-6
        f = PackedElementFieldNumericType
        self.grid.log(Grid(timestamp=ts, frame_id="vehicle", pose=_pose(g.x_min_m, g.y_min_m),
                           column_count=nx, cell_size=Vector2(x=g.cell_m, y=g.cell_m),
                           row_stride=5 * nx, cell_stride=5,
                           fields=[PackedElementField(name="evidence", offset=0,
                                                      type=f.Float32),
                                   PackedElementField(name="occupied", offset=4, type=f.Uint8)],
                           data=cells.tobytes()), log_time=t_ns)
        self._count("/grid")

    def _scene(self, res, tracks, ts, t_ns) -> None:
        from foxglove.messages import (CubePrimitive, SceneEntity, SceneEntityDeletion,
                                       SceneEntityDeletionType, SceneUpdate, TextPrimitive,
                                       Vector3)
        from appliance.zones import stop_length
        z = self.cfg.zones
        veh = res.inputs.vehicle if res.inputs is not None else None
        stop = stop_length(veh.speed_mps if veh is not None else 0.0, z)
        f, hw = z.front_x_m, z.half_width_m

        def box(x0, x1, y0, y1, h, col):
            return CubePrimitive(pose=_pose((x0 + x1) / 2, (y0 + y1) / 2, h / 2),
                                 size=Vector3(x=x1 - x0, y=y1 - y0, z=h), color=col)

        ents = [
            SceneEntity(timestamp=ts, frame_id="vehicle", id="stop_zone",
                        cubes=[box(f, f + stop, -hw, hw, 0.05, _color(0.9, 0.1, 0.1, 0.35))]),
            SceneEntity(timestamp=ts, frame_id="vehicle", id="slow_zone",
                        cubes=[box(f + stop, f + stop + z.slow_extra_m, -hw, hw, 0.05,
                                   _color(0.95, 0.7, 0.0, 0.3))]),
            SceneEntity(timestamp=ts, frame_id="vehicle", id="vehicle",
                        cubes=[box(min(0.0, f - 2.6), f, -0.75, 0.75, 1.5,
                                   _color(0.8, 0.8, 0.8, 0.8))]),
        ]
        for t in tracks:
            conf = t.get("confirmed", True)
            ln, wd = max(0.1, float(t.get("length_m") or 0.5)), max(0.1, float(t.get("width_m")
                                                                              or 0.5))
            h = max(0.1, float(t.get("height_m") or 1.0))
            col = _color(0.2, 0.6, 1.0, 0.8 if conf else 0.3)
            ents.append(SceneEntity(
                timestamp=ts, frame_id="vehicle", id=f"track-{t.get('id')}",
                cubes=[box(t["x_m"] - ln / 2, t["x_m"] + ln / 2, t["y_m"] - wd / 2,
                           t["y_m"] + wd / 2, h, col)],
                texts=[TextPrimitive(pose=_pose(t["x_m"], t["y_m"], h + 0.3), billboard=True,
                                     font_size=14, scale_invariant=True, color=col,
                                     text=f"#{t.get('id')}" + ("" if conf else " ?"))]))
        self.scene.log(SceneUpdate(deletions=[SceneEntityDeletion(
            timestamp=ts, type=SceneEntityDeletionType.All)], entities=ents), log_time=t_ns)
        self._count("/scene")

    def log_truth(self, obstacles: list[dict], t_ns: int) -> None:
        from foxglove.messages import (CubePrimitive, SceneEntity, SceneEntityDeletion,
                                       SceneEntityDeletionType, SceneUpdate, TextPrimitive,
                                       Vector3)
        ts = _ts(t_ns)
        ents = []
        for o in obstacles:
            h = float(o.get("height_m") or 1.0)
            col = _color(0.2, 0.9, 0.3, 0.5)
            pose = _pose(o["x_m"], o["y_m"], float(o.get("z_m", 0.0)) + h / 2,
                         yaw=math.radians(float(o.get("yaw_deg", 0.0))))
            ents.append(SceneEntity(
                timestamp=ts, frame_id="vehicle", id=f"truth-{o['id']}",
                cubes=[CubePrimitive(pose=pose, size=Vector3(x=o["length_m"], y=o["width_m"],
                                                             z=h), color=col)],
                texts=[TextPrimitive(pose=_pose(o["x_m"], o["y_m"], h + 0.3), billboard=True,
                                     font_size=14, scale_invariant=True, color=col,
                                     text=f"{o['class']} {o['id']}")]))
        self.truth.log(SceneUpdate(deletions=[SceneEntityDeletion(
            timestamp=ts, type=SceneEntityDeletionType.All)], entities=ents), log_time=t_ns)
        self._count("/truth")

    def log_recorded_state(self, state: str, reason: str, index: int, t_ns: int) -> None:
        self.recorded.log({"state": state, "reason": reason, "index": index}, log_time=t_ns)
        self._count("/recording/state")


class LiveFoxglove:
    """The foxglove-sdk WebSocket server with the box's channels, fed by the console's tap
    (the same bounded-rate, already-encoded views: the annotated camera JPEG is sent as it is;
    the plain camera image is not re-encoded live)."""

    def __init__(self, host: str, port: int, cfg):
        self.host, self.port, self.cfg = host, port, cfg
        self.error: str | None = None
        self.server = None
        self.channels: FoxgloveChannels | None = None
        self.sent = 0

    def start(self) -> bool:
        import foxglove
        try:
            self.context = foxglove.Context()
            self.channels = FoxgloveChannels(self.context, self.cfg)
            self.server = foxglove.start_server(name="fieldguard", host=self.host,
                                                port=self.port, context=self.context)
        except Exception as exc:            # a port that is taken, a bad address: never fatal
            self.error = f"cannot listen on {self.host}:{self.port}: {exc}"
            log.error("foxglove: %s; the box runs on without its Foxglove server", self.error)
            self.server = None
            return False
        self.port = self.server.port
        log.info("foxglove: WebSocket server on ws://%s:%d (subprotocol foxglove.sdk.v1)",
                 self.host, self.port)
        return True

    @property
    def url(self) -> str | None:
        return None if self.server is None else f"ws://{self.host}:{self.port}"

    def on_view(self, view) -> None:
        """On the console's encoder thread: one view to every connected Foxglove client."""
        self.channels.log_cycle(view.res, view.evidence, view.tracks,
                                int(view.wall_s * 1e9), annotated_jpeg=view.camera_jpeg,
                                encode_camera=False)
        self.sent += 1

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    def info(self) -> dict:
        return {"url": self.url, "error": self.error, "views_sent": self.sent}
