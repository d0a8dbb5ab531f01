"""The link rig, shared by the link tests, tools/bench_links.py and tools/soak.py: a peer process
with JSON events on stdout (the vehicle emulators in drivers/emulators), free ports, waiting, and
the real appliance loop with a hand-driven laser and the link under test, run at 10 Hz."""
from __future__ import annotations

import gc
import json
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def wait_for(pred, timeout=5.0, step=0.02):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(step)
    return pred()


class Peer:
    """A child process speaking JSON lines on stdout and taking commands on stdin."""

    def __init__(self, argv, env=None, cwd=None):
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=env,
                                     cwd=cwd or str(ROOT))
        self.events: list[dict] = []
        self._q: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            self.events.append(ev)

    def cmd(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def find(self, **kw) -> list[dict]:
        return [e for e in list(self.events) if all(e.get(k) == v for k, v in kw.items())]

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(3)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.stderr.read() if self.proc.stderr else ""


class LoopRig:
    """ApplianceLoop(HandLaser + link) on the real clock in a background thread."""

    def __init__(self, link, hold_off_s=0.3):
        from appliance.config import Config, GateConfig, GridConfig
        from appliance.loop import ApplianceLoop
        from appliance.perception import make_pipeline
        from drivers.emulators.hand_laser import HandLaser
        cfg = Config(gate=GateConfig(hold_off_s=hold_off_s), grid=GridConfig(occupied_at=1.0))
        self.clock = link.clock
        self.laser = HandLaser("laser", self.clock)
        self.link = link
        self.loop = ApplianceLoop(cfg, self.clock, {"laser": self.laser, "link": link},
                                  [make_pipeline("laser", cfg)])
        self.outputs = []
        self.loop.on_cycle.append(lambda r: self.outputs.append(r.output))
        self.stop_evt = threading.Event()
        self.thread = threading.Thread(target=self.loop.run, args=(self.stop_evt,), daemon=True)
        self._froze = False

    _frozen = 0           # rigs running: the test process's heap is frozen while any runs

    def start(self):
        # The loop runs in a thread of the test process, whose heap is ~1.6 GB late in the
        # suite: one full garbage collection there stalls every thread for 335-397 ms (gc
        # callbacks logged through a whole suite run), three missed cycles, and a CAN status
        # gap of 403 ms was seen once. The real daemon is its own small process. So the rig
        # collects once now and freezes what the suite built (gc.freeze: left out of later
        # collections) until the last rig closes.
        if LoopRig._frozen == 0:
            gc.collect()
            gc.freeze()
        LoopRig._frozen += 1
        self._froze = True
        self.link.open()
        self.link.start_acquisition()
        self.thread.start()
        return self

    @property
    def state(self):
        return self.loop.gate.state

    def close(self):
        self.stop_evt.set()
        self.thread.join(3)
        self.loop.send_stop_everywhere("test over")
        self.link.close()
        if self._froze:
            self._froze = False
            LoopRig._frozen -= 1
            if LoopRig._frozen == 0:
                gc.unfreeze()
