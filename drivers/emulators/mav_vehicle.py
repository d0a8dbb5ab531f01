"""A scripted MAVLink vehicle (ArduPilot Rover-like) in its own process: the vehicle side for the
link tests, tools/bench_links.py and the soak (tools/soak.py).

    python -m drivers.emulators.mav_vehicle CONNECTION [--sysid 1]

Sends HEARTBEAT (1 Hz, custom_mode = current mode), ATTITUDE and VFR_HUD (20 Hz); answers
MAV_CMD_DO_SET_MODE with COMMAND_ACK according to the script. Reads commands on stdin, one per
line; prints one JSON event per line on stdout:

    silent | talk           stop / resume sending anything
    mode N                  set the current custom mode
    refuse N                answer the next N DO_SET_MODE with DENIED
    drop N                  ignore the next N DO_SET_MODE (no ack at all)
    accept                  answer every DO_SET_MODE with ACCEPTED (default)
    garbage N               send N malformed packets (bad CRC, truncated, random bytes)
    nan                     send one ATTITUDE with NaN roll
    speed V                 ground speed in VFR_HUD
    yaw DEG                 heading in ATTITUDE (clockwise from north)
    pos LAT LON             position in GLOBAL_POSITION_INT (sent at the rate once set)
    mission LAT,LON ...     the mission: item 0 home at the first point, then a NAV_WAYPOINT
                            at each (global, degE7), served over the mission protocol
    current N               MISSION_CURRENT's seq (sent at 1 Hz with the mission's total)
    mission_mute N          leave the next N mission requests unanswered
    quit

Events: {"ev": "ready"}, {"ev": "set_mode", "mode": 4, "confirmation": 0, "answer": "..."},
{"ev": "mission_rq", "type": "MISSION_REQUEST_LIST" | "MISSION_REQUEST_INT", "seq": n,
"answer": "sent" | "muted"} and {"ev": "mission_ack", "type": n} for the box's mission requests,
{"ev": "rx", "type": "..."} for the first message of each type from the box; with --states also
"hb", "od" and "vhb" (see --help).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import sys
import threading
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402


def emit(**kw):
    sys.stdout.write(json.dumps(kw) + "\n")
    sys.stdout.flush()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("connection")
    ap.add_argument("--sysid", type=int, default=1)
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--states", action="store_true",
                    help="print every HEARTBEAT from a component 196 (the box) as "
                         '{"ev": "hb", "status": MAV_STATE, "t": monotonic, "lost": n, "rx": n}; '
                         "lost counts gaps in the box's packet sequence numbers; and "
                         '{"ev": "od", "t": monotonic} for every OBSTACLE_DISTANCE (one a cycle); '
                         'and {"ev": "vhb", "mode": N, "t": monotonic} for each HEARTBEAT the '
                         "vehicle itself sends (its own mode, as the box is told it)")
    a = ap.parse_args()
    m = mavutil.mavlink_connection(a.connection, source_system=a.sysid, source_component=1,
                                   dialect="ardupilotmega")
    st = {"silent": False, "mode": 10, "refuse": 0, "drop": 0, "speed": 1.5, "nan": False,
          "yaw": 0.3, "pos": None, "mission": [], "current": 0, "mission_mute": 0}
    lock = threading.Lock()
    seen = set()
    box_seq = {}                      # (sysid, compid) -> last packet sequence number
    box_rx = {"rx": 0, "lost": 0}

    def stdin_reader():
        for line in sys.stdin:
            parts = line.split()
            if not parts:
                continue
            cmd, arg = parts[0], (parts[1] if len(parts) > 1 else "0")
            with lock:
                if cmd == "quit":
                    os._exit(0)
                elif cmd in ("silent", "talk"):
                    st["silent"] = cmd == "silent"
                elif cmd in ("mode", "refuse", "drop"):
                    st[cmd] = int(arg)
                elif cmd == "accept":
                    st["refuse"] = st["drop"] = 0
                elif cmd == "speed":
                    st["speed"] = float(arg)
                elif cmd == "nan":
                    st["nan"] = True
                elif cmd == "yaw":
                    st["yaw"] = math.radians(float(arg))
                elif cmd == "pos":
                    st["pos"] = (float(parts[1]), float(parts[2]))
                elif cmd == "mission":
                    pts = [tuple(float(v) for v in p.split(",")) for p in parts[1:]]
                    st["mission"] = pts[:1] + pts if pts else []     # item 0: home
                elif cmd in ("current", "mission_mute"):
                    st[cmd] = int(arg)
                elif cmd == "garbage":
                    for i in range(int(arg)):
                        good = m.mav.attitude_encode(0, 0.1, 0.0, 0.0, 0, 0, 0).pack(m.mav)
                        bad = bytearray(good)
                        if i % 3 == 0:
                            bad[-3] ^= 0xFF                 # bad CRC
                        elif i % 3 == 1:
                            bad = bad[:len(bad) // 2]       # truncated
                        else:
                            bad = bytearray([0xFD]) + bytearray(random.randbytes(30))
                        m.write(bytes(bad))
            emit(ev="ack_cmd", cmd=cmd)

    threading.Thread(target=stdin_reader, daemon=True).start()
    emit(ev="ready")
    period = 1.0 / a.rate
    next_tick, last_hb, t0 = time.monotonic(), 0.0, time.monotonic()
    while True:
        now = time.monotonic()
        if now >= next_tick:
            next_tick += period
            with lock:
                silent, mode, speed = st["silent"], st["mode"], st["speed"]
                nan, st["nan"] = st["nan"], False
                yaw, pos = st["yaw"], st["pos"]
                current, total = st["current"], len(st["mission"])
            if not silent:
                boot_ms = int((now - t0) * 1000)
                if now - last_hb >= 1.0:
                    last_hb = now
                    m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GROUND_ROVER,
                                         mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                         mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | 128,
                                         mode, mavutil.mavlink.MAV_STATE_ACTIVE)
                    if a.states:
                        emit(ev="vhb", mode=mode, t=time.monotonic())
                    if total:
                        m.mav.mission_current_send(current, max(0, total - 1))
                m.mav.attitude_send(boot_ms, math.nan if nan else 0.02, -0.05, yaw, 0.0, 0.0,
                                    0.1)
                if pos is not None:
                    m.mav.global_position_int_send(
                        boot_ms, int(round(pos[0] * 1e7)), int(round(pos[1] * 1e7)), 0, 0,
                        int(speed * 100 * math.cos(yaw)), int(speed * 100 * math.sin(yaw)), 0,
                        int(math.degrees(yaw) * 100) % 36000)
                m.mav.vfr_hud_send(speed, speed, 17, 0, 0.0, 0.0)
        msg = m.recv_match(blocking=True, timeout=max(0.0, min(period, next_tick - now)))
        if msg is None:
            continue
        t = msg.get_type()
        if a.states and t != "BAD_DATA" and msg.get_srcComponent() == 196:
            src = (msg.get_srcSystem(), 196)
            seq = msg.get_seq()
            if src in box_seq:
                box_rx["lost"] += (seq - box_seq[src] - 1) % 256
            box_seq[src] = seq
            box_rx["rx"] += 1
            if t == "HEARTBEAT":
                emit(ev="hb", status=msg.system_status, t=time.monotonic(), **box_rx)
            elif t == "OBSTACLE_DISTANCE":            # one a cycle: the box's cycles counted
                emit(ev="od", t=time.monotonic())
        if t not in seen and t != "BAD_DATA":
            seen.add(t)
            emit(ev="rx", type=t, src=[msg.get_srcSystem(), msg.get_srcComponent()])
        if t in ("MISSION_REQUEST_LIST", "MISSION_REQUEST_INT", "MISSION_REQUEST") and \
                msg.target_system == a.sysid:
            with lock:
                mute = st["mission_mute"] > 0
                st["mission_mute"] -= 1 if mute else 0
                items = list(st["mission"])
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            seq = getattr(msg, "seq", -1)
            if not mute:
                if t == "MISSION_REQUEST_LIST":
                    m.mav.mission_count_send(*src, len(items))
                elif 0 <= seq < len(items):
                    lat, lon = items[seq]
                    m.mav.mission_item_int_send(*src, seq, 6 if seq else 0, 16, 0, 1, 0, 0, 0,
                                                0, int(round(lat * 1e7)),
                                                int(round(lon * 1e7)), 0.0)
            emit(ev="mission_rq", type=t, seq=seq, answer="muted" if mute else "sent",
                 src=list(src))
        elif t == "MISSION_ACK" and msg.target_system == a.sysid:
            emit(ev="mission_ack", type=msg.type, src=[msg.get_srcSystem(),
                                                       msg.get_srcComponent()])
        if t == "COMMAND_LONG" and msg.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE:
            with lock:
                if st["silent"]:
                    answer = "silent"
                elif st["drop"] > 0:
                    st["drop"] -= 1
                    answer = "dropped"
                elif st["refuse"] > 0:
                    st["refuse"] -= 1
                    answer = "denied"
                else:
                    answer = "accepted"
                    st["mode"] = int(msg.param2)
            if answer in ("denied", "accepted"):
                res = (mavutil.mavlink.MAV_RESULT_ACCEPTED if answer == "accepted"
                       else mavutil.mavlink.MAV_RESULT_DENIED)
                m.mav.command_ack_send(msg.command, res, 0, 0, msg.get_srcSystem(),
                                       msg.get_srcComponent())
            emit(ev="set_mode", mode=int(msg.param2), confirmation=msg.confirmation,
                 answer=answer, t=time.monotonic())


if __name__ == "__main__":
    main()
