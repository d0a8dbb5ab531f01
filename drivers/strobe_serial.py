"""The strobe/trigger controller on a serial port, and day/night switching.

The controller fires both cameras' hardware trigger inputs at ``rate_hz`` and, at night, a pulsed
light in step with the exposure. It speaks a small line protocol (documented in
docs/hardware.md, "Strobe/trigger protocol"): ASCII lines ending in ``\\n``, each ending in
``*HH``, the XOR of the bytes before the ``*`` in hex (as NMEA 0183), 115200 8N1.

    host -> controller            controller -> host
    RATE 10.00*HH                 OK RATE 10.00*HH
    ARM*HH / DISARM*HH            OK ARM*HH / OK DISARM*HH
    STROBE ON*HH / STROBE OFF*HH  OK STROBE ON*HH
    STATUS?*HH                    STATUS rate=10.00 armed=1 strobe=0 pulses=1234 fault=0*HH
    PING*HH                       PONG <model> <firmware>*HH
    (bad line or checksum)        ERR <code> <text>*HH
                                  FAULT <code> <text>*HH   (unsolicited, e.g. lamp open circuit)

The driver keeps the controller configured (rate, armed, strobe) and polls STATUS every
``status_period_s`` (25 Hz); each good STATUS is a sample. A FAULT line, a STATUS with ``fault``
not 0, a pulse that was due but is not in the counter (the controller has stopped firing; see
:class:`PulseCheck`), lines that fail the checksum, unanswered commands and a port that goes
away all mark the device FAULT; the garbage cases are held for ``fault_hold_s`` so the 10 Hz
loop cannot miss them. A silent controller goes stale after ``timeout_s``. The port is reopened
with back-off.

:func:`next_illumination` is the day/night rule (pure): switch to the strobe when the ambient
brightness falls below ``night_below`` and back only when it rises above ``day_above``.
"""
from __future__ import annotations

import collections
import math
import os
import queue
import select
import time

import numpy as np

from hal.devices import StrobeTrigger, check_timeout
from hal.errors import DeviceOperationError

from .reconnect import Backoff, Reconnecting

DAY, NIGHT = "day", "night-strobe"


# ---------------------------------------------------------------------------------------------
# day / night
def scene_brightness(image: np.ndarray, exposure_us: float = 1.0, gain_db: float = 0.0,
                     ref_exposure_us: float = 1.0) -> float:
    """Mean luma (0..255) of a BGR or grey image, normalised to a reference exposure and 0 dB
    gain, so that auto-exposure does not hide the dusk: ambient = mean * (ref/exposure) /
    10^(gain/20). Sub-sampled (every 8th pixel): cheap enough for every frame."""
    img = np.asarray(image)
    sub = img[::8, ::8]
    if sub.ndim == 3:
        sub = sub[..., 0] * 0.114 + sub[..., 1] * 0.587 + sub[..., 2] * 0.299
    m = float(np.mean(sub)) if sub.size else 0.0
    return m * (ref_exposure_us / max(exposure_us, 1e-9)) / (10 ** (gain_db / 20.0))


def next_illumination(current: str, ambient: float, night_below: float = 35.0,
                      day_above: float = 60.0) -> str:
    """The illumination mode for the next frames, with hysteresis: day -> night when the ambient
    brightness drops below ``night_below``; night -> day only above ``day_above``. Measure the
    ambient on a frame taken WITHOUT the strobe (in night mode, the strobe lights the scene and
    would switch it straight back)."""
    if night_below >= day_above:
        raise ValueError("night_below must be lower than day_above (that is the hysteresis)")
    if current == NIGHT:
        return DAY if ambient > day_above else NIGHT
    return NIGHT if ambient < night_below else DAY


# ---------------------------------------------------------------------------------------------
# the line protocol
def checksum(payload: str) -> str:
    c = 0
    for b in payload.encode("ascii", "replace"):
        c ^= b
    return f"{c:02X}"


def frame_line(payload: str) -> bytes:
    return f"{payload}*{checksum(payload)}\n".encode("ascii")


def parse_line(raw: bytes) -> str:
    """The payload of one received line (without the newline). ValueError if it is not a
    well-formed, correctly check-summed line."""
    try:
        text = raw.decode("ascii").strip("\r\n")
    except UnicodeDecodeError:
        raise ValueError("not ASCII") from None
    payload, star, cs = text.rpartition("*")
    if not star or len(cs) != 2:
        raise ValueError(f"no checksum: {text[:40]!r}")
    if not payload or not payload.isprintable():
        raise ValueError(f"not printable: {text[:40]!r}")
    if checksum(payload) != cs.upper():
        raise ValueError(f"bad checksum: {text[:40]!r}")
    return payload


def parse_status(payload: str) -> dict:
    """``STATUS rate=10.00 armed=1 strobe=0 pulses=1234 fault=0`` -> dict. ValueError if wrong."""
    w = payload.split()
    if not w or w[0] != "STATUS":
        raise ValueError(f"not a status line: {payload!r}")
    kv = dict(x.split("=", 1) for x in w[1:] if "=" in x)
    try:
        return {"rate_hz": float(kv["rate"]), "armed": kv["armed"] == "1",
                "strobe": kv["strobe"] == "1", "pulses": int(kv["pulses"]),
                "fault": int(kv["fault"])}
    except (KeyError, ValueError) as exc:
        raise ValueError(f"bad status line {payload!r}: {exc}") from None


# ---------------------------------------------------------------------------------------------
class PulseCheck:
    """Is the trigger still firing? Decided on every STATUS from its pulse counter, as early as
    the counter can tell.

    The controller fires pulse k at ``t0 + k / rate`` (t0 unknown, its clock is not ours). A
    STATUS saying ``pulses=p`` was composed at some time c between the moment the driver sent
    ``STATUS?`` (s, taken before the write) and the moment the answer was read (r). Pulse p had
    fired by c <= r, so ``t0 <= r - p / rate``; the smallest such bound over the recent answers,
    U, is a bound for t0, and pulse p + 1 was due by ``U + (p + 1) / rate`` at the latest. An
    answer still saying p to a request sent after that (``s > U + (p + 1) / rate + margin_s``)
    proves a pulse is missing: no tolerance for serial latency is needed (c >= s), only
    ``margin_s`` for the controller's clock running slow (answers older than ``window_s`` are
    forgotten, so a 100 ppm crystal drifts 0.2 ms). U tightens as the polls (25 Hz) fall at
    different points between the pulses (10 Hz). A late pulse looks the same as a stopped
    trigger until it comes; when the counter moves again the phase is learned afresh.
    """

    def __init__(self, margin_s: float = 0.005, window_s: float = 2.0):
        self.margin_s, self.window_s = float(margin_s), float(window_s)
        self.reset()

    def reset(self) -> None:
        self._bounds: collections.deque = collections.deque()    # (r, r - p / rate)
        self._rate: float | None = None
        self._last_p: int | None = None
        self.missing_since: float | None = None   # due time of the pulse that did not come

    def update(self, rate_hz: float, pulses: int, sent_s: float | None, read_s: float) -> bool:
        """One STATUS answer (monotonic seconds). True while a due pulse is missing."""
        if (rate_hz != self._rate or self._last_p is None or pulses < self._last_p
                or (self.missing_since is not None and pulses > self._last_p)):
            self.reset()             # new rate, counter reset, or firing again after a gap
            self._rate = rate_hz
        self._last_p = pulses
        period = 1.0 / rate_hz
        b = self._bounds
        b.append((read_s, read_s - pulses * period))
        while len(b) > 1 and read_s - b[0][0] > self.window_s:
            b.popleft()
        due = min(v for _, v in b) + (pulses + 1) * period
        if sent_s is not None and sent_s > due + self.margin_s:
            if self.missing_since is None:
                self.missing_since = due
            return True
        return False


# ---------------------------------------------------------------------------------------------
class StrobeSerialTrigger(Reconnecting, StrobeTrigger):
    """The trigger/strobe controller on a serial port (pyserial)."""

    options_schema = {"port": str, "baudrate": int, "rate_hz": float, "strobe": bool,
                      "status_period_s": float, "ack_timeout_s": float, "fault_hold_s": float,
                      "backoff_max_s": float, "day_night": bool, "night_below": float,
                      "day_above": float, "probe_s": float}
    # one STATUS period (0.04 s) + 60 ms late tolerance: a silent controller is stale 60 ms after
    # its next answer was due, so the gate stops within two 10 Hz cycles (docs/hardware.md)
    default_timeout_s = 0.1
    reconnect_counter = "reopens"

    def __init__(self, name, clock, port: str = "/dev/fieldguard-strobe", baudrate: int = 115200,
                 timeout_s: float = default_timeout_s, rate_hz: float = 10.0,
                 strobe: bool = False, status_period_s: float = 0.04, ack_timeout_s: float = 0.5,
                 fault_hold_s: float = 0.3, backoff_max_s: float = 2.0,
                 day_night: bool = True, night_below: float = 35.0, day_above: float = 60.0,
                 probe_s: float = 10.0):
        super().__init__(name, clock, timeout_s)
        if night_below >= day_above:
            raise ValueError("night_below must be lower than day_above (the hysteresis)")
        # day/night switching by the daemon (DayNightSwitch), when a stereo camera is configured
        self.day_night = bool(day_night)
        self.night_below, self.day_above, self.probe_s = (float(night_below), float(day_above),
                                                          float(probe_s))
        self.port, self.baudrate = port, int(baudrate)
        self.want_rate_hz = float(rate_hz)
        self.want_strobe = bool(strobe)
        self.status_period_s = float(status_period_s)
        self.ack_timeout_s = float(ack_timeout_s)
        self.fault_hold_s = float(fault_hold_s)
        self.backoff = Backoff(0.1, backoff_max_s)
        self._ser = None
        self._buf = b""
        self._cmds: queue.Queue[str] = queue.Queue()
        self._queued: set[str] = set()       # command words in _cmds (see _correct)
        self._pending: dict[str, float] = {}      # command word -> deadline (monotonic)
        self._next_status = 0.0
        self.pulse_check = PulseCheck()
        self._status_sent: collections.deque = collections.deque()   # STATUS? send times
        self._judge_after = 0.0           # no pulse-check verdicts before (monotonic s)
        self.last_status: dict | None = None
        self._fault_text: dict[str, str] = {}

    @classmethod
    def from_config(cls, cfg, clock, shared):
        o = cfg.options
        check_timeout(cfg.name, cfg.timeout_s, o.get("status_period_s", 0.04),
                      "the status period (status_period_s)")
        if o.get("night_below", 35.0) >= o.get("day_above", 60.0):
            from hal.errors import ConfigError
            raise ConfigError("must be lower than day_above (that gap is the hysteresis)",
                              key=f"devices.{cfg.name}.night_below")
        return cls(cfg.name, clock, port=o.get("port", "/dev/fieldguard-strobe"),
                   baudrate=o.get("baudrate", 115200), timeout_s=cfg.timeout_s,
                   rate_hz=o.get("rate_hz", 10.0), strobe=o.get("strobe", False),
                   status_period_s=o.get("status_period_s", 0.04),
                   ack_timeout_s=o.get("ack_timeout_s", 0.5),
                   fault_hold_s=o.get("fault_hold_s", 0.3),
                   backoff_max_s=o.get("backoff_max_s", 2.0),
                   day_night=o.get("day_night", True), night_below=o.get("night_below", 35.0),
                   day_above=o.get("day_above", 60.0), probe_s=o.get("probe_s", 10.0))

    # ---- the interface (callable from any thread, never blocks) ----------------------------
    def set_rate(self, rate_hz: float) -> None:
        if not 0.1 <= rate_hz <= 60.0:
            raise ValueError(f"rate_hz must be in 0.1..60, got {rate_hz}")
        self.want_rate_hz = float(rate_hz)
        self._cmds.put(f"RATE {rate_hz:.2f}")

    def set_strobe(self, on: bool) -> None:
        self.want_strobe = bool(on)
        self._cmds.put("STROBE ON" if on else "STROBE OFF")

    # ---- port -----------------------------------------------------------------------------------
    def _open(self) -> None:
        import serial  # noqa: F401  (fail at start-up, not in the thread, if pyserial is missing)

    def _close(self) -> None:
        s, self._ser = self._ser, None
        if s is not None:
            try:
                s.write(frame_line("DISARM"))
            except Exception:
                pass
            s.close()

    def _disconnect(self) -> None:
        s, self._ser = self._ser, None
        if s is not None:
            try:
                s.close()
            except Exception:
                pass
        self._buf = b""
        self._pending.clear()
        self._status_sent.clear()
        self.pulse_check.reset()

    def _connect(self) -> None:
        import serial
        try:
            # reads wait at most 10 ms, so the STATUS polls keep to their period
            self._ser = serial.Serial(self.port, self.baudrate, timeout=0.01, write_timeout=0.2)
        except (serial.SerialException, OSError) as exc:
            self._ser = None
            raise DeviceOperationError(f"cannot open {self.port}: {exc}") from None
        self._ser.reset_input_buffer()
        self._buf = b""
        self._status_sent.clear()
        self._judge_after = 0.0
        self.pulse_check.reset()
        # (re)configure from scratch: the controller may have been power-cycled
        for c in (f"RATE {self.want_rate_hz:.2f}", "STROBE ON" if self.want_strobe else
                  "STROBE OFF", "ARM"):
            self._send(c)
        self._next_status = 0.0

    WRITE_TIMEOUT_S = 0.2

    def _write_all(self, data: bytes) -> None:
        """Write every byte, waiting at most WRITE_TIMEOUT_S for the port to take more. Not
        pyserial's write with a write_timeout: after a complete write it checks the clock and
        raises 'Write timeout' if the thread was descheduled that long (a loaded box, the
        soak's starved daemon), a reconnect over a write that went out (found by
        tests/fuzz/fuzz_strobe.py at nice 19 beside the soak; input regress-write-after-stall)."""
        view, end = memoryview(data), None
        while view:
            try:
                n = os.write(self._ser.fd, view)
            except BlockingIOError:
                n = 0
            view = view[n:]
            if not view:
                return
            now = time.monotonic()
            end = end or now + self.WRITE_TIMEOUT_S
            if now >= end:
                raise OSError(f"write timed out: {len(view)} byte(s) not taken in "
                              f"{self.WRITE_TIMEOUT_S:g} s")
            select.select([], [self._ser.fd], [], end - now)

    def _send(self, payload: str) -> None:
        import serial
        if payload == "STATUS?":
            # before the write: the controller cannot answer earlier (PulseCheck relies on it);
            # a request unanswered for timeout_s is given up (its answer was lost or is late:
            # either way the data is stale by then, and a new request is the best next step)
            t = time.monotonic()
            while self._status_sent and t - self._status_sent[0] > self.timeout_s:
                self._status_sent.popleft()
                # its answer may still come, and would take the next request's place: the
                # pulse check judges no answer for a while (the staleness check still runs)
                self._judge_after = t + 2 * self.ack_timeout_s
            self._status_sent.append(t)
        try:
            self._write_all(frame_line(payload))
        except (serial.SerialException, OSError) as exc:
            raise DeviceOperationError(f"write to {self.port} failed: {exc}") from None
        word = payload.split()[0]
        if word not in ("STATUS?", "PING"):
            self._pending[word] = time.monotonic() + self.ack_timeout_s
        self._count("sent")

    # ---- acquisition ----------------------------------------------------------------------------
    def _acquire_once(self) -> None:
        import serial
        if self._ser is None:
            self._connect_when_due(self._connect)
            return
        try:
            while True:
                try:
                    c = self._cmds.get_nowait()
                    self._queued.discard(c.split()[0])
                except queue.Empty:
                    break
                self._send(c)
            now = time.monotonic()
            # one STATUS? at a time (stop-and-wait): an answer is then paired with the one
            # request outstanding, or with none. With several outstanding and the old ones
            # given up after a timeout, answers that came later than that were paired with
            # the requests after theirs, for good: every answer judged against a request sent
            # after it was composed, and "stopped firing" whenever a pulse fell in between
            # (the soak with every device attached: a false stall every few seconds)
            waiting = self._status_sent and now - self._status_sent[-1] <= self.timeout_s
            if now >= self._next_status and not waiting:
                self._send("STATUS?")
                self._next_status = now + self.status_period_s
            data = self._ser.read(max(1, self._ser.in_waiting))
        except DeviceOperationError as exc:
            self._drop(str(exc))
            return
        except (serial.SerialException, OSError) as exc:
            self._drop(f"{self.port}: {exc}")
            return
        if data:
            self._buf += data
            while b"\n" in self._buf:
                line, self._buf = self._buf.split(b"\n", 1)
                self._handle(line)
            if len(self._buf) > 512:                     # no newline in sight: line noise
                self._count("bad_lines")
                self._buf = b""
                self._wire_error("bad data on the serial line: overlong line")
        now = time.monotonic()
        for word, deadline in list(self._pending.items()):
            if now > deadline:
                del self._pending[word]
                self._count("unanswered")
                self._fault(f"controller did not answer {word}")

    def _handle(self, raw: bytes) -> None:
        try:
            payload = parse_line(raw)
        except ValueError as exc:
            self._count("bad_lines")
            self._wire_error(f"bad data on the serial line: {exc}")
            return
        w = payload.split()
        if w[0] == "OK" and len(w) > 1:
            self._pending.pop(w[1], None)
        elif w[0] == "ERR":
            self._count("errors")
            self._fault(f"controller error: {payload[4:]}")
        elif w[0] == "FAULT":
            self._count("controller_faults")
            code, _, text = payload[6:].partition(" ")
            self._fault_text[code] = text
            self._wire_error(f"controller fault {code}: {text}")
        elif w[0] == "STATUS":
            try:
                st = parse_status(payload)
            except ValueError as exc:
                self._count("bad_lines")
                self._wire_error(str(exc))
                return
            # the request waiting (at most one, see _acquire_once): this answer's, unless it
            # is the late answer of a request given up (_send): then it takes the next one's
            # place and the next answer finds none waiting; neither is judged (_judge_after),
            # and the pairing is in step again
            sent = self._status_sent.popleft() if self._status_sent else None
            if time.monotonic() < self._judge_after:
                sent = None
            self._on_status(st, sent)
        else:
            self._count("other_lines")

    def _correct(self, command: str) -> None:
        """Queue a command that puts the controller right, unless the same command word is
        queued or waiting for its OK already: a controller that says "not armed" in every
        STATUS gets one ARM at a time, not 25 a second piling up and then written in one burst
        (found by tests/fuzz/fuzz_strobe.py: a queue of hundreds filled the serial line's
        buffer, a write timeout, a reconnect; corpus regress-command-flood)."""
        word = command.split()[0]
        if word in self._pending or word in self._queued:
            return
        self._queued.add(word)
        self._cmds.put(command)

    def _on_status(self, st: dict, sent_s: float | None = None) -> None:
        now = time.monotonic()
        self.last_status = st
        if st["fault"] or not st["armed"] or abs(st["rate_hz"] - self.want_rate_hz) > 0.01:
            self.pulse_check.reset()     # the pulse phase is learned again once all is well
        if st["fault"]:
            text = self._fault_text.get(str(st["fault"]), "")
            self._fault(f"controller fault {st['fault']}: {text}".rstrip(": "))
            return
        if not st["armed"]:
            self._fault("controller is not armed (cameras are not being triggered)")
            self._correct("ARM")
            return
        if abs(st["rate_hz"] - self.want_rate_hz) > 0.01:
            self._fault(f"controller runs at {st['rate_hz']:g} Hz, wanted "
                        f"{self.want_rate_hz:g} Hz")
            self._correct(f"RATE {self.want_rate_hz:.2f}")
            return
        if st["strobe"] != self.want_strobe:
            self._correct("STROBE ON" if self.want_strobe else "STROBE OFF")
        # is it firing? every pulse that was due must be in the counter
        was_missing = self.pulse_check.missing_since is not None
        if self.pulse_check.update(st["rate_hz"], st["pulses"], sent_s, now):
            if not was_missing:
                self._count("stalls")
            self._fault(f"trigger stopped firing (pulse counter stuck at {st['pulses']}, the "
                        f"next pulse is overdue)")
            return
        if self._distrusted() or self._pending:
            return          # keep the fault visible / wait for the acks
        self.backoff.reset()
        self._publish({"stamp_ns": self.clock.now_ns(), "rate_hz": st["rate_hz"],
                       "armed": st["armed"], "strobe": st["strobe"], "pulses": st["pulses"],
                       "fault": st["fault"]})

    def _stamp_of(self, sample) -> int:
        return sample["stamp_ns"]

    def day_night_switch(self, devices: dict) -> "DayNightSwitch | None":
        """The daemon's day/night switch for this controller and the first stereo camera that
        labels its frames (None if ``day_night`` is off or there is no such camera)."""
        if not self.day_night:
            return None
        cams = [d for d in devices.values() if d.kind == "stereo" and hasattr(d, "illumination")]
        if not cams:
            return None
        return DayNightSwitch(cams[0], self, self.night_below, self.day_above, self.probe_s)

    def selftest(self) -> tuple[bool, str]:
        h = self.selftest_health()
        st = self.last_status
        if h.ok and st:
            return True, (f"{self.port}: firing at {st['rate_hz']:g} Hz, strobe "
                          f"{'on' if st['strobe'] else 'off'}, {st['pulses']} pulses")
        return False, f"{self.port}: {h.reason or h.state.value}"


# ---------------------------------------------------------------------------------------------
class DayNightSwitch:
    """Day/night switching for a stereo camera lit by this controller's strobe. The daemon calls
    it after every loop cycle with the cycle's result (``loop.on_cycle``).

    * Labels: the camera's ``illumination`` (stamped on each frame it publishes, so the pipeline
      knows) follows the strobe state the controller *confirms* in its STATUS, not the command.
    * Day: each cycle, the ambient brightness of the cycle's left image (:func:`scene_brightness`:
      every 8th pixel, ~20k pixels at 1280x1024) goes through :func:`next_illumination`; below
      ``night_below`` the strobe is switched on.
    * Night: a lit frame says nothing about the ambient light, so every ``probe_s`` the strobe is
      switched off until a frame taken without it has arrived (stamped ``settle_s`` after the
      controller confirmed the strobe off; about 2-3 frames, labelled "day"), the ambient is
      measured on it, and the strobe goes back on unless the ambient is
      above ``day_above``. A probe that sees no unlit frame within ``probe_timeout_s`` puts the
      strobe back on (the camera or controller is in trouble; their health stops the gate).
    """

    def __init__(self, camera, trigger: "StrobeSerialTrigger", night_below: float = 35.0,
                 day_above: float = 60.0, probe_s: float = 10.0, probe_timeout_s: float = 1.0,
                 settle_s: float = 0.05):
        if night_below >= day_above:
            raise ValueError("night_below must be lower than day_above (the hysteresis)")
        self.camera, self.trigger = camera, trigger
        self.night_below, self.day_above = float(night_below), float(day_above)
        self.probe_ns, self.probe_timeout_ns = int(probe_s * 1e9), int(probe_timeout_s * 1e9)
        self.settle_ns = int(settle_s * 1e9)
        self._off_since: int | None = None      # when the controller confirmed the strobe off
        self.mode = NIGHT if getattr(trigger, "want_strobe", False) else DAY
        self.ambient: float | None = None
        self.switches = 0
        self.probes = 0
        self._probe_since: int | None = None
        self._next_probe: int | None = None

    def status(self) -> dict:
        return {"mode": self.mode, "ambient": None if self.ambient is None else
                round(self.ambient, 1), "switches": self.switches, "probes": self.probes}

    def _measure(self, frame) -> float:
        self.ambient = scene_brightness(frame.left)
        return self.ambient

    def __call__(self, res) -> None:
        st = self.trigger.newest()
        if st is not None:                      # label = what the controller says it does
            self.camera.illumination = NIGHT if st.get("strobe") else DAY
            if st.get("strobe"):
                self._off_since = None
            elif self._off_since is None:
                self._off_since = st["stamp_ns"]
        frame = res.inputs.stereo if res.inputs is not None else None
        now = res.stamp_ns
        if self.mode == DAY:
            if frame is None or frame.illumination != DAY:
                return
            if next_illumination(DAY, self._measure(frame), self.night_below,
                                 self.day_above) == NIGHT:
                self.mode = NIGHT
                self.switches += 1
                self.trigger.set_strobe(True)
                self._next_probe = now + self.probe_ns
            return
        # night
        if self._probe_since is None:
            if self._next_probe is None:
                self._next_probe = now + self.probe_ns
            if now >= self._next_probe:
                self._probe_since = now
                self.probes += 1
                self.trigger.set_strobe(False)
            return
        unlit = (frame is not None and frame.illumination == DAY and self._off_since is not None
                 and frame.stamp_ns > max(self._probe_since, self._off_since + self.settle_ns))
        if unlit:
            self._probe_since = None
            if next_illumination(NIGHT, self._measure(frame), self.night_below,
                                 self.day_above) == DAY:
                self.mode = DAY                  # the strobe is already off
                self.switches += 1
                return
            self.trigger.set_strobe(True)
            self._next_probe = now + self.probe_ns
        elif now - self._probe_since > self.probe_timeout_ns:
            self._probe_since = None
            self.trigger.set_strobe(True)
            self._next_probe = now + self.probe_ns
