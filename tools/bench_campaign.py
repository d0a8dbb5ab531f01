"""Campaign throughput and its scaling from 1 to 2 workers.

    python tools/bench_campaign.py [--scene stubble-coverage] [--seeds 0-1] [--minutes 0.5]
        [--stereo-scale 0.5] [--config extra.toml] [--out /tmp/bench-campaign] [--json]

Runs the same campaign twice into fresh folders: ``--workers 1`` (no Ray, the drives one after
the other) and ``--workers 2`` (local Ray, two drives at once), and prints:

- ``sim_h_per_cpu_h_1`` / ``_2``: simulated hours per CPU hour (the drives' own process CPU
  time, summed): what a core buys, nearly independent of other users of the machine;
- ``wall_s_1`` / ``wall_s_2`` and ``scaling_1_to_2`` = wall_1 / wall_2 (2.0 is perfect; Ray's
  start-up is inside wall_2); wall time IS disturbed by other load, so the load average over
  each run is printed beside it;
- ``same_results``: the two summaries are equal (all but engine, workers, timing, provenance).

Training seeds (< 1000) by default: a benchmark is not an acceptance run.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from appliance.campaign import COMPARE_EXCLUDE, Campaign, _commit  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="stubble-coverage")
    ap.add_argument("--seeds", default="0-1")
    ap.add_argument("--minutes", type=float, default=0.5)
    ap.add_argument("--stereo-scale", type=float, default=0.5)
    ap.add_argument("--config")
    ap.add_argument("--out", default="/tmp/bench-campaign")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    out = Path(a.out)
    res = {"command": "python tools/bench_campaign.py " + " ".join(sys.argv[1:] if argv is None
                                                                   else argv),
           "commit": _commit(), "cpu_count": os.cpu_count(), "scene": a.scene,
           "seeds": a.seeds, "minutes": a.minutes, "stereo_scale": a.stereo_scale}
    sums = {}
    for w in (1, 2):
        d = out / f"workers-{w}"
        shutil.rmtree(d, ignore_errors=True)
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        s = Campaign(a.scene, a.seeds, a.minutes, d, workers=w, config_file=a.config,
                     stereo_scale=a.stereo_scale, progress=not a.json, report=False).run()
        wall = time.perf_counter() - t0
        t = s["timing"]
        res[f"wall_s_{w}"] = round(wall, 1)
        res[f"drives_cpu_s_{w}"] = t["drives_cpu_s"]
        res[f"sim_h_per_cpu_h_{w}"] = t["simulated_hours_per_cpu_hour"]
        res[f"sim_h_per_wall_h_{w}"] = round(s["simulated_hours"] / (wall / 3600.0), 3)
        res[f"loadavg_1min_{w}"] = [round(load0[0], 2), round(os.getloadavg()[0], 2)]
        sums[w] = {k: v for k, v in s.items() if k not in COMPARE_EXCLUDE}
        res["simulated_hours"] = s["simulated_hours"]
    res["scaling_1_to_2"] = round(res["wall_s_1"] / res["wall_s_2"], 3)
    res["same_results"] = sums[1] == sums[2]
    if a.json:
        print(json.dumps(res, indent=2))
    else:
        for k, v in res.items():
            print(f"{k:24s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
