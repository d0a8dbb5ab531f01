"""Kinect-class RGB-D camera through libfreenect (the OpenKinect library and its Python binding).

Colour (640x480 RGB) and depth registered to it (``FREENECT_DEPTH_REGISTERED``: millimetres,
aligned to the colour image, 0 = no reading) become a :class:`hal.DepthFrame` (BGR colour,
float32 metres = counts x ``depth_unit_m``, 0 kept as "no reading").

**Why a helper process.** The binding (``pip install freenect``, the OpenKinect Cython wrapper)
calls ``freenect_process_events`` without releasing the GIL. That call blocks until the USB
stack has something (on a silent or unplugged Kinect, up to libusb's timeout), and fakenect's
playback sleeps inside it between frames: measured here, a 2 s gap in a dump froze every other
Python thread for 2 s. In the daemon's process that would freeze the loop, so the binding runs
in a child process (``python -m drivers.freenect_rgbd --child``) that pairs each depth frame with
the newest colour frame, throttles to ``max_fps`` and hands the pairs over through a shared-memory
ring, announcing each with a small message on a pipe (nothing in libfreenect's callbacks may
block: see the ring below); this driver's acquisition thread reads the pipe with a short
``select`` and never blocks. The child also
isolates the C library: a crash, an ``exit()`` (fakenect does that on a missing file) or a USB
error ends the child, not the daemon.

Health: the child's end (exit code and the tail of its stderr) or garbled data on the pipe mark
the device FAULT at once; no frame for ``lost_after_s`` kills the child; either way it is
restarted with exponential back-off (0.2 s doubling to ``backoff_max_s``). Between, the base
class marks the data stale after ``timeout_s``. Counters: ``pairs``, ``unmatched`` (depth frames
with no colour frame within ``pair_tolerance_ms``), ``throttled`` (above ``max_fps``),
``overwritten`` (read too late from the ring), ``starts``, ``restarts``.

``python -m drivers.freenect_rgbd --stream [--fakenect DUMP --preload STUB.so]`` runs the driver
alone and prints figures (a technician's check of a Kinect, and the benchmark in the docs).

Stamps: the child's monotonic arrival time of the depth frame (CLOCK_MONOTONIC is the same in
both processes), converted to the loop's clock.

``fakenect = "DUMP"`` plays a recorded dump through libfreenect's own playback library instead of
USB (bench and tests; see drivers/emulators/fakenect_dump.py and docs/hardware.md).
"""
from __future__ import annotations

import os
import select
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hal.devices import DepthCamera, check_timeout
from hal.errors import DeviceError, DeviceOperationError
from hal.types import DepthCalibration, DepthFrame, Mount, PinholeCalibration

from .calibration import MOUNT_SCHEMA, mount_from_options
from .reconnect import Backoff, Reconnecting

ROOT = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT = 640, 480
DEPTH_BYTES, COLOUR_BYTES = WIDTH * HEIGHT * 2, WIDTH * HEIGHT * 3

# The pipe carries small messages: header, then `size` payload bytes. The frames themselves go
# through a shared-memory ring of SLOTS slots (a memfd the driver creates and the helper
# inherits): [seq at start u64][seq at end u64][depth uint16 640x480][colour RGB 640x480]; a
# PAIR message names the slot and its sequence number, and the reader checks both copies of the
# number after copying the slot out (a slot overwritten meanwhile is dropped and counted).
MAGIC = b"FGK1"
HEADER = struct.Struct("<4sBxxxIIQd")     # magic, kind, depth ts, video ts, size, mono time s
PAIR_INFO = struct.Struct("<IIIQ")       # slot, unmatched, throttled, seq
HELLO, PAIR, ERROR = 1, 2, 3
SLOTS = 4
SLOT_HEAD = 16
SLOT_BYTES = SLOT_HEAD + DEPTH_BYTES + COLOUR_BYTES


# ---------------------------------------------------------------------------------------------
class FreenectDepthCamera(Reconnecting, DepthCamera):
    """A Kinect (v1 / Kinect for Windows, anything libfreenect drives) as a hal.DepthCamera."""

    options_schema = {"index": int, "fx": float, "fy": float, "cx": float, "cy": float,
                      "depth_unit_m": float, "min_range_m": float, "max_range_m": float,
                      "max_fps": float, "pair_tolerance_ms": float, "lost_after_s": float,
                      "backoff_max_s": float, "fakenect": str, "fakenect_preload": str,
                      **MOUNT_SCHEMA}
    # one period at max_fps 15 (67 ms) + 60 ms late tolerance: stale 60 ms after the next pair
    # was due, so the gate stops within two 10 Hz cycles (docs/hardware.md)
    default_timeout_s = 0.13
    DEFAULT_MOUNT = Mount(x_m=1.0, z_m=0.9, pitch_deg=10.0)
    # Kinect v1 colour camera (registered depth uses the colour camera's geometry)
    DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)

    def __init__(self, name, clock, index: int = 0, timeout_s: float = default_timeout_s,
                 mount: Mount | None = None, fx: float = 525.0, fy: float = 525.0,
                 cx: float = 319.5, cy: float = 239.5, depth_unit_m: float = 0.001,
                 min_range_m: float = 0.5, max_range_m: float = 5.0, max_fps: float = 15.0,
                 pair_tolerance_ms: float = 40.0, lost_after_s: float = 1.0,
                 backoff_max_s: float = 2.0, fakenect: str = "", fakenect_preload: str = "",
                 python: str | None = None):
        super().__init__(name, clock, timeout_s)
        if index < 0:
            raise ValueError("index must be >= 0")
        if not 0 < max_fps <= 30:
            raise ValueError("max_fps must be in (0, 30]")
        self.index = int(index)
        self.calib = DepthCalibration(PinholeCalibration(WIDTH, HEIGHT, fx, fy, cx, cy),
                                      mount or self.DEFAULT_MOUNT, float(depth_unit_m),
                                      float(min_range_m), float(max_range_m))
        self.max_fps = float(max_fps)
        self.pair_tolerance_ms = float(pair_tolerance_ms)
        self.lost_after_s = float(lost_after_s)
        self.backoff = Backoff(0.2, backoff_max_s)
        self.fakenect = fakenect
        self.fakenect_preload = fakenect_preload
        self.python = python or sys.executable
        self._proc: subprocess.Popen | None = None
        self._shm = None
        self._shm_fd = -1
        self._buf = bytearray()
        self._err = b""
        self._errmsg = ""
        self._started = 0.0
        self._last_frame = 0.0
        self._seq = 0
        self.hello = ""

    @classmethod
    def from_config(cls, cfg, clock, shared):
        o = cfg.options
        check_timeout(cfg.name, cfg.timeout_s, 1.0 / max(o.get("max_fps", 15.0), 1e-3),
                      "the pair period (1 / max_fps)")
        fx, fy, cx, cy = cls.DEFAULT_INTRINSICS
        return cls(cfg.name, clock, index=o.get("index", 0), timeout_s=cfg.timeout_s,
                   mount=mount_from_options(o, cls.DEFAULT_MOUNT), fx=o.get("fx", fx),
                   fy=o.get("fy", fy), cx=o.get("cx", cx), cy=o.get("cy", cy),
                   depth_unit_m=o.get("depth_unit_m", 0.001),
                   min_range_m=o.get("min_range_m", 0.5), max_range_m=o.get("max_range_m", 5.0),
                   max_fps=o.get("max_fps", 15.0),
                   pair_tolerance_ms=o.get("pair_tolerance_ms", 40.0),
                   lost_after_s=o.get("lost_after_s", 1.0),
                   backoff_max_s=o.get("backoff_max_s", 2.0), fakenect=o.get("fakenect", ""),
                   fakenect_preload=o.get("fakenect_preload", ""))

    @property
    def source(self) -> str:
        return f"fakenect {self.fakenect}" if self.fakenect else f"kinect #{self.index}"

    # ---- the helper process ---------------------------------------------------------------------
    def _env(self) -> dict:
        env = dict(os.environ)
        env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}".rstrip(os.pathsep)
        if self.fakenect:
            from drivers.emulators.fakenect_dump import build_stub, fakenect_env
            stub = self.fakenect_preload
            if not stub:
                try:
                    stub = str(build_stub(Path(self.fakenect) / ".stub"))
                except RuntimeError as exc:
                    raise DeviceOperationError(str(exc)) from None
            try:
                env = fakenect_env(self.fakenect, stub, base=env)
            except RuntimeError as exc:
                raise DeviceOperationError(str(exc)) from None
        return env

    def _ring(self):
        if self._shm is None:
            import mmap
            fd = os.memfd_create("fieldguard-kinect", 0)
            os.ftruncate(fd, SLOTS * SLOT_BYTES)
            self._shm_fd, self._shm = fd, mmap.mmap(fd, SLOTS * SLOT_BYTES)
        return self._shm_fd

    def _spawn(self) -> None:
        try:
            fd = self._ring()
        except OSError as exc:
            raise DeviceOperationError(f"cannot make the frame ring: {exc}") from None
        cmd = [self.python, "-m", "drivers.freenect_rgbd", "--child", "--index", str(self.index),
               "--max-fps", str(self.max_fps), "--pair-tolerance-ms", str(self.pair_tolerance_ms),
               "--ring-fd", str(fd)]
        try:
            self._proc = subprocess.Popen(cmd, cwd=str(ROOT), env=self._env(),
                                          stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, bufsize=0, pass_fds=(fd,))
        except OSError as exc:
            raise DeviceOperationError(f"cannot start the libfreenect helper: {exc}") from None
        for f in (self._proc.stdout, self._proc.stderr):
            os.set_blocking(f.fileno(), False)
        self._buf = bytearray()
        self._err = b""
        self._errmsg = ""
        self._started = self._last_frame = time.monotonic()
        self._count("starts")

    def _kill(self) -> None:
        p, self._proc = self._proc, None
        if p is None:
            return
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(1.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(2.0)
        for f in (p.stdout, p.stderr):
            try:
                f.close()
            except OSError:
                pass

    reconnect_counter = "restarts"

    def _disconnect(self) -> None:
        self._kill()

    def _close(self) -> None:
        self._kill()
        shm, self._shm = self._shm, None
        if shm is not None:
            shm.close()
            os.close(self._shm_fd)

    def _err_tail(self) -> str:
        lines = [x.strip() for x in self._err.decode("utf-8", "replace").splitlines()
                 if x.strip()]
        return " | ".join(lines[-2:])[-300:]

    # ---- acquisition ----------------------------------------------------------------------------
    def _acquire_once(self) -> None:
        if self._proc is None:
            self._connect_when_due(self._spawn)
            return
        p = self._proc
        out, err = p.stdout.fileno(), p.stderr.fileno()
        try:
            ready, _, _ = select.select([out, err], [], [], 0.05)
        except (OSError, ValueError) as exc:
            self._drop(f"{self.source}: helper pipe failed: {exc}")
            return
        eof = False
        if err in ready:
            chunk = _read(err)
            if chunk:
                self._err = (self._err + chunk)[-4000:]
        if out in ready:
            chunk = _read(out)
            if chunk:
                self._buf += chunk
            elif chunk is not None:
                eof = True
        try:
            self._parse()
        except DeviceError as exc:
            self._drop(str(exc))
            return
        if eof:
            try:
                rc = p.wait(1.0)
            except subprocess.TimeoutExpired:
                rc = None
            tail = _read(err) or b""
            self._err = (self._err + tail)[-4000:]
            self._drop(f"{self.source}: stopped (helper exit {rc}): "
                       f"{self._errmsg or self._err_tail() or 'no message'}")
            return
        now = time.monotonic()
        grace = 3.0 if self._last_frame == self._started else 0.0     # start-up: imports
        if now - self._last_frame > self.lost_after_s + grace:
            self._drop(f"{self.source}: no frames for {now - self._last_frame:.1f} s")

    def _parse(self) -> None:
        while len(self._buf) >= HEADER.size:
            magic, kind, dts, vts, size, mono = HEADER.unpack_from(self._buf)
            if magic != MAGIC or kind not in (HELLO, PAIR, ERROR) or size > 4096:
                self._count("bad_messages")
                raise DeviceOperationError(f"{self.source}: garbled data from the helper")
            if len(self._buf) < HEADER.size + size:
                return
            payload = self._buf[HEADER.size:HEADER.size + size]
            del self._buf[:HEADER.size + size]
            if kind == HELLO:
                self.hello = payload.decode("utf-8", "replace")
            elif kind == ERROR:
                self._errmsg = payload.decode("utf-8", "replace")[:300]
            else:
                self._on_pair(payload, dts, vts, mono)

    def _on_pair(self, payload: bytes, dts: int, vts: int, mono: float) -> None:
        if len(payload) != PAIR_INFO.size:
            raise DeviceOperationError(f"{self.source}: bad frame message from the helper")
        k, unmatched, throttled, seq = PAIR_INFO.unpack(payload)
        if k >= SLOTS:
            raise DeviceOperationError(f"{self.source}: bad frame slot {k} from the helper")
        base = k * SLOT_BYTES
        ring = self._shm
        head = struct.Struct("<QQ")
        if head.unpack_from(ring, base) != (seq, seq):
            self._count("overwritten")
            return
        depth = np.frombuffer(ring, np.uint16, WIDTH * HEIGHT, base + SLOT_HEAD)
        rgb = np.frombuffer(ring, np.uint8, COLOUR_BYTES, base + SLOT_HEAD + DEPTH_BYTES)
        depth_m = depth.reshape(HEIGHT, WIDTH).astype(np.float32)
        bgr = np.ascontiguousarray(rgb.reshape(HEIGHT, WIDTH, 3)[..., ::-1])
        del depth, rgb                           # no views into the ring may outlive this
        if head.unpack_from(ring, base) != (seq, seq):   # overwritten while we copied
            self._count("overwritten")
            return
        depth_m *= np.float32(self.calib.depth_unit_m)
        self._last_frame = time.monotonic()
        age_ns = max(0, int((self._last_frame - mono) * 1e9))
        stamp = self.clock.now_ns() - age_ns
        with self._lock:
            self.counters["unmatched"] = int(unmatched)
            self.counters["throttled"] = int(throttled)
        self._seq += 1
        self._count("pairs")
        self.backoff.reset()
        self._publish(DepthFrame(stamp_ns=stamp, seq=self._seq, color=bgr, depth_m=depth_m,
                                 calib=self.calib))

    def selftest(self) -> tuple[bool, str]:
        h = self.selftest_health()
        c = h.counters
        if h.ok:
            return True, (f"{self.source}: streaming registered depth + colour, "
                          f"{c.get('pairs', 0)} pairs, {c.get('unmatched', 0)} unmatched, "
                          f"{c.get('restarts', 0)} restarts")
        reason = h.reason or h.state.value
        return False, reason if reason.startswith(self.source) else f"{self.source}: {reason}"


def _read(fd: int) -> bytes | None:
    """What is available on a non-blocking fd: b"" at end of file, None if nothing yet."""
    try:
        return os.read(fd, 1 << 20)
    except BlockingIOError:
        return None
    except OSError:
        return b""


# ---------------------------------------------------------------------------------------------
# the helper process: the binding's async API, one pair per depth frame, written to the pipe
def _child(index: int, max_fps: float, pair_tolerance_ms: float, ring_fd: int) -> int:
    import mmap
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)            # the C library prints to stdout (fakenect does): keep the pipe clean
    try:                     # die with the daemon even when blocked in the library
        import ctypes
        ctypes.CDLL(None).prctl(1, signal.SIGTERM)          # PR_SET_PDEATHSIG
    except Exception:
        pass
    ring = mmap.mmap(ring_fd, SLOTS * SLOT_BYTES)
    head = struct.Struct("<QQ")

    def send(kind, payload=b"", dts=0, vts=0, mono=0.0):
        out.write(HEADER.pack(MAGIC, kind, dts & 0xFFFFFFFF, vts & 0xFFFFFFFF, len(payload),
                              mono) + payload)

    def fail(text, code):
        try:
            send(ERROR, text.encode())
        except OSError:
            print(f"freenect helper: {text}", file=sys.stderr, flush=True)
        return code

    try:
        import freenect
    except ImportError as exc:
        return fail(f"the freenect Python binding is not installed ({exc}); "
                    f"pip install freenect (needs libfreenect-dev)", 2)
    ctx = freenect.init()
    if ctx is None:
        return fail("libfreenect could not start (freenect_init failed: USB?)", 3)
    n = freenect.num_devices(ctx)
    if n <= index:
        return fail(f"no Kinect #{index} (libfreenect sees {n} device(s))", 4)
    dev = freenect.open_device(ctx, index)
    if dev is None:
        return fail(f"cannot open Kinect #{index} (in use, or no permission on its USB "
                    f"device: see the udev rule in docs/hardware.md)", 5)
    if freenect.set_depth_mode(dev, freenect.RESOLUTION_MEDIUM, freenect.DEPTH_REGISTERED) < 0:
        return fail("the Kinect refused registered depth mode", 6)
    if freenect.set_video_mode(dev, freenect.RESOLUTION_MEDIUM, freenect.VIDEO_RGB) < 0:
        return fail("the Kinect refused RGB video mode", 6)
    # the binding holds the GIL inside process_events, so no helper thread could write while
    # libfreenect waits: everything happens in the callbacks, and nothing in them blocks (one
    # memcpy per image into the ring, a 56-byte message on the pipe)
    state = {"video": None, "unmatched": 0, "throttled": 0, "last_sent": 0.0, "seq": 0}
    period = 1.0 / max_fps
    tol = pair_tolerance_ms / 1e3

    def slot_base():
        return (state["seq"] % SLOTS) * SLOT_BYTES

    def video_cb(_dev, data, ts):
        # straight into the slot the next pair will use (marked invalid while it is written)
        c = np.asarray(data, np.uint8)
        if c.shape != (HEIGHT, WIDTH, 3):
            return
        base = slot_base()
        head.pack_into(ring, base, 0, 0)
        ring[base + SLOT_HEAD + DEPTH_BYTES:base + SLOT_BYTES] = np.ascontiguousarray(c).data
        state["video"] = (time.monotonic(), ts)

    def depth_cb(_dev, data, ts):
        now = time.monotonic()
        if now - state["last_sent"] < period * 0.9:
            state["throttled"] += 1
            return
        v = state["video"]
        if v is None or abs(now - v[0]) > tol:
            state["unmatched"] += 1
            return
        d = np.asarray(data, np.uint16)
        if d.shape != (HEIGHT, WIDTH):
            state["unmatched"] += 1
            return
        state["last_sent"] = now
        base = slot_base()
        ring[base + SLOT_HEAD:base + SLOT_HEAD + DEPTH_BYTES] = np.ascontiguousarray(d).data
        state["seq"] += 1
        seq = state["seq"]
        head.pack_into(ring, base, seq, seq)
        state["video"] = None                 # its slot now holds this pair
        send(PAIR, PAIR_INFO.pack(base // SLOT_BYTES, state["unmatched"], state["throttled"],
                                  seq), ts, v[1], now)

    freenect.set_depth_callback(dev, depth_cb)
    freenect.set_video_callback(dev, video_cb)
    freenect.start_depth(dev)
    freenect.start_video(dev)
    send(HELLO, f"kinect #{index} of {n}, registered depth + RGB 640x480".encode())
    try:
        while True:
            r = freenect.process_events(ctx)
            if r < 0:
                return fail(f"libfreenect stopped delivering (process_events returned {r})", 7)
    except (BrokenPipeError, KeyboardInterrupt):
        return 0
    finally:
        try:
            freenect.stop_depth(dev)
            freenect.stop_video(dev)
            freenect.close_device(dev)
            freenect.shutdown(ctx)
        except Exception:
            pass


def stream_check(seconds: float = 5.0, **kw) -> dict:
    """Run the driver alone for ``seconds`` (a real Kinect, or ``fakenect=DUMP``) and measure:
    pairs per second, the age of each pair when published (helper arrival -> driver), the CPU
    time per pair of the daemon side (this process) and of the helper (reaped children)."""
    import resource
    from hal.clock import MonotonicClock
    d = FreenectDepthCamera("rgbd", MonotonicClock(), **kw)
    ages, publish = [], d._publish

    def timed(sample):
        ages.append((d.clock.now_ns() - sample.stamp_ns) / 1e6)
        publish(sample)

    d._publish = timed
    ru0, cpu0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.process_time(), \
        time.monotonic()
    d.open()
    d.start_acquisition()
    time.sleep(seconds)
    ok, msg = d.selftest()
    d.close()
    wall, cpu = time.monotonic() - t0, time.process_time() - cpu0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    helper = (ru.ru_utime + ru.ru_stime) - (ru0.ru_utime + ru0.ru_stime)
    n = max(1, len(ages))
    a = np.array(ages or [np.nan])
    return {"seconds": round(wall, 2), "pairs": len(ages), "pairs_per_s": round(len(ages) / wall,
                                                                               2),
            "publish_age_ms": {"p50": round(float(np.median(a)), 2),
                               "max": round(float(np.max(a)), 2)},
            "driver_cpu_ms_per_pair": round(cpu * 1e3 / n, 2),
            "helper_cpu_ms_per_pair": round(helper * 1e3 / n, 2),
            "counters": dict(d.counters), "selftest": [ok, msg]}


def main(argv=None) -> int:
    import argparse
    import json
    ap = argparse.ArgumentParser(prog="python -m drivers.freenect_rgbd",
                                 description="--stream: check a Kinect (or a fakenect dump) "
                                             "streams through the driver, with figures")
    ap.add_argument("--child", action="store_true", help="run as the driver's helper process")
    ap.add_argument("--stream", action="store_true", help="run the driver alone, print figures")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--fakenect", default="", help="with --stream: play this dump")
    ap.add_argument("--preload", default="", help="with --fakenect: the stub library")
    ap.add_argument("--index", type=int, default=0)
    ap.add_argument("--max-fps", type=float, default=15.0)
    ap.add_argument("--pair-tolerance-ms", type=float, default=40.0)
    ap.add_argument("--ring-fd", type=int, help="the frame ring (a memfd; --child)")
    a = ap.parse_args(argv)
    if a.stream:
        print(json.dumps(stream_check(a.seconds, index=a.index, max_fps=a.max_fps,
                                      pair_tolerance_ms=a.pair_tolerance_ms,
                                      fakenect=a.fakenect, fakenect_preload=a.preload)))
        return 0
    if not a.child or a.ring_fd is None:
        ap.error("give --stream, or --child --ring-fd N (the driver runs its helper so)")
    return _child(a.index, a.max_fps, a.pair_tolerance_ms, a.ring_fd)


if __name__ == "__main__":
    sys.exit(main())
