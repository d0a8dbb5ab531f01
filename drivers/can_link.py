"""The box's link to a tractor or sprayer over CAN: SAE J1939 / ISO 11783, with python-can and
cantools.

What goes out (every frame is described by ``drivers/fieldguard.dbc`` and encoded through it):

* ``FG_SafetyStatus`` (PGN 0xFF50) every cycle: state, reason code, zone, nearest obstacle
  distance and bearing, speed limit, a 4-bit alive counter and a CRC-8/SAE-J1850. The vehicle
  side stops when no valid frame arrived for 300 ms, the counter freezes or the CRC is wrong.
  It is sent only from the loop's ``send()``: a hung loop falls silent, and silence is STOP.
* ``FG_ObstacleSectors`` (PGN 0xFF51): the 72 sectors, 12 multiplexed frames, every cycle.
* ISO 11783-7 ``AISO`` (PGN 64770, all implements stop operations) with its transition number:
  every cycle while STOP, on change and every second otherwise (state "permit").
* ADDRESS CLAIMED (PGN 60928) at start, in answer to requests, and when contested.

What comes in: vehicle speed from a configurable PGN (default wheel-based speed, 65096) decoded
with the same DBC, address claims, requests, and error frames. No speed frame for ``timeout_s``
(missing peer), bus-off, a burst of error frames, a lost address claim or a failed write is a
fault, so the gate stops; counters and peers show in ``fieldguard status``.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

from drivers.j1939 import (ADDR_NULL, PGN_AISO, AddressClaimer, ClaimState, J1939Id, J1939Name,
                           crc8_sae_j1850, make_id)
from drivers.reconnect import WireFaults
from hal.devices import VehicleLink
from hal.errors import DeviceInitializationError, DeviceOperationError
from hal.types import GateOutput, GateState, VehicleState

log = logging.getLogger("fieldguard.link.can")

# package data (pyproject.toml): beside this module in a source tree and in the installed wheel
DEFAULT_DBC = str(Path(__file__).resolve().with_name("fieldguard.dbc"))
DEFAULT_NAME = "0xA00C810000E00001"      # arbitrary-address capable, agricultural, function 129
STATE_CODE = {GateState.STOP: 0, GateState.SLOW: 1, GateState.CLEAR: 2}
CAN_ERR_BUSOFF = 0x40                     # linux/can/error.h
CAN_ERR_RESTARTED = 0x100

# (substring of the gate's reason, code in FG_ReasonCode) - first match wins
REASON_CODES = (
    ("shutting down", 7), ("stop zone", 1), ("slow zone", 2), ("holding", 6), ("booting", 6),
    ("lagging", 4), ("did not go out", 5), ("no vehicle link", 9), ("pipeline", 8),
    ("stale", 3), ("no data", 3), ("fault", 3), ("could not open", 3), ("error", 3),
    ("zone clear", 0),
)


def reason_code(out: GateOutput) -> int:
    text = out.reason.lower()
    for key, code in REASON_CODES:
        if key in text:
            return code
    return 0 if out.state is GateState.CLEAR else 255


def _sector_raw(d: float | None) -> int:
    if d is None:
        return 251                                  # clear
    if not math.isfinite(d) or d < 0:
        return 255
    return max(0, min(250, int(round(d / 0.2))))


class CanJ1939VehicleLink(WireFaults, VehicleLink):
    options_schema = {
        "interface": str, "channel": str, "bitrate": int, "port": int,
        "name": str, "preferred_address": int, "dbc": str,
        "speed_pgn": int, "speed_signal": str, "direction_signal": str,
        "speed_source_address": int, "sectors": bool, "aiso": bool,
        "error_frames_per_s_fault": int,
    }
    default_timeout_s = 0.3

    def __init__(self, name, clock, timeout_s=0.3, *, interface="socketcan", channel="can0",
                 bitrate=0, port=0, j1939_name=DEFAULT_NAME, preferred_address=0x80,
                 dbc=DEFAULT_DBC, speed_pgn=65096, speed_signal="WBSD_Speed",
                 direction_signal="WBSD_Direction", speed_source_address=-1, sectors=True,
                 aiso=True, error_frames_per_s_fault=20):
        super().__init__(name, clock, timeout_s)
        self.interface, self.channel, self.bitrate, self.port = interface, channel, bitrate, port
        self.jname = J1939Name.parse(j1939_name)
        self.claimer = AddressClaimer(self.jname, preferred_address)
        self.dbc_path = dbc or DEFAULT_DBC
        self.speed_pgn = speed_pgn
        self.speed_signal, self.direction_signal = speed_signal, direction_signal
        self.speed_source_address = speed_source_address
        self.send_sectors, self.send_aiso = sectors, aiso
        self.error_limit = error_frames_per_s_fault
        self.bus = None
        self.db = None
        self._tx_lock = threading.Lock()
        self._alive = 15                          # the first frame carries 0
        self._aiso_state: int | None = None
        self._aiso_transitions = 0
        self._aiso_last_ns = 0
        self._speed_seq = 0
        self._speed_peer: dict = {}
        self._err_times: list[float] = []
        self._last_addr = None
        self._last_state_check = 0.0
        self.last_wire_ns: int | None = None      # when the newest status frame went out

    @classmethod
    def check_options(cls, options) -> tuple[str, str] | None:
        """(key, message) for what ``open`` would refuse (config check and run agree): a DBC
        that is not there or does not parse, a python-can interface that does not exist."""
        dbc = options.get("dbc") or DEFAULT_DBC
        try:
            import cantools
            cantools.database.load_file(dbc)
        except ImportError:
            pass
        except Exception as exc:
            what = "" if options.get("dbc") else " (the shipped one: reinstall fieldguard)"
            return "dbc", f"cannot load the DBC {dbc}{what}: {exc}"
        iface = options.get("interface", "socketcan")
        try:
            from can.interfaces import VALID_INTERFACES
        except ImportError:
            return None
        if iface not in VALID_INTERFACES:
            return "interface", (f"unknown python-can interface {iface!r}; known: "
                                 f"{', '.join(sorted(VALID_INTERFACES))}")
        return None

    @classmethod
    def from_config(cls, cfg, clock, shared):
        o = dict(cfg.options)
        kw = {k: o[k] for k in ("interface", "channel", "bitrate", "port", "preferred_address",
                                 "dbc", "speed_pgn", "speed_signal", "direction_signal",
                                 "speed_source_address", "sectors", "aiso",
                                 "error_frames_per_s_fault") if k in o}
        if "name" in o:
            kw["j1939_name"] = o["name"]
        return cls(cfg.name, clock, cfg.timeout_s, **kw)

    # ---- life cycle ---------------------------------------------------------------------------
    def _open(self) -> None:
        try:
            import can
            import cantools
        except ImportError as exc:
            raise DeviceInitializationError(f"python-can and cantools are needed: {exc}")
        try:
            self.db = cantools.database.load_file(self.dbc_path)
        except Exception as exc:
            raise DeviceInitializationError(f"cannot load DBC {self.dbc_path}: {exc}")
        self.msg_status = self.db.get_message_by_name("FG_SafetyStatus")
        self.msg_sectors = self.db.get_message_by_name("FG_ObstacleSectors")
        self.msg_aiso = self.db.get_message_by_name("AISO_AllImplementsStop")
        self.msg_claim = self.db.get_message_by_name("J1939_AddressClaimed")
        self._rx_by_pgn = {J1939Id.parse(m.frame_id).pgn: m for m in self.db.messages}
        self.speed_msg = self._rx_by_pgn.get(self.speed_pgn)
        if self.speed_msg is None or self.speed_signal not in [s.name for s in
                                                                self.speed_msg.signals]:
            raise DeviceInitializationError(
                f"speed PGN {self.speed_pgn} / signal {self.speed_signal!r} not in {self.dbc_path}")
        kw = {}
        if self.bitrate:
            kw["bitrate"] = self.bitrate
        if self.port:
            kw["port"] = self.port
        try:
            self.bus = can.Bus(interface=self.interface, channel=self.channel, **kw)
        except Exception as exc:
            raise DeviceInitializationError(
                f"cannot open CAN {self.interface}:{self.channel}: {exc}")
        self._claim_start()

    def _close(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.shutdown()

    def _claim_start(self):
        for f in self.claimer.start(time.monotonic()):
            self._tx(f.can_id, f.data)
        self._last_addr = self.claimer.address

    # ---- wire ---------------------------------------------------------------------------------
    def _tx(self, can_id: int, data: bytes) -> None:
        """One frame out, never waiting for the bus. Raises DeviceOperationError."""
        import can
        bus = self.bus
        if bus is None:
            raise DeviceOperationError("bus not open")
        msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=True)
        try:
            with self._tx_lock:
                bus.send(msg, timeout=0.0)
        except can.CanError as exc:
            self._count("tx_errors")
            cause = exc.__cause__ or exc
            raise DeviceOperationError(f"CAN write failed: {cause}") from exc
        self._count("tx_frames")

    def _encode(self, message, values: dict) -> bytes:
        return bytes(message.encode(values, scaling=False, padding=True, strict=False))

    def status_payload(self, out: GateOutput) -> bytes:
        """The FG_SafetyStatus payload for ``out`` (advances the alive counter)."""
        self._alive = (self._alive + 1) & 0xF
        nearest_raw, bearing_raw = 0xFFFF, 0xFF
        if out.nearest_m is not None and math.isfinite(out.nearest_m):
            nearest_raw = max(0, min(0xFFFE, int(round(out.nearest_m / 0.01))))
        near = [s for s in out.sectors if s.distance_m is not None]
        if near:
            s = min(near, key=lambda s: s.distance_m)
            bearing = 0.5 * (s.angle_min_deg + s.angle_max_deg)
            bearing_raw = max(0, min(254, int(round(bearing)) + 127))
        if out.state is GateState.CLEAR:
            zone = 0
        elif out.state is GateState.SLOW:
            zone = 1
        else:
            zone = 2 if "stop zone" in out.reason else 3
        limit = 0xFF
        if out.speed_limit_mps is not None:
            limit = max(0, min(254, int(round(out.speed_limit_mps / 0.1))))
        values = {"FG_State": STATE_CODE[out.state], "FG_Zone": zone,
                  "FG_AliveCounter": self._alive, "FG_ReasonCode": reason_code(out),
                  "FG_NearestDistance": nearest_raw, "FG_NearestBearing": bearing_raw,
                  "FG_SpeedLimit": limit, "FG_GateSeq": out.seq & 0xFF, "FG_CRC": 0}
        data = self._encode(self.msg_status, values)
        values["FG_CRC"] = crc8_sae_j1850(data[:7])
        return self._encode(self.msg_status, values)

    def sector_payloads(self, out: GateOutput) -> list[bytes]:
        raws = [_sector_raw(s.distance_m) for s in out.sectors[:72]]
        raws += [255] * (72 - len(raws))              # no picture: no data
        frames = []
        for g in range(12):
            vals = {"FG_SectorGroup": g, "FG_SectorGateSeq": out.seq & 0xFF}
            for k in range(6):
                i = 6 * g + k
                vals[f"FG_Sector_{i:02d}"] = raws[i]
            frames.append(self._encode(self.msg_sectors, vals))
        return frames

    def aiso_payload(self, stop: bool) -> bytes:
        st = 0 if stop else 1
        if self._aiso_state is not None and st != self._aiso_state:
            self._aiso_transitions = (self._aiso_transitions + 1) & 0xFF
        self._aiso_state = st
        return self._encode(self.msg_aiso, {"AISO_TransitionNumber": self._aiso_transitions,
                                            "AISO_StopAllImplementOperations": st})

    def _id(self, message) -> int:
        j = J1939Id.parse(message.frame_id)
        return make_id(j.priority, j.pgn, self.claimer.address, j.da)

    # ---- the loop side ------------------------------------------------------------------------
    def send(self, output: GateOutput) -> bool:
        if self.bus is None or self.db is None:
            return False
        self.claimer.tick(time.monotonic())
        if not self.claimer.usable:
            self._count("not_sent_no_address")
            if self.claimer.state == ClaimState.CANNOT_CLAIM:
                self._fault("J1939 address claim lost: cannot claim an address")
            return False
        try:
            self._tx(self._id(self.msg_status), self.status_payload(output))
            self.last_wire_ns = time.monotonic_ns()
            if self.send_aiso:
                stop = output.state is GateState.STOP
                now = self.clock.now_ns()
                changed = self._aiso_state != (0 if stop else 1)
                if stop or changed or now - self._aiso_last_ns >= 1_000_000_000:
                    self._tx(self._id(self.msg_aiso), self.aiso_payload(stop))
                    self._aiso_last_ns = now
            if self.send_sectors:
                sid = self._id(self.msg_sectors)
                for data in self.sector_payloads(output):
                    self._tx(sid, data)
        except DeviceOperationError as exc:
            self._fault(str(exc))
            return False
        return True

    # ---- the receive side (own thread) --------------------------------------------------------
    def _acquire_once(self) -> None:
        import can
        bus = self.bus
        if bus is None:
            self._stop_evt.wait(0.1)
            return
        try:
            msg = bus.recv(timeout=0.05)
        except can.CanError as exc:
            self._count("rx_errors")
            raise DeviceOperationError(f"CAN read failed: {exc.__cause__ or exc}") from exc
        now = time.monotonic()
        self._check_bus_state(now)
        for f in self.claimer.tick(now):
            self._tx(f.can_id, f.data)
        if msg is None:
            return
        if msg.is_error_frame:
            self._on_error_frame(msg, now)
            return
        if not msg.is_extended_id:
            self._count("rx_ignored")
            return
        self._count("rx_frames")
        data = bytes(msg.data)
        for f in self.claimer.on_frame(msg.arbitration_id, data, now):
            try:
                self._tx(f.can_id, f.data)
            except DeviceOperationError as exc:
                self._fault(str(exc))
        if self.claimer.address != self._last_addr:
            log.warning("%s: address claim contested (%d lost): now at %s", self.name,
                        self.claimer.lost, self.claimer.address)
            self._count("address_changes")
            self._last_addr = self.claimer.address
        if self.claimer.state == ClaimState.CANNOT_CLAIM:
            self._fault("J1939 address claim lost: cannot claim an address")
            return
        jid = J1939Id.parse(msg.arbitration_id)
        if jid.pgn == self.speed_pgn and (self.speed_source_address < 0
                                          or jid.sa == self.speed_source_address):
            self._on_speed(jid, data)

    def _on_speed(self, jid: J1939Id, data: bytes) -> None:
        if self._distrusted():
            self._count("speed_discarded")
            return
        if len(data) < self.speed_msg.length:
            self._count("rx_malformed")
            self._fault(f"malformed speed frame from 0x{jid.sa:02X}: {len(data)} bytes")
            return
        raw = self.speed_msg.decode(data, decode_choices=False, scaling=False)
        sig = self.speed_msg.get_signal_by_name(self.speed_signal)
        r = int(raw[self.speed_signal])
        if sig.length >= 16 and r >= 0xFB00 or sig.length == 8 and r >= 0xFB:
            self._count("speed_not_available")      # J1939 error / not-available range
            return
        speed = r * sig.scale + sig.offset
        if self.direction_signal and self.direction_signal in raw:
            if int(raw[self.direction_signal]) == 0:
                speed = -speed
        self._speed_seq += 1
        self._speed_peer = {"peer": "speed source", "address": jid.sa, "pgn": self.speed_pgn,
                            "speed_mps": round(speed, 3), "seen_ns": self.clock.now_ns()}
        self._publish(VehicleState(stamp_ns=self.clock.now_ns(), seq=self._speed_seq,
                                   speed_mps=float(speed)))

    def _on_error_frame(self, msg, now: float) -> None:
        self._count("error_frames")
        # latched for fault_hold_s: the next speed frame (<= 100 ms) must not clear a bus-off
        # before the loop has seen it (the soak found bus-offs that never became a STOP)
        if msg.arbitration_id & CAN_ERR_BUSOFF:
            self._count("bus_off")
            self._wire_error("CAN bus-off")
            return
        self._err_times = [t for t in self._err_times if now - t < 1.0] + [now]
        if len(self._err_times) >= self.error_limit:
            self._wire_error(f"CAN bus errors: {len(self._err_times)} error frames in 1 s")

    def _check_bus_state(self, now: float) -> None:
        if now - self._last_state_check < 0.5:
            return
        self._last_state_check = now
        try:
            import can
            state = self.bus.state
        except (NotImplementedError, AttributeError):
            return
        except Exception:
            return
        if state is can.BusState.ERROR:
            self._count("bus_off")
            self._fault("CAN controller in error state (bus-off)")

    # ---- status -------------------------------------------------------------------------------
    def peers(self):
        c = self.claimer
        me = {"peer": "self", "interface": f"{self.interface}:{self.channel}",
              "address": c.address, "claim": c.state, "name": f"0x{self.jname.value:016X}",
              "contests": c.contests, "lost": c.lost}
        out = [me]
        if self._speed_peer:
            p = dict(self._speed_peer)
            p["age_s"] = round((self.clock.now_ns() - p.pop("seen_ns")) / 1e9, 3)
            out.append(p)
        for addr, nm in sorted(c.others.items()):
            if nm != self.jname.value:
                out.append({"peer": "claimant", "address": addr, "name": f"0x{nm:016X}"})
        return out
