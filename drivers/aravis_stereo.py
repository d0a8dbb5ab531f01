"""GigE Vision colour stereo pair through Aravis 0.8 (GObject introspection, ``gi``).

Each camera is found by serial number, device id (``Vendor-Model-Serial``) or IP address,
configured (region = the calibration's image size, pixel format, exposure, gain, trigger, GigE
packet size) and streamed into a small ring of buffers. Frames are paired by timestamp: a left
and a right frame whose stamps differ by at most ``pair_tolerance_ms`` make a pair; a frame with
no partner within the tolerance is dropped and counted (``unmatched``). Pairs are debayered
(GenICam ``BayerRG8`` is OpenCV's ``BayerBG`` pattern, and so on), rectified with the
calibration file (drivers/calibration.py) and published as a :class:`hal.StereoFrame`.

Trigger: ``trigger = "Line0"`` (default) lets the strobe/trigger controller fire both cameras on
one edge; ``"Software"`` makes the driver fire both at ``rate_hz`` (bench, no controller);
``"Off"`` free-runs (pairs then rarely match: for focusing only).

Timestamps: ``pair_by = "system"`` (default) pairs by the host's arrival time of each frame,
which works with any camera; ``"device"`` pairs by the cameras' own timestamps and needs their
clocks synchronised (IEEE 1588/PTP on both). The published stamp is the host arrival time of the
older frame, converted to the loop's clock.

Health: ``dropped_frames`` (Aravis's failed/missing frames), ``missing_packets``,
``resent_packets`` and ``resend_requests`` from the GigE stream statistics, ``unmatched`` and
``pairs``. A camera that delivers nothing for ``lost_after_s`` while being triggered, or whose
control channel is lost, marks the device FAULT; both cameras are then reopened with back-off.
"""
from __future__ import annotations

import collections
import ipaddress
import queue
import threading
import time

import numpy as np

from hal.devices import StereoCamera, check_timeout
from hal.errors import DeviceInitializationError, DeviceOperationError, DeviceError
from hal.types import Mount, StereoCalibration, StereoFrame

from .calibration import MOUNT_SCHEMA, Rectifier, load_stereo_calibration, mount_from_options
from .reconnect import Backoff, Reconnecting

# GenICam pixel format -> OpenCV conversion code name (OpenCV names Bayer patterns by the second
# row's second pixel, so the names are swapped)
DEBAYER = {"BayerRG8": "COLOR_BayerBG2BGR", "BayerBG8": "COLOR_BayerRG2BGR",
           "BayerGR8": "COLOR_BayerGB2BGR", "BayerGB8": "COLOR_BayerGR2BGR"}
PIXEL_FORMATS = tuple(DEBAYER) + ("Mono8", "RGB8", "BGR8")


def aravis():
    """The Aravis 0.8 module (``gi.repository.Aravis``); DeviceInitializationError if absent."""
    try:
        import gi
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceInitializationError(
            f"Aravis 0.8 is not available from Python ({exc}); install gir1.2-aravis-0.8 and "
            f"PyGObject<3.51 (see docs/hardware.md)") from None
    return Aravis


def to_bgr(data: bytes | memoryview, width: int, height: int, pixel_format: str) -> np.ndarray:
    """One camera buffer -> HxWx3 uint8 BGR."""
    import cv2
    if pixel_format in ("RGB8", "BGR8"):
        img = np.frombuffer(data, np.uint8, width * height * 3).reshape(height, width, 3)
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if pixel_format == "RGB8" else img.copy()
    raw = np.frombuffer(data, np.uint8, width * height).reshape(height, width)
    if pixel_format == "Mono8":
        return cv2.cvtColor(raw, cv2.COLOR_GRAY2BGR)
    try:
        code = getattr(cv2, DEBAYER[pixel_format])
    except KeyError:
        raise DeviceOperationError(f"unsupported pixel format {pixel_format}") from None
    return cv2.cvtColor(raw, code)



# Aravis stamps a buffer's arrival with the wall clock (g_get_real_time); the age of a frame is
# the wall clock now minus that stamp. A wall-clock step between the two (NTP, GPS time, an
# operator) makes the age meaningless: +400 days read a fresh frame as 400 days old (a STOP
# "stereo: stale", found by the soak's clock steps), and a step back would read an old one as
# new. Such a frame is dropped (the next one is stamped on the stepped clock); an age beyond
# this is not a frame's wait in the driver's queue.
MAX_FRAME_AGE_NS = 5_000_000_000


def frame_age_ns(wall_now_ns: int, stamp_ns: int) -> int | None:
    """The age of a frame stamped ``stamp_ns`` on the wall clock, or None when the wall clock
    must have stepped since (a negative age, or more than MAX_FRAME_AGE_NS)."""
    age = wall_now_ns - stamp_ns
    if age < -1_000_000 or age > MAX_FRAME_AGE_NS:     # 1 ms of clock slew is no step
        return None
    return max(0, age)

class FramePairer:
    """Pairs (stamp_ns, item) from two streams whose stamps agree within ``tolerance_ns``.
    Frames that can no longer find a partner are dropped and counted in ``unmatched``."""

    def __init__(self, tolerance_ns: int, depth: int = 8):
        self.tol = int(tolerance_ns)
        self.q = (collections.deque(maxlen=depth), collections.deque(maxlen=depth))
        self.unmatched = 0

    def add(self, side: int, stamp_ns: int, item) -> list[tuple]:
        q = self.q[side]
        if len(q) == q.maxlen:
            self.unmatched += 1
        q.append((stamp_ns, item))
        return self._match()

    def _match(self) -> list[tuple]:
        out = []
        L, R = self.q
        while L and R:
            (tl, il), (tr, ir) = L[0], R[0]
            if abs(tl - tr) <= self.tol:
                L.popleft()
                R.popleft()
                out.append((min(tl, tr), il, ir))
            elif tl < tr:            # the left frame is older than any right frame to come
                L.popleft()
                self.unmatched += 1
            else:
                R.popleft()
                self.unmatched += 1
        return out


class _Reaper:
    """One thread that drops the last reference to closed cameras, so that their finalisation
    (which joins Aravis's own threads and can take seconds) runs neither in the acquisition
    thread (it would starve the live cameras) nor in an Aravis thread (GLib would join a
    thread from itself and abort). Started on first use."""

    def __init__(self):
        self._q: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def put(self, box: list) -> None:
        """Hand over ``box`` (a one-item list: the reaper pops the object out of it, so the
        caller's last reference cannot outlive the reaper's)."""
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="aravis-reaper",
                                                daemon=True)
                self._thread.start()
        self._q.put(box)

    def _run(self) -> None:
        while True:
            box = self._q.get()
            box.clear()                  # the last reference: finalised here (a finaliser's
            self._q.task_done()          # error is printed by Python, never raised)

    def wait_idle(self, timeout_s: float) -> bool:
        """True once everything handed over has been let go (within ``timeout_s``)."""
        end = time.monotonic() + timeout_s
        while self._q.unfinished_tasks:
            if time.monotonic() >= end:
                return False
            time.sleep(0.01)
        return True


REAPER = _Reaper()


class _Cam:
    """One Aravis camera and its stream."""

    def __init__(self, Aravis, ident: str, side: str):
        self.A, self.ident, self.side = Aravis, ident, side
        self.cam = None
        self.stream = None
        self.dev = None
        self.handler = None               # the control-lost signal handler's id
        # Closed cameras, held until RELEASE_AFTER_S after their signal handler was
        # disconnected, then let go by the acquisition thread (reap()). Dropping the last
        # reference to an ArvCamera finalises its device, which joins Aravis's own threads; if
        # that last reference goes in one of those threads (the control-lost callback's
        # arguments, released in the heartbeat thread as the driver closes the camera), GLib
        # joins a thread from itself and aborts the process ("g_system_thread_wait: Resource
        # deadlock avoided", SIGTRAP): the soak's daemon died so after a GigE unplug.
        self.graveyard: list[tuple[float, object]] = []
        self.lost = threading.Event()
        self.last_frame = time.monotonic()
        self.pixel_format = "BayerRG8"
        self.stats_prev: dict[str, int] = {}

    def resolve(self) -> str:
        """What Aravis.Camera.new() wants for ``ident``: an address or a device id."""
        try:
            ipaddress.ip_address(self.ident)
            return self.ident
        except ValueError:
            pass
        A = self.A
        A.update_device_list()
        for i in range(A.get_n_devices()):
            if self.ident in (A.get_device_serial_nbr(i), A.get_device_id(i),
                              A.get_device_physical_id(i)):
                return A.get_device_id(i)
        raise DeviceOperationError(f"{self.side} camera {self.ident!r} not found on the network")

    def open(self, *, width, height, pixel_format, exposure_us, gain_db, trigger, packet_size,
             buffers):
        A = self.A
        target = self.resolve()
        try:
            cam = A.Camera.new(target)
        except Exception as exc:
            raise DeviceOperationError(f"{self.side} camera {self.ident}: cannot open: {exc}")
        try:
            dev = cam.get_device()
            lost = self.lost              # the callback holds the event, not this object
            handler = dev.connect("control-lost", lambda *_: lost.set())
            self.dev, self.handler = dev, handler
            sw, sh = cam.get_sensor_size()
            if width > sw or height > sh:
                raise DeviceInitializationError(
                    f"{self.side} camera {self.ident}: sensor {sw}x{sh} is smaller than the "
                    f"calibration's {width}x{height}")
            cam.set_region((sw - width) // 2 // 2 * 2, (sh - height) // 2 // 2 * 2, width, height)
            if pixel_format not in cam.dup_available_pixel_formats_as_strings():
                raise DeviceInitializationError(
                    f"{self.side} camera {self.ident}: no pixel format {pixel_format} (has "
                    f"{', '.join(cam.dup_available_pixel_formats_as_strings())})")
            cam.set_pixel_format_from_string(pixel_format)
            self.pixel_format = pixel_format
            if exposure_us > 0:
                cam.set_exposure_time(exposure_us)
            if gain_db >= 0 and cam.is_gain_available():
                cam.set_gain(gain_db)
            if trigger == "Off":
                cam.clear_triggers()
            else:
                cam.set_trigger(trigger)
            if cam.is_gv_device():
                if packet_size > 0:
                    cam.gv_set_packet_size(packet_size)
                else:
                    try:
                        cam.gv_auto_packet_size()
                    except Exception:
                        pass
            stream = cam.create_stream(None, None)
            if stream is None:
                raise DeviceOperationError(f"{self.side} camera {self.ident}: no stream")
            if cam.is_gv_device():
                # a receive buffer of a whole frame (Aravis's AUTO; at most net.core.rmem_max,
                # docs/hardware.md): left as it was (FIXED, size 0) the socket kept the
                # kernel's rmem_default (208 kB here), less than one 640x480 Bayer frame
                # (307 kB), and a frame's burst overflowed it whenever the stream thread was
                # late: thousands of missing packets on a busy host
                stream.set_property("socket-buffer", A.GvStreamSocketBuffer.AUTO)
            payload = cam.get_payload()
            for _ in range(buffers):
                stream.push_buffer(A.Buffer.new_allocate(payload))
            cam.start_acquisition()
        except DeviceError:
            raise
        except Exception as exc:    # GLib.Error from a GenICam node
            raise DeviceOperationError(f"{self.side} camera {self.ident}: configuration "
                                       f"failed: {exc}") from None
        self.cam, self.stream = cam, stream
        self.last_frame = time.monotonic()
        self.stats_prev = {}

    # long enough for a control-lost callback in flight (it only sets an event) to return;
    # short, because the old device keeps the camera's control channel until it is let go
    # (held 2 s, the fake camera refused the reconnect: tests/test_hw_aravis.py)
    RELEASE_AFTER_S = 0.3

    def close(self):
        cam, stream, self.cam, self.stream = self.cam, self.stream, None, None
        dev, handler, self.dev, self.handler = self.dev, self.handler, None, None
        if dev is not None and handler is not None:
            try:
                dev.disconnect(handler)
            except Exception:
                pass
        if cam is not None:
            try:
                cam.stop_acquisition()
            except Exception:
                pass
        if dev is not None and hasattr(dev, "leave_control"):
            try:                          # a GigE camera takes one controller: free it now,
                dev.leave_control()       # not when the held object is let go
            except Exception:
                pass
        if cam is not None or dev is not None:
            self.graveyard.append((time.monotonic(), (cam, stream, dev)))
        cam = stream = dev = None

    def reap(self, force: bool = False, now: float | None = None) -> int:
        """Let go of closed cameras whose handler has been off for RELEASE_AFTER_S (all with
        ``force``, once Aravis's callbacks cannot run any more): handed to the reaper thread,
        which drops the last reference. Never blocks: finalising a closed ArvCamera joins
        Aravis's threads and took 5 s a camera here; done in the acquisition thread it starved
        a freshly reconnected pair for 10 s (the flaky replug check of
        tests/test_hw_aravis.py). ``now``: the monotonic time (default: the clock's). Returns
        how many were let go."""
        now = time.monotonic() if now is None else now
        old, self.graveyard, n = self.graveyard, [], 0
        while old:
            t, o = old.pop(0)
            if not force and now - t < self.RELEASE_AFTER_S:
                self.graveyard.append((t, o))
            else:
                box = [o]                # the reaper takes it out: no reference stays here
                del o
                REAPER.put(box)
                n += 1
            o = None
        return n

    def pop(self):
        """A finished buffer (or None), without waiting."""
        return self.stream.try_pop_buffer() if self.stream is not None else None

    def stats(self) -> dict[str, int]:
        """Increments of the stream's counters since the last call."""
        out = {}
        if self.stream is None:
            return out
        for name, key in (("n_failures", "dropped_frames"), ("n_missing_frames", "dropped_frames"),
                          ("n_missing_packets", "missing_packets"),
                          ("n_resent_packets", "resent_packets"),
                          ("n_resend_requests", "resend_requests"),
                          ("n_underruns", "underruns")):
            try:
                v = int(self.stream.get_info_uint64_by_name(name))
            except Exception:
                continue
            d = v - self.stats_prev.get(name, 0)
            self.stats_prev[name] = v
            if d > 0:
                out[key] = out.get(key, 0) + d
        return out


class AravisStereoCamera(Reconnecting, StereoCamera):
    options_schema = {"left": str, "right": str, "calibration": str, "pixel_format": str,
                      "exposure_us": float, "gain_db": float, "trigger": str, "rate_hz": float,
                      "pair_tolerance_ms": float, "pair_by": str, "packet_size": int,
                      "buffers": int, "lost_after_s": float, "backoff_max_s": float,
                      **MOUNT_SCHEMA}
    # one trigger period at 10 Hz + 60 ms late tolerance: a silent camera is stale 60 ms after
    # its next pair was due, so the gate stops within two 10 Hz cycles (docs/hardware.md);
    # raise it with a lower trigger rate
    default_timeout_s = 0.16
    DEFAULT_MOUNT = Mount(x_m=1.2, z_m=1.55, pitch_deg=15.0)

    def __init__(self, name, clock, left: str, right: str, calibration: str,
                 timeout_s: float = default_timeout_s, mount: Mount | None = None,
                 pixel_format: str = "BayerRG8", exposure_us: float = 0.0, gain_db: float = -1.0,
                 trigger: str = "Line0", rate_hz: float = 10.0, pair_tolerance_ms: float = 15.0,
                 pair_by: str = "system", packet_size: int = 0, buffers: int = 6,
                 lost_after_s: float = 1.0, backoff_max_s: float = 2.0):
        super().__init__(name, clock, timeout_s)
        if pixel_format not in PIXEL_FORMATS:
            raise DeviceInitializationError(f"{name}: pixel_format must be one of "
                                            f"{', '.join(PIXEL_FORMATS)}")
        if trigger not in ("Line0", "Line1", "Line2", "Software", "Off"):
            raise DeviceInitializationError(f"{name}: trigger must be Line0..2, Software or Off")
        if pair_by not in ("system", "device"):
            raise DeviceInitializationError(f"{name}: pair_by must be system or device")
        self.ids = (left, right)
        self.calibration_path = calibration
        self.mount = mount or self.DEFAULT_MOUNT
        self.cfg = dict(pixel_format=pixel_format, exposure_us=exposure_us, gain_db=gain_db,
                        trigger=trigger, packet_size=packet_size, buffers=buffers)
        self.rate_hz = float(rate_hz)
        self.pair_by = pair_by
        self.lost_after_s = float(lost_after_s)
        self.backoff = Backoff(0.2, backoff_max_s)
        self.pairer = FramePairer(int(pair_tolerance_ms * 1e6))
        self.rectifier: Rectifier | None = None
        self.cams: list[_Cam] = []
        self._streaming = False
        self._next_trigger = 0.0
        self._next_stats = 0.0
        self._seq = 0
        self.illumination = "day"

    @classmethod
    def from_config(cls, cfg, clock, shared):
        o = cfg.options
        check_timeout(cfg.name, cfg.timeout_s, 1.0 / max(o.get("rate_hz", 10.0), 1e-3),
                      "the frame period (1 / rate_hz)")
        for k in ("left", "right", "calibration"):
            if not o.get(k):
                from hal.errors import ConfigError
                raise ConfigError(f"an aravis stereo camera needs {k} = ...",
                                  key=f"devices.{cfg.name}.{k}")
        return cls(cfg.name, clock, o["left"], o["right"], o["calibration"],
                   timeout_s=cfg.timeout_s, mount=mount_from_options(o, cls.DEFAULT_MOUNT),
                   pixel_format=o.get("pixel_format", "BayerRG8"),
                   exposure_us=o.get("exposure_us", 0.0), gain_db=o.get("gain_db", -1.0),
                   trigger=o.get("trigger", "Line0"), rate_hz=o.get("rate_hz", 10.0),
                   pair_tolerance_ms=o.get("pair_tolerance_ms", 15.0),
                   pair_by=o.get("pair_by", "system"), packet_size=o.get("packet_size", 0),
                   buffers=o.get("buffers", 6), lost_after_s=o.get("lost_after_s", 1.0),
                   backoff_max_s=o.get("backoff_max_s", 2.0))

    @property
    def calibration(self) -> StereoCalibration:
        if self.rectifier is None:
            raise DeviceInitializationError(f"{self.name}: not opened")
        return self.rectifier.stereo_calibration

    # ---- life cycle -----------------------------------------------------------------------------
    def _open(self) -> None:
        A = aravis()
        cal = load_stereo_calibration(self.calibration_path)
        self.rectifier = Rectifier(cal, self.mount)
        self.cams = [_Cam(A, self.ids[0], "left"), _Cam(A, self.ids[1], "right")]
        # cameras are opened by the acquisition thread (never blocks start-up)

    def _close(self) -> None:
        for c in self.cams:
            c.close()
        self._streaming = False

    def _disconnect(self) -> None:
        for c in self.cams:
            c.close()
        self._streaming = False

    def _start(self) -> None:
        w, h = self.rectifier.cal.image_size
        for c in self.cams:
            c.lost.clear()
            c.open(width=w, height=h, **self.cfg)
        self._streaming = True
        self._next_trigger = time.monotonic()
        self.pairer = FramePairer(self.pairer.tol)

    # ---- acquisition ----------------------------------------------------------------------------
    def _acquire_once(self) -> None:
        for c in self.cams:
            if c.graveyard:
                c.reap()
        if not self._streaming:
            self._connect_when_due(self._start)
            return
        now = time.monotonic()
        if self.cfg["trigger"] == "Software" and now >= self._next_trigger:
            for c in self.cams:
                try:
                    c.cam.software_trigger()
                except Exception as exc:
                    self._drop(f"{c.side} camera {c.ident}: trigger failed: {exc}")
                    return
            self._count("triggers")
            self._next_trigger = max(self._next_trigger + 1.0 / self.rate_hz, now)
        got = False
        for side, c in enumerate(self.cams):
            while True:
                buf = c.pop()
                if buf is None:
                    break
                got = True
                self._take(side, c, buf)
        now = time.monotonic()
        for c in self.cams:
            if c.lost.is_set():
                self._drop(f"{c.side} camera {c.ident}: control connection lost")
                return
            if now - c.last_frame > self.lost_after_s:
                self._drop(f"{c.side} camera {c.ident}: no frames for {now - c.last_frame:.1f} s")
                return
        if now >= self._next_stats:
            self._next_stats = now + 0.5
            for c in self.cams:
                for k, v in c.stats().items():
                    self._count(k, v)
        if not got:
            self._stop_evt.wait(0.005)

    def _take(self, side: int, c: _Cam, buf) -> None:
        try:
            status = buf.get_status()
            if int(status) != 0:                       # ARV_BUFFER_STATUS_SUCCESS
                self._count("dropped_frames")
                self._count(f"{c.side}_bad_buffers")
                return
            c.last_frame = time.monotonic()
            sys_ns = buf.get_system_timestamp()
            dev_ns = buf.get_timestamp()
            data = buf.get_data()
            w, h = buf.get_image_width(), buf.get_image_height()
            # host arrival time -> the loop's clock
            age_ns = frame_age_ns(time.time_ns(), sys_ns)
            if age_ns is None:                 # the wall clock stepped since Aravis stamped it
                self._count("frames_dropped_clock_step")
                return
            loop_ns = self.clock.now_ns() - age_ns
            key = sys_ns if self.pair_by == "system" else dev_ns
            img = to_bgr(bytes(data), w, h, c.pixel_format)
        finally:
            c.stream.push_buffer(buf)
        before = self.pairer.unmatched
        pairs = self.pairer.add(side, key, (loop_ns, img))
        if self.pairer.unmatched > before:
            self._count("unmatched", self.pairer.unmatched - before)
        for _, (tl, left), (tr, right) in pairs:
            self._publish_pair(min(tl, tr), left, right)

    def _publish_pair(self, stamp_ns: int, left: np.ndarray, right: np.ndarray) -> None:
        cal_w, cal_h = self.rectifier.cal.image_size
        if left.shape[:2] != (cal_h, cal_w) or right.shape[:2] != (cal_h, cal_w):
            self._fault(f"frames are {left.shape[1]}x{left.shape[0]}, the calibration is "
                        f"{cal_w}x{cal_h}")
            return
        rl, rr = self.rectifier.rectify(left, right)
        self._seq += 1
        self._count("pairs")
        self.backoff.reset()
        self._publish(StereoFrame(stamp_ns=stamp_ns, seq=self._seq, left=rl, right=rr,
                                  calib=self.rectifier.stereo_calibration,
                                  illumination=self.illumination))

    def selftest(self) -> tuple[bool, str]:
        h = self.selftest_health()
        c = h.counters
        if h.ok:
            return True, (f"streaming {self.ids[0]} + {self.ids[1]}: {c.get('pairs', 0)} pairs, "
                          f"{c.get('unmatched', 0)} unmatched, {c.get('dropped_frames', 0)} "
                          f"dropped, {c.get('resent_packets', 0)} packets resent")
        return False, f"{self.ids[0]} + {self.ids[1]}: {h.reason or h.state.value}"
