"""The vehicle side of the CAN contract in its own process (the link tests and the soak).

    python -m drivers.emulators.can_vehicle INTERFACE CHANNEL DBC

Sends wheel-based speed (PGN 65096, SA 0xF0) at 10 Hz; decodes every frame from the box with
cantools from the shipped DBC, and applies the contract: STOP unless a FG_SafetyStatus with a
good CRC and a new alive counter arrived within 300 ms and says SLOW/CLEAR. stdin commands:
``silent``, ``talk``, ``speed V``, ``report``, ``quit``. ``report`` prints one JSON line.
``busoff`` puts one error frame with CAN_ERR_BUSOFF on the bus (what SocketCAN hands a node
whose controller went bus-off; python-can's udp_multicast carries error frames). With
``--events`` every change of the vehicle's own verdict is printed as
``{"ev": "state", "stop": bool, "state": "STOP|SLOW|CLEAR|timeout|bad_crc|bad_counter", "t":
monotonic}``; ``report`` then also has ``lost`` (alive-counter gaps: frames that never came).
"""
from __future__ import annotations

import json
import sys
import threading
import time

import can
import cantools

sys.path.insert(0, __file__.rsplit("/drivers/", 1)[0])
from drivers.j1939 import J1939Id, crc8_sae_j1850, make_id  # noqa: E402


def main():
    iface, channel, dbc = sys.argv[1:4]
    events = "--events" in sys.argv[4:]
    db = cantools.database.load_file(dbc)
    by_pgn = {J1939Id.parse(m.frame_id).pgn: m for m in db.messages}
    bus = can.Bus(interface=iface, channel=channel)
    st = {"silent": False, "speed": 1.0}
    rep = {"status_ok": 0, "bad_crc": 0, "bad_counter": 0, "states": {}, "sa": [],
           "aiso": [], "sectors": 0, "last_status": None, "vehicle_stop": True,
           "stops_by_timeout": 0, "max_gap_ms": 0.0, "claims": [], "lost": 0}
    lock = threading.Lock()
    last = {"t": None, "ctr": None}

    def verdict(stop: bool, why: str, now: float) -> None:
        """The vehicle's own STOP/go verdict (under the lock); printed when it changes."""
        was = rep["vehicle_stop"]
        rep["vehicle_stop"] = stop
        if events and (stop != was or why != last.get("why")):
            last["why"] = why
            sys.stdout.write(json.dumps({"ev": "state", "stop": stop, "state": why,
                                         "t": now, "lost": rep["lost"]}) + "\n")
            sys.stdout.flush()

    def report():
        with lock:
            sys.stdout.write(json.dumps(rep) + "\n")
            sys.stdout.flush()

    def commands():
        for line in sys.stdin:
            p = line.split()
            if not p:
                continue
            with lock:
                if p[0] in ("silent", "talk"):
                    st["silent"] = p[0] == "silent"
                elif p[0] == "speed":
                    st["speed"] = float(p[1])
                elif p[0] == "reset":
                    rep.update(status_ok=0, bad_crc=0, bad_counter=0, states={}, aiso=[],
                               max_gap_ms=0.0, stops_by_timeout=0)
            if p[0] == "busoff":
                bus.send(can.Message(arbitration_id=0x40, is_error_frame=True, dlc=8,
                                     data=bytes(8)))
            elif p[0] == "report":
                report()
            elif p[0] == "quit":
                bus.shutdown()
                sys.exit(0)

    def sender():
        wbsd = by_pgn[65096]
        while True:
            with lock:
                silent, v = st["silent"], st["speed"]
            if not silent:
                data = wbsd.encode({"WBSD_Speed": v, "WBSD_Distance": 0, "WBSD_Direction": 1},
                                   padding=True)
                try:
                    bus.send(can.Message(arbitration_id=make_id(3, 65096, 0xF0), data=data,
                                         is_extended_id=True))
                except can.CanError:
                    pass
            time.sleep(0.1)

    threading.Thread(target=commands, daemon=True).start()
    threading.Thread(target=sender, daemon=True).start()
    sys.stdout.write(json.dumps({"ev": "ready"}) + "\n")
    sys.stdout.flush()
    while True:
        msg = bus.recv(0.05)
        now = time.monotonic()
        with lock:
            if last["t"] is not None and now - last["t"] > 0.3 and not rep["vehicle_stop"]:
                verdict(True, "timeout", now)       # the contract: 300 ms without a valid frame
                rep["stops_by_timeout"] += 1
            if msg is None:
                continue
            jid = J1939Id.parse(msg.arbitration_id)
            m = by_pgn.get(jid.pgn)
            if m is None or jid.sa == 0xF0:
                continue
            if jid.pgn == 60928:
                rep["claims"].append([jid.sa, bytes(msg.data).hex()])
                continue
            data = bytes(msg.data)
            if m.name == "FG_SafetyStatus":
                sig = m.decode(data, decode_choices=True)
                if crc8_sae_j1850(data[:7]) != data[7]:
                    rep["bad_crc"] += 1
                    verdict(True, "bad_crc", now)
                    continue
                ctr = sig["FG_AliveCounter"]
                if last["ctr"] is not None and ctr != (last["ctr"] + 1) % 16:
                    rep["bad_counter"] += 1
                    rep["lost"] += (ctr - last["ctr"] - 1) % 16
                    verdict(True, "bad_counter", now)
                    last["ctr"] = ctr
                    continue
                if last["t"] is not None:
                    rep["max_gap_ms"] = max(rep["max_gap_ms"], (now - last["t"]) * 1000)
                last["t"], last["ctr"] = now, ctr
                rep["status_ok"] += 1
                state = str(sig["FG_State"])
                rep["states"][state] = rep["states"].get(state, 0) + 1
                verdict(state == "STOP", state, now)
                rep["last_status"] = {k: (str(v) if not isinstance(v, (int, float)) else v)
                                      for k, v in sig.items()}
                if jid.sa not in rep["sa"]:
                    rep["sa"].append(jid.sa)
            elif m.name == "AISO_AllImplementsStop":
                s = m.decode(data, decode_choices=False)
                rep["aiso"].append([s["AISO_TransitionNumber"],
                                    s["AISO_StopAllImplementOperations"], data[:6].hex()])
                del rep["aiso"][:-50]
            elif m.name == "FG_ObstacleSectors":
                m.decode(data)
                rep["sectors"] += 1


if __name__ == "__main__":
    main()
