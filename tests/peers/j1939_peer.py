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

    # udp_multicast delivers a node's own frames back to it (SocketCAN does not, by default).
    # can-j1939 answers an address claim carrying its own NAME by claiming again ("the
    # contender lost"), so its own echo made it claim ~25 000 times a second: the flood
    # overflowed the receivers' socket buffers and, now and then, a status frame of the box
    # was dropped on the way to the vehicle peer (a flaky alive-counter failure). NAMEs are
    # unique on a J1939 bus, so a claim with ours is our echo: ignore it.
    process_claim = ca._process_addressclaim

    def claim_unless_own_echo(mid, data, timestamp):
        if j1939.Name(bytes=data).value == name.value:
            return
        process_claim(mid, data, timestamp)

    ca._process_addressclaim = claim_unless_own_echo
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
