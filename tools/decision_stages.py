"""What each stage of the decision is worth: score run folders under [tracking] settings,
running the perception once per (run, pipeline) and the decision core many times.

    python tools/decision_stages.py RUN[,RUN...] PIPELINE[+PIPELINE...] \
        '{"confirm_logodds": [1.5, 2.0]}' [--base '{"input": "occupied"}'] [--cells] \
        [--cache DIR] [--indices]

Each pipeline's detections are recorded per frame the first time (``--cache``, default
/tmp/fieldguard-decision-cache) by running ``fieldguard eval``'s own runner with the pipeline;
then every setting (the cross product of the JSON lists, keys under ``[tracking]``, ``a.b`` for
``weights.x``) replays those detections through ``appliance.evaluation.evaluate_run``, i.e.
the same decision core (grid, tracks, zones, gate) and scoring as ``fieldguard eval``. The
perception pipelines are deterministic given the frames, so a replayed figure equals what
``fieldguard eval RUN --config FILE`` prints for that setting. ``--cells`` adds the cell-based
decision (``enabled = false``) as the first row.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import pickle
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

import appliance.perception as perception  # noqa: E402
from appliance.config import parse_config  # noqa: E402
from appliance.evaluation import evaluate_run  # noqa: E402
from appliance.perception.base import Detections, Pipeline  # noqa: E402

_DEBUG_KEYS = ("groups_raised", "groups_holes", "groups_colour", "groups_texture",
               "groups_learned", "cue_cells")


def recorded(run: str, name: str, cache: Path) -> dict:
    """{stamp_ns: Detections} of pipeline ``name`` over ``run`` (computed once, then cached)."""
    p = cache / f"{Path(run).name}--{name}.pkl"
    if p.exists():
        with open(p, "rb") as f:
            return pickle.load(f)
    store = {}
    real = perception.make_pipeline

    class Recorder(Pipeline):
        def __init__(self, inner):
            super().__init__(None)
            self.inner, self.name, self.requires = inner, inner.name, inner.requires

        def process(self, inputs):
            d = self.inner.process(inputs)
            store[inputs.stamp_ns] = Detections(
                points_xy=np.asarray(d.points_xy),
                debug={k: v for k, v in d.debug.items() if k in _DEBUG_KEYS},
                candidates=d.candidates)
            return d

        def close(self):
            self.inner.close()

    perception.make_pipeline = lambda n, cfg=None: Recorder(real(n, cfg))
    try:
        evaluate_run(run, name)
    finally:
        perception.make_pipeline = real
    cache.mkdir(parents=True, exist_ok=True)
    with open(p, "wb") as f:
        pickle.dump(store, f)
    return store


class Replay(Pipeline):
    def __init__(self, name, store, requires):
        super().__init__(None)
        self.name, self.store, self.requires = name, store, requires

    def process(self, inputs):
        return self.store.get(inputs.stamp_ns, Detections())


def replay(run: str, names: list[str], cfg, cache: Path) -> dict:
    from appliance.perception.fused import FusedPipeline
    real = perception.make_pipeline
    parts = [Replay(n, recorded(run, n, cache), real(n).requires) for n in names]
    pipe = parts[0] if len(parts) == 1 else FusedPipeline(parts)
    perception.make_pipeline = lambda n, c=None: pipe
    try:
        return evaluate_run(run, "+".join(names), cfg)
    finally:
        perception.make_pipeline = real


def _set(d: dict, key: str, value) -> None:
    parts = key.split(".")
    for p in parts[:-1]:
        d = d.setdefault(p, {})
    d[parts[-1]] = value


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs")
    ap.add_argument("pipelines")
    ap.add_argument("grid", help='JSON {"tracking key": [values]}')
    ap.add_argument("--base", default="{}", help="JSON [tracking] keys for every row")
    ap.add_argument("--grid-keys", default="{}",
                    help='JSON [grid] keys for every row, e.g. {"stop_at": 1.7}')
    ap.add_argument("--cells", action="store_true", help="add the cell decision first")
    ap.add_argument("--cache", default="/tmp/fieldguard-decision-cache")
    ap.add_argument("--indices", action="store_true",
                    help="add each run's false-stop and missed-stop frame indices")
    a = ap.parse_args(argv)
    runs, names = a.runs.split(","), a.pipelines.split("+")
    grid, base = json.loads(a.grid), json.loads(a.base)
    keys = list(grid)
    combos = ([None] if a.cells else []) + list(itertools.product(*[grid[k] for k in keys]))
    f3 = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    for combo in combos:
        tr = json.loads(json.dumps(base))
        tr["enabled"] = combo is not None
        for k, v in zip(keys, combo or ()):
            _set(tr, k, v)
        cfg = parse_config({"tracking": tr, "grid": json.loads(a.grid_keys)},
                           "<decision_stages>")
        t0 = time.process_time()
        row = []
        for run in runs:
            r = replay(run, names, cfg, Path(a.cache))
            row.append(f"{Path(run).name}: recall {f3(r['recall'])} path {f3(r['path_recall'])} "
                       f"fp-frames {r['false_positive_frames']}/{r['frames']} "
                       f"fp-cells {r['fp_cells_per_frame']:.1f} false-stop "
                       f"{r['false_stop_frames']} missed-stop {r['missed_stop_frames']}"
                       + (f" (stop-zone {r['stop_zone_frames']}; false-stop at "
                          f"{r['false_stop_frame_indices']}, missed at "
                          f"{r['missed_stop_frame_indices']})" if a.indices else ""))
        label = "cells" if combo is None else json.dumps(dict(zip(keys, combo)))
        print(f"{label} | " + " | ".join(row) + f"  ({time.process_time() - t0:.0f} s CPU)",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
