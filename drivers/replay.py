"""Replay twins of the HAL devices: play a run folder (docs/run-format.md) as if live.

One :class:`RunPlayer` maps the clock to a frame position for all devices of a run: frame k is due
at ``start + (stamp_ns[k] - stamp_ns[0])``, where start is the clock time when the player is
first asked (or given to :meth:`RunPlayer.start`). A device publishes the newest frame due,
re-stamped to the player's clock, once; frames the loop was too slow to see are skipped (a slot,
never a queue); a frame whose file is missing publishes nothing (the data ages, as a dropped
frame would). After the last frame the devices publish nothing more, so their data goes stale and
the gate stops, with the reason "end of recording" — unless ``loop=True``, which replays the run again and again.

- lock-step (``realtime=False``): the loop's ``service(now_ns)`` publishes; deterministic with a
  :class:`hal.ManualClock`.
- realtime (``realtime=True``): ``start_acquisition()`` runs a thread that publishes on time;
  ``service`` does nothing, so the loop never waits on file I/O.
"""
from __future__ import annotations

import bisect
import dataclasses
import threading

from hal import (Clock, DepthCamera, DepthFrame, DeviceInitializationError, GateOutput,
                 Health, LaserScan, RunFormatError, SafetyLaser, StereoCalibration, StereoCamera,
                 StereoFrame, VehicleLink, VehicleState)

from .runfolder import RunReader

__all__ = ["RunPlayer", "ReplayStereoCamera", "ReplayDepthCamera", "ReplayLaser",
           "ReplayVehicleLink", "replay_devices"]


class RunPlayer:
    """Maps clock time to a frame position of a run, shared by the run's replay devices."""

    def __init__(self, reader: RunReader, clock: Clock, realtime: bool = False,
                 loop: bool = False, start_ns: int | None = None):
        self.reader, self.clock = reader, clock
        self.realtime, self.loop = bool(realtime), bool(loop)
        frames = reader.frames
        self.offsets_ns = [f.stamp_ns - frames[0].stamp_ns for f in frames] if frames else []
        frame_period = int(round(1e9 / reader.info.rate_hz))
        # the run lasts until one frame period after its last frame; a loop starts again then
        self.duration_ns = (self.offsets_ns[-1] + frame_period) if frames else 0
        self._index_span = (max(f.index for f in frames) + 1) if frames else 1
        self._lock = threading.Lock()
        self._start_ns = start_ns

    def start(self, now_ns: int | None = None) -> int:
        """Fix the start time (first call wins) and return it."""
        with self._lock:
            if self._start_ns is None:
                self._start_ns = self.clock.now_ns() if now_ns is None else int(now_ns)
            return self._start_ns

    @property
    def start_ns(self) -> int | None:
        return self._start_ns

    def _elapsed(self, now_ns: int) -> tuple[int, int] | None:
        """(lap, offset within the lap), or None when not started yet / finished."""
        e = now_ns - self.start(now_ns)
        if e < 0 or not self.offsets_ns:
            return None
        if self.loop:
            return divmod(e, self.duration_ns)
        if e >= self.duration_ns:
            return None
        return 0, e

    def due(self, now_ns: int) -> tuple[int, int, int] | None:
        """(position, player stamp_ns, lap) of the newest frame due at now_ns, or None."""
        le = self._elapsed(now_ns)
        if le is None:
            return None
        lap, e = le
        pos = bisect.bisect_right(self.offsets_ns, e) - 1
        stamp = self.start(now_ns) + lap * self.duration_ns + self.offsets_ns[pos]
        return pos, stamp, lap

    def next_due_ns(self, now_ns: int) -> int | None:
        """Clock time at which the next frame after now_ns is due, None when the run is over."""
        le = self._elapsed(now_ns)
        if le is None:
            return None
        lap, e = le
        pos = bisect.bisect_right(self.offsets_ns, e)
        base = self.start(now_ns) + lap * self.duration_ns
        if pos < len(self.offsets_ns):
            return base + self.offsets_ns[pos]
        return base + self.duration_ns if self.loop else None

    def finished(self, now_ns: int) -> bool:
        """True once the run is over (never with loop=True, unless the run has no frames)."""
        if not self.offsets_ns:
            return True
        if self.loop:
            return False
        return now_ns - self.start(now_ns) >= self.duration_ns

    def seq(self, pos: int, lap: int) -> int:
        return self.reader.frames[pos].index + lap * self._index_span


class _Replay:
    """Shared work of the replay devices; mixed in before the HAL interface class."""

    sensor = ""

    def __init__(self, player: RunPlayer, name: str | None = None, timeout_s: float = 0.25):
        if self.sensor and getattr(player.reader.info, self.sensor) is None:
            raise DeviceInitializationError(
                f"run {player.reader.info.name!r} ({player.reader.path}) has no {self.sensor}")
        super().__init__(name or self.kind, player.clock, timeout_s)   # type: ignore[call-arg]
        self.player = player
        self._last: tuple[int, int] | None = None
        self._step_lock = threading.Lock()

    def _load(self, pos: int):  # override: the recorded sample or None
        raise NotImplementedError

    def _step(self, now_ns: int) -> None:
        with self._step_lock:
            d = self.player.due(now_ns)
            if d is None:
                return
            pos, stamp, lap = d
            if self._last == (lap, pos):
                return
            self._last = (lap, pos)
            try:
                sample = self._load(pos)
            except RunFormatError as exc:
                self._fault(str(exc))                     # type: ignore[attr-defined]
                return
            if sample is None:
                self._count("missing_frames")             # type: ignore[attr-defined]
                return
            self._publish(dataclasses.replace(              # type: ignore[attr-defined]
                sample, stamp_ns=stamp, seq=self.player.seq(pos, lap)))

    def service(self, now_ns: int) -> None:
        if not self.player.realtime:
            self._step(now_ns)

    def health(self, now_ns: int | None = None):
        """As every device's; data gone stale because the run is over says so ("end of
        recording"), not "stale" as a sensor that stopped would."""
        h = super().health(now_ns)                        # type: ignore[misc]
        if h.state is Health.NO_DATA and self.player.start_ns is not None:
            now = self.player.clock.now_ns() if now_ns is None else now_ns
            if self.player.finished(now):
                return dataclasses.replace(
                    h, reason=f"end of recording ({self.player.reader.info.name})")
        return h

    def _acquire_once(self) -> None:
        if not self.player.realtime:
            self._stop_evt.wait(0.1)                      # type: ignore[attr-defined]
            return
        now = self.player.clock.now_ns()
        self._step(now)
        nxt = self.player.next_due_ns(now)
        wait_s = 0.1 if nxt is None else min(max((nxt - now) / 1e9, 0.001), 0.1)
        self._stop_evt.wait(wait_s)                       # type: ignore[attr-defined]


class ReplayStereoCamera(_Replay, StereoCamera):
    sensor = "stereo"

    @property
    def calibration(self) -> StereoCalibration:
        return self.player.reader.info.stereo

    def _load(self, pos: int) -> StereoFrame | None:
        return self.player.reader.stereo(pos)


class ReplayDepthCamera(_Replay, DepthCamera):
    sensor = "rgbd"

    @property
    def calibration(self):
        return self.player.reader.info.rgbd

    def _load(self, pos: int) -> DepthFrame | None:
        return self.player.reader.rgbd(pos)


class ReplayLaser(_Replay, SafetyLaser):
    sensor = "laser"

    @property
    def geometry(self):
        return self.player.reader.info.laser

    def _load(self, pos: int) -> LaserScan | None:
        return self.player.reader.laser(pos)


class ReplayVehicleLink(_Replay, VehicleLink):
    """Samples are the recorded vehicle state; ``send`` records each output in :attr:`sent`
    and returns :attr:`send_ok` (True; set it False to inject a failed send)."""

    sensor = ""

    def __init__(self, player: RunPlayer, name: str | None = None, timeout_s: float = 0.25):
        super().__init__(player, name, timeout_s)
        self.sent: list[GateOutput] = []
        self.send_ok = True

    def _load(self, pos: int) -> VehicleState:
        return self.player.reader.vehicle(pos)

    def send(self, output: GateOutput) -> bool:
        self.sent.append(output)
        return self.send_ok


def replay_devices(player: RunPlayer, timeout_s: float = 0.25) -> dict:
    """The replay devices a run can feed: {"stereo", "rgbd", "laser"} as present, and "link"."""
    info = player.reader.info
    out: dict = {}
    if info.stereo is not None:
        out["stereo"] = ReplayStereoCamera(player, timeout_s=timeout_s)
    if info.rgbd is not None:
        out["rgbd"] = ReplayDepthCamera(player, timeout_s=timeout_s)
    if info.laser is not None:
        out["laser"] = ReplayLaser(player, timeout_s=timeout_s)
    out["link"] = ReplayVehicleLink(player, timeout_s=timeout_s)
    return out
