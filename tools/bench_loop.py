#!/usr/bin/env python3
"""Benchmark the daemon's loop on the simulated field: per-stage wall times and the whole
cycle's p50/p99, from a lock-step sim run (rendering is outside the loop's stages: it is the
simulated sensors' own time, reported apart).

    .venv/bin/python tools/bench_loop.py [--scene stubble-day] [--cycles 600] [--config F]

Prints a table; numbers are wall-clock milliseconds on this machine.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from appliance.config import default_config, load_config  # noqa: E402
from appliance.daemon import Daemon, sim_config  # noqa: E402
from appliance.loop import STAGES  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="stubble-day")
    ap.add_argument("--cycles", type=int, default=600)
    ap.add_argument("--config")
    a = ap.parse_args()
    cfg = sim_config(load_config(a.config) if a.config else default_config(), a.scene)
    d = Daemon(cfg, mode="sim", pace=0.0, serve_status=False)
    d.start()
    stages = {s: [] for s in STAGES}
    cycle = []
    render = []              # per cycle: the sim's rendering done within that cycle (ms)
    pending = [0.0]          # rendering since the last cycle ended

    # time the sim rendering apart. The lock-step clock renders the next sample while the loop
    # sleeps (appliance/daemon.py, RenderAheadClock.sleep_until), so it is in none of the loop's
    # stages; the devices' service() calls find it made. (This tool used to subtract the
    # renders from the acquire stage, which printed negative times.)
    hub_at = None

    def on_cycle(res):
        for s in STAGES:
            stages[s].append(res.wall_ms[s])
        cycle.append(sum(res.wall_ms.values()))
        render.append(pending[0])
        pending[0] = 0.0

    d.loop.on_cycle.append(on_cycle)
    hub = d.shared.get("sim_hub")
    if hub is not None:
        hub_at = hub.at

        def timed_at(now_ns):
            t0 = time.perf_counter()
            fresh = hub._last_ns != now_ns
            out = hub_at(now_ns)
            if fresh:
                pending[0] += (time.perf_counter() - t0) * 1e3
            return out
        hub.at = timed_at
    pending[0] = 0.0                        # renders of start-up belong to no cycle
    t0 = time.perf_counter()
    try:
        d.run(max_cycles=a.cycles)
    finally:
        d.shutdown()
    wall = time.perf_counter() - t0

    def row(name, xs):
        x = np.asarray(xs)
        return (f"{name:22s} {np.percentile(x, 50):9.2f} {np.percentile(x, 99):9.2f} "
                f"{x.max():9.2f}")
    rend = np.asarray(render) if hub_at is not None else np.zeros(len(cycle))
    print(f"fieldguard loop benchmark: scene {a.scene}, {a.cycles} cycles, pipelines "
          f"{', '.join(cfg.perception.pipelines)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cpus, python {platform.python_version()}")
    print(f"{'stage':22s} {'p50 ms':>9s} {'p99 ms':>9s} {'max ms':>9s}")
    for s in STAGES:
        print(row(s, stages[s]))
    print(row("cycle", cycle))
    if (rend > 0).any():
        print(row("sim rendering (apart)", rend[rend > 0]))
    st = d.status()
    print(f"overruns {st['overruns']}, skipped {st['skipped']}, wall {wall:.1f} s for "
          f"{a.cycles / 10:.0f} s of loop time")
    return 0


if __name__ == "__main__":
    sys.exit(main())
