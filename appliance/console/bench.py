"""What the web console costs the loop: ``python -m appliance.console.bench``.

Replays one run folder (a simulated stubble-day run with the stereo camera and the laser, made
once) through the daemon at real time, in alternating blocks with the console off and on; while
on, a client polls it as the page does (status once a second, both pictures twice a second).
Reported per condition: the loop's own cycle time (wall, what status shows), and the loop
thread's CPU time per full iteration including the on_cycle callbacks (where the tap's
hand-over runs). Run it under ``taskset -c 1`` so the encoder and the HTTP threads compete with
the loop for one core (the worst case, and much less disturbed by other load than wall time).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np


def _run_folder(path: Path, frames: int) -> Path:
    if not (path / "done").exists():
        from drivers.sim.record import write_sim_run
        write_sim_run("stubble-day", frames, path, sensors=("stereo", "laser"), stereo_scale=0.5,
                      overwrite=True)
        (path / "done").write_text("")
    return path


def _poller(url: str, stop: threading.Event, counts: dict) -> None:
    t_next = {"api/status": 0.0, "api/view.jpg": 0.0, "api/grid.jpg": 0.0}
    period = {"api/status": 1.0, "api/view.jpg": 0.5, "api/grid.jpg": 0.5}
    while not stop.is_set():
        now = time.monotonic()
        for p, t in t_next.items():
            if now >= t:
                try:
                    with urllib.request.urlopen(url + p, timeout=5) as r:
                        r.read()
                    counts[p] = counts.get(p, 0) + 1
                except OSError:
                    counts["errors"] = counts.get("errors", 0) + 1
                t_next[p] = now + period[p]
        stop.wait(0.05)


def block(run: Path, console: bool, seconds: float, sock: str) -> dict:
    from appliance.config import ConsoleConfig, default_config
    from appliance.daemon import Daemon, replay_config
    cfg = dataclasses.replace(default_config(),
                              console=ConsoleConfig(listen="127.0.0.1:0" if console else ""))
    cfg = replay_config(cfg, str(run))
    cfg = dataclasses.replace(cfg, devices=tuple(          # the run again and again
        dataclasses.replace(dv, options={**dv.options, "loop": True}) if dv.type == "replay"
        else dv for dv in cfg.devices))
    d = Daemon(cfg, mode="replay", replay_path=str(run), pace=1.0, status_socket=sock)
    d.start()
    cpu, marks = [], []

    def last_callback(res):                     # registered last: after every other callback
        marks.append(time.thread_time())

    d.loop.on_cycle.append(last_callback)
    stop = threading.Event()
    counts: dict = {}
    poll = None
    if console:
        poll = threading.Thread(target=_poller, args=(d.console.console.url, stop, counts),
                                daemon=True)
        poll.start()
    try:
        d.run(max_cycles=int(seconds * cfg.loop.rate_hz))
        wall = list(d.loop.timing["cycle"].samples)
        info = d.status().get("console", {}).get("console")
    finally:
        stop.set()
        if poll is not None:
            poll.join(5)
        d.shutdown()
    cpu = np.diff(marks) * 1e3
    wall = np.array(wall[1:])
    q = lambda a, p: round(float(np.percentile(a, p)), 3)  # noqa: E731
    return {"console": console, "cycles": len(marks),
            "cycle_wall_ms": {"p50": q(wall, 50), "p99": q(wall, 99)},
            "iteration_cpu_ms": {"p50": q(cpu, 50), "p99": q(cpu, 99)},
            "requests": counts, "console_info": info}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", default=None, help="run folder (default: a simulated one in /tmp)")
    ap.add_argument("--frames", type=int, default=40, help="of the simulated run (it loops)")
    ap.add_argument("--seconds", type=float, default=25.0, help="per block")
    ap.add_argument("--blocks", type=int, default=2, help="off/on pairs")
    a = ap.parse_args(argv)
    run = Path(a.run) if a.run else _run_folder(
        Path(f"/tmp/fieldguard-bench-console-run-{a.frames}"), a.frames)
    sock = f"/tmp/fieldguard-bench-console-{time.time_ns()}.sock"
    out = []
    for _ in range(a.blocks):
        for on in (False, True):
            r = block(run, on, a.seconds, sock)
            out.append(r)
            print(json.dumps(r), flush=True)
    for on in (False, True):
        rs = [r for r in out if r["console"] is on]
        print(f"console {'on ' if on else 'off'}: loop cycle wall p50 "
              f"{np.median([r['cycle_wall_ms']['p50'] for r in rs]):.2f} ms, p99 "
              f"{np.median([r['cycle_wall_ms']['p99'] for r in rs]):.2f} ms; loop thread CPU "
              f"per iteration p50 {np.median([r['iteration_cpu_ms']['p50'] for r in rs]):.2f} "
              f"ms, p99 {np.median([r['iteration_cpu_ms']['p99'] for r in rs]):.2f} ms "
              f"({sum(r['cycles'] for r in rs)} cycles)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
