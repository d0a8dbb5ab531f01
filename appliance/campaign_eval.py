"""``fieldguard eval RUN1 RUN2 ... [--workers N] [--address ADDR]``: score many run folders (a
fleet's recordings) with :func:`appliance.evaluation.evaluate_run`, in parallel on Ray (one task
per run; local Ray with N CPUs, or an existing cluster with ``--address``), and print one table
(or JSON with ``--json``). ``--workers 1`` scores them one after the other without Ray; the
figures are the same either way."""
from __future__ import annotations

import json
import os
import sys

from hal.errors import FieldguardError


def _score(run: str, pipeline, config_path):
    """One run, in this process or a Ray worker: (result, None) or (None, error text)."""
    from appliance.evaluation import evaluate_run
    try:
        return evaluate_run(run, pipeline, config_path), None
    except FieldguardError as exc:
        return None, str(exc)
    except Exception as exc:                # a broken run folder: name it, score the others
        return None, f"{type(exc).__name__}: {exc}"


def eval_many(runs: list[str], pipeline=None, config_path=None, workers: int | None = None,
              address: str | None = None, progress=None) -> list[tuple[str, dict | None,
                                                                        str | None]]:
    """[(run, result or None, error or None)] in the order of ``runs``."""
    workers = workers if workers is not None else (os.cpu_count() or 1)
    if workers < 1:
        raise FieldguardError(f"--workers {workers}: give 1 or more (1 runs without Ray)")
    missing = [r for r in runs if not os.path.isdir(r)]
    if missing:
        raise FieldguardError(f"no such run folder: {', '.join(missing)}")
    if workers == 1 and not address:
        out = []
        for i, r in enumerate(runs):
            out.append((r, *_score(r, pipeline, config_path)))
            if progress:
                progress(i + 1, len(runs))
        return out
    try:
        import ray
    except ImportError:
        raise FieldguardError(f"--workers {workers} needs Ray, which is not installed: pip "
                              "install 'fieldguard[campaign]' (or pip install ray), or run "
                              "with --workers 1") from None
    from appliance.campaign import init_ray
    started = not ray.is_initialized()
    if started:
        init_ray(workers, address, object_store_mb=100)
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_score)
        refs = [task.remote(os.path.abspath(r), pipeline,
                            None if config_path is None else os.path.abspath(config_path))
                for r in runs]
        left, n = list(refs), 0
        while left:
            ready, left = ray.wait(left, num_returns=1)
            n += len(ready)
            if progress:
                progress(n, len(runs))
        return [(r, *ray.get(ref)) for r, ref in zip(runs, refs)]
    finally:
        if started:
            ray.shutdown()


def _pct(v):
    return "-" if v is None else f"{100 * v:.1f}%"


def _num(v, fmt="{:.2f}"):
    return "-" if v is None else (fmt.format(v) if isinstance(v, float) else str(v))


def totals(results: list[dict]) -> dict:
    """Frames, obstacle frames and false positives summed over the scored runs."""
    ok = [r for r in results if r is not None]
    sumk = lambda k: sum(int(r.get(k) or 0) for r in ok)  # noqa: E731
    of, det = sumk("obstacle_frames"), sumk("detected_obstacle_frames")
    out = {"runs": len(ok), "frames": sumk("frames"), "obstacle_frames": of,
           "detected_obstacle_frames": det, "recall": None if not of else det / of,
           "obstacles": sumk("obstacles"), "obstacles_detected": sumk("obstacles_detected"),
           "false_positive_frames": sumk("false_positive_frames"),
           "fp_cells": sumk("fp_cells")}
    out["fp_cells_per_frame"] = None if not out["frames"] else out["fp_cells"] / out["frames"]
    for k in ("false_stop_frames", "missed_stop_frames"):
        if any(k in r for r in ok):
            out[k] = sumk(k)
    return out


def format_many(rows: list[tuple[str, dict | None, str | None]]) -> str:
    results = [r for _, r, _ in rows]
    extra = [k for k in ("false_stop_frames", "missed_stop_frames")
             if any(r is not None and k in r for r in results)]
    cols = ["run", "pipeline", "frames", "recall", "obstacles det/all", "FP frames",
            "FP cells/frame", *[k.replace("_", " ") for k in extra], "ms/frame"]
    table = []
    for run, r, err in rows:
        if r is None:
            table.append([os.path.basename(os.path.normpath(run)), "error: " + (err or "?")])
            continue
        table.append([r.get("run", run), str(r.get("pipeline")), str(r["frames"]),
                      _pct(r["recall"]), f"{r['obstacles_detected']}/{r['obstacles']}",
                      str(r["false_positive_frames"]), _num(r["fp_cells_per_frame"]),
                      *[str(r.get(k, "-")) for k in extra], _num(r.get("ms_per_frame"))])
    t = totals(results)
    table.append(["all", "", str(t["frames"]), _pct(t["recall"]),
                  f"{t['obstacles_detected']}/{t['obstacles']}", str(t["false_positive_frames"]),
                  _num(t["fp_cells_per_frame"]), *[str(t.get(k, "-")) for k in extra], ""])
    full = [r for r in table if len(r) == len(cols)]
    widths = [max(len(c), *(len(r[i]) for r in full)) for i, c in enumerate(cols)]

    def line(r):
        if len(r) != len(cols):
            return "  ".join([r[0].ljust(widths[0]), *r[1:]])
        return "  ".join(s.ljust(w) if i < 2 else s.rjust(w)
                         for i, (s, w) in enumerate(zip(r, widths)))
    sep = "  ".join("-" * w for w in widths)
    return "\n".join([line(cols), sep, *map(line, table[:-1]), sep, line(table[-1])])


def cmd_eval_many(a) -> int:
    from appliance.progress import Progress
    if getattr(a, "out", None):
        raise FieldguardError("--out writes one run's decisions: give one RUN with --out")
    rows = eval_many(a.run, a.pipeline, a.config, workers=a.workers,
                     address=getattr(a, "address", None),
                     progress=Progress(f"eval {len(a.run)} runs", len(a.run)))
    errors = [(r, e) for r, res, e in rows if res is None]
    if a.json:
        print(json.dumps({"runs": [{"run": r, "result": res, "error": e} for r, res, e in rows],
                          "all": totals([res for _, res, _ in rows])}, indent=2, default=float))
    else:
        print(format_many(rows))
    if errors:
        print(f"fieldguard: error: {len(errors)} of {len(rows)} runs could not be scored: "
              + "; ".join(f"{r}: {e}" for r, e in errors), file=sys.stderr)
        return 2
    return 0
