"""Write the hand-made seed inputs of every target into tests/fuzz/corpus/<target>/seed-*
(``python -m tests.fuzz.make_seeds``). The fuzzers' own finds are added next to them by
tools/fuzz.sh (libFuzzer's merge: only inputs that add coverage)."""
from __future__ import annotations

import json
import os
import struct

import numpy as np

from tests.fuzz.common import CORPUS, ROOT


def _write(target: str, name: str, data: bytes) -> None:
    d = CORPUS / target
    d.mkdir(parents=True, exist_ok=True)
    (d / f"seed-{name}").write_bytes(data)


def cola():
    from drivers.emulators.sick_lms1xx import encode_scandata
    r = np.linspace(0.5, 30, 61)
    r[5] = np.nan
    a = encode_scandata(r, -45.0, 4.5, telegram_counter=1, scan_counter=1, time_us=1000)
    b = encode_scandata(r[::-1], -45.0, 4.5, telegram_counter=2, scan_counter=2, time_us=41000,
                        rssi=np.arange(61) % 256)
    _write("cola", "two-scans", b"\x00" + a + b)
    _write("cola", "split", b"\x05" + b"junk" + a + b"\x02sRA LMDscandata 1" + b)
    _write("cola", "other", b"\x00\x02sRA LMCstartmeas 0\x03\x02sEA LMDscandata 1\x03" + a)


def strobe():
    from drivers.strobe_serial import frame_line
    lines = [frame_line("STATUS rate=10.00 armed=1 strobe=0 pulses=1234 fault=0"),
             frame_line("OK RATE"), frame_line("OK ARM"), frame_line("ERR unknown command"),
             frame_line("FAULT 3 lamp overtemperature"),
             frame_line("STATUS rate=10.00 armed=1 strobe=0 pulses=1240 fault=3"),
             frame_line("STATUS rate=12.00 armed=0 strobe=1 pulses=1 fault=0")]
    _write("strobe", "lines", b"".join(lines))
    _write("strobe", "noise", b"STATUS rate=1*00\n\xff\xfe\r\n" + lines[0][:20])


def mavlink():
    def rec(kind, body, src=None):
        head = kind if src is None else (0xC0 | kind) & 0xF8 | kind
        return bytes([head]) + (bytes(src) if src else b"") + body
    f = lambda *v: struct.pack("<" + "f" * len(v), *v)  # noqa: E731
    hb = rec(0, struct.pack("<BBBIB", 10, 3, 129, 4, 4))
    att = rec(2, struct.pack("<I", 100) + f(0.01, -0.02, 1.0, 0.0, 0.0, 0.1))
    hud = rec(3, f(1.5, 1.8) + struct.pack("<hH", 90, 30) + f(0.0, 0.0))
    ack = rec(1, struct.pack("<BBBi", 0, 0, 0, 0))
    gpi = rec(4, struct.pack("<Iiiiihhh H", 1, 0, 0, 0, 0, 150, 20, 0, 0).replace(b" ", b""))
    lpn = rec(5, struct.pack("<I", 5) + f(0, 0, 0, 1.2, 0.3, 0))
    _write("mavlink", "vehicle", b"\x01" + hb + att + hud + ack + att + hud)
    _write("mavlink", "speeds", b"\x00" + hb + att + gpi + lpn + b"\x0e" + b"\xfd\x09\x00" * 5)
    _write("mavlink", "refused", b"\x01" + hb + rec(1, struct.pack("<BBBi", 0, 2, 0, 0)))


def j1939():
    from drivers.j1939 import PGN_ADDRESS_CLAIMED, make_id
    def frame(can_id, data, flags=1):
        return struct.pack("<IBB", can_id, flags, len(data)) + data
    speed = make_id(3, 65096, 0x20)
    out = frame(speed, struct.pack("<HHBBBB", 700, 650, 100, 0xFF, 0x01, 0xFF))
    out += frame(make_id(6, PGN_ADDRESS_CLAIMED, 0x80), bytes(8))
    out += frame(make_id(6, 59904, 0x10, 0x80), bytes([0x00, 0xEE, 0x00]))
    out += frame(0x20000004, b"\0" * 8, flags=3)           # an error frame (bus-off bit)
    out += frame(speed, struct.pack("<HHBBBB", 0xFB01, 0, 0, 0xFF, 0, 0xFF))
    _write("j1939", "bus", out)
    _write("j1939", "short", frame(speed, b"\x01\x02") + frame(0x123, b"\x01", flags=0))


def runfolder():
    from tests.fuzz.fuzz_runfolder import FILES, _template
    base = _template()
    for i, f in enumerate(FILES):
        _write("runfolder", f.replace("/", "_"), bytes([i]) + base[f])


def config():
    _write("config", "shipped", (ROOT / "deploy/fieldguard.toml").read_bytes())
    _write("config", "devices", b"""[loop]\nrate_hz = 10.0\n[gate]\nrequired = ["laser"]\n
[devices.laser]\ntype = "sick-lms1xx"\nhost = "192.168.0.1"\ntimeout_s = 0.1\n
[devices.link]\ntype = "mavlink"\nconnection = "udpout:127.0.0.1:14550"\nsysid = 1\n
[devices.can]\ntype = "can-j1939"\nchannel = "can0"\npreferred_address = 128\n
[devices.strobe]\ntype = "serial"\nport = "/dev/null"\nnight_below = 30.0\n
[perception]\npipelines = ["laser"]\n[[zones.exclusion]]\nx_min_m = -3.0\nx_max_m = 0.0
y_min_m = -2.5\ny_max_m = 2.5\n""")


def annotations():
    doc = {"format": "fieldguard-rgbd-annotations", "version": 1,
           "classes": ["plant", "person"],
           "frames": {"a/000000.png": [{"class": "plant", "rect": [1, 2, 5, 4]},
                                       {"class": "person", "polygon": [[0, 0], [9, 1], [4, 8]]}]}}
    from appliance import rgbd_model
    doc["format"] = rgbd_model.ANNOTATION_FORMAT
    _write("annotations", "json", b"\x00" + json.dumps(doc).encode())
    _write("annotations", "model", b"\x01" + (ROOT / "appliance/models/greenhouse-classes.npz")
           .read_bytes())


def cue_model():
    _write("cue-model", "stubble", b"\x00" + (ROOT / "appliance/models/cue-stubble.onnx")
           .read_bytes())
    import onnx
    m = onnx.load(str(ROOT / "appliance/models/cue-stubble.onnx"))
    meta = b"\0".join(f"{p.key}={p.value}".encode() for p in m.metadata_props)
    _write("cue-model", "metadata", b"\x01" + meta)


def status():
    for w in ("status", "snapshot", "selftest", "record 2 /nonexistent/fuzz-run",
              "record-status", "record nan x", "bogus words"):
        _write("status", w.split()[0] + str(len(w)), w.encode() + b"\n")


def console():
    reqs = {"page": b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
            "status": b"GET /api/status?x=1 HTTP/1.0\r\n\r\n",
            "head": b"HEAD /api/snapshot.png HTTP/1.0\r\n\r\n",
            "grid": b"GET /api/grid.jpg HTTP/1.1\r\nConnection: keep-alive\r\n\r\n",
            "stops": b"GET /api/stops/0/grid.jpg HTTP/1.0\r\n\r\n",
            "incidents": b"GET /api/incidents HTTP/1.0\r\n\r\n",
            "download": b"GET /api/incidents/20261201-120000-obstacle-4-m.tar HTTP/1.0\r\n\r\n",
            "traversal": b"GET /api/incidents/..%2fsecret.tar HTTP/1.0\r\n\r\n",
            "post": b"POST /api/status HTTP/1.1\r\nContent-Length: 3\r\n\r\nabc",
            "http09": b"GET /\r\n\r\n",
            "http2": b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"}
    for name, data in reqs.items():
        _write("console", name, data)


if __name__ == "__main__":
    os.chdir(ROOT)
    for fn in (cola, strobe, mavlink, j1939, runfolder, config, annotations, cue_model, status,
               console):
        fn()
    print("seeds written under", CORPUS)
