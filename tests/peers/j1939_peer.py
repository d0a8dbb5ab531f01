"""An independent J1939 node (the can-j1939 stack) for the link tests: it claims an address with
its own NAME and counts the box's frames per (PGN, source address).

    python tests/peers/j1939_peer.py INTERFACE CHANNEL ADDRESS NAME_HEX

stdin: ``report`` prints {"state": ..., "address": ..., "rx": {"pgn:sa": n}}; ``quit``.
"""
from __future__ import annotations

import json
import sys
import threading

import j1939


def main():
    iface, channel, addr, name_hex = sys.argv[1:5]
    name = j1939.Name(value=int(name_hex, 0))
    ecu = j1939.ElectronicControlUnit()
    ecu.connect(interface=iface, channel=channel)
    ca = j1939.ControllerApplication(name, int(addr, 0))
    rx: dict[str, int] = {}
    lock = threading.Lock()

    def on_message(priority, pgn, sa, timestamp, data):
        with lock:
            k = f"{pgn}:{sa}"
            rx[k] = rx.get(k, 0) + 1

    ecu.subscribe(on_message)
    ecu.add_ca(controller_application=ca)
    ca.start()
    print(json.dumps({"ev": "ready"}), flush=True)
    for line in sys.stdin:
        cmd = line.strip()
        if cmd == "report":
            with lock:
                print(json.dumps({"ev": "report", "state": ca.state,
                                  "address": ca.device_address, "rx": dict(rx)}), flush=True)
        elif cmd == "quit":
            break
    ca.stop()
    ecu.disconnect()


if __name__ == "__main__":
    main()
