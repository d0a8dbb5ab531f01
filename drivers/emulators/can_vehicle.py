"""The vehicle side of the CAN contract in its own process (the link tests and the soak).

    python -m drivers.emulators.can_vehicle INTERFACE CHANNEL DBC

Sends wheel-based speed (PGN 65096, SA 0xF0) at 10 Hz; decodes every frame from the box with
cantools from the shipped DBC, and applies the contract: STOP unless a FG_SafetyStatus with a
good CRC and a new alive counter arrived within 300 ms and says SLOW/CLEAR. stdin commands:
``silent``, ``talk``, ``speed V``, ``report``, ``quit``. ``report`` prints one JSON line.
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
    db = cantools.database.load_file(dbc)
    by_pgn = {J1939Id.parse(m.frame_id).pgn: m for m in db.messages}
    bus = can.Bus(interface=iface, channel=channel)
    st = {"silent": False, "speed": 1.0}
    rep = {"status_ok": 0, "bad_crc": 0, "bad_counter": 0, "states": {}, "sa": [],
           "aiso": [], "sectors": 0, "last_status": None, "vehicle_stop": True,
           "stops_by_timeout": 0, "max_gap_ms": 0.0, "claims": []}
    lock = threading.Lock()
    last = {"t": None, "ctr": None}

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
            if p[0] == "report":
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
                rep["vehicle_stop"] = True          # the contract: 300 ms without a valid frame
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
                    rep["vehicle_stop"] = True
                    continue
                ctr = sig["FG_AliveCounter"]
                if last["ctr"] is not None and ctr != (last["ctr"] + 1) % 16:
                    rep["bad_counter"] += 1
                    rep["vehicle_stop"] = True
                    last["ctr"] = ctr
                    continue
                if last["t"] is not None:
                    rep["max_gap_ms"] = max(rep["max_gap_ms"], (now - last["t"]) * 1000)
                last["t"], last["ctr"] = now, ctr
                rep["status_ok"] += 1
                state = str(sig["FG_State"])
                rep["states"][state] = rep["states"].get(state, 0) + 1
                rep["vehicle_stop"] = state == "STOP"
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
