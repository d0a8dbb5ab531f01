"""Thread CPU time per stage of the stereo-novelty pipeline over a run folder, with and
without one option (docs/front-end.md "The local ground": the cost of ``ground_local``).

    taskset -c 1 python tools/bench_front_stages.py RUN [--set key=value ...] [--passes 2]

Each pass runs the pipeline twice over every frame of RUN (the options as given, then with
``--set`` applied; the novelty model is not persisted), timing ``process`` in this thread's
CPU time (time.thread_time) and reading each stage's ``cpu_ms`` from its debug record. Prints
per configuration the whole frame's p50/p99 and each stage's median, over frames 5 and
later (the first frames learn the model). The load average is printed before and after.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def _value(v: str):
    low = v.lower()
    if low in ("true", "false"):
        return low == "true"
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--passes", type=int, default=2)
    a = ap.parse_args(argv)
    from appliance.config import parse_config
    from appliance.evaluation import RunReader, _sync_model_updates
    from appliance.perception import SensorInputs, make_pipeline
    extra = dict((k, _value(v)) for k, v in (s.split("=", 1) for s in a.set))
    rd = RunReader(a.run)
    print("load average before:", " ".join(f"{x:.2f}" for x in os.getloadavg()))
    for _ in range(a.passes):
        for label, opts in (("as configured", {}), ("with " + " ".join(a.set), extra)):
            cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"], "stereo-novelty":
                                               {"model_state": "off", **opts}}})
            pipe = make_pipeline("stereo-novelty", cfg)
            whole, stages = [], {}
            try:
                for i in range(len(rd)):
                    fr = rd.frames[i]
                    t0 = time.thread_time()
                    det = pipe.process(SensorInputs(stamp_ns=fr.stamp_ns, vehicle=rd.vehicle(i),
                                                    stereo=rd.stereo(i)))
                    whole.append(1e3 * (time.thread_time() - t0))
                    _sync_model_updates([pipe])
                    for k, v in det.debug["cpu_ms"].items():
                        stages.setdefault(k, []).append(v)
            finally:
                pipe.close()
            w = whole[5:]
            print(f"{label}: whole CPU p50 {np.percentile(w, 50):.1f} ms, p99 "
                  f"{np.percentile(w, 99):.1f} ms; stage medians (ms): " +
                  ", ".join(f"{k} {np.median(v[5:]):.2f}" for k, v in stages.items()))
    print("load average after:", " ".join(f"{x:.2f}" for x in os.getloadavg()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
