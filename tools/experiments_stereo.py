"""The stereo paper's experiments on the simulated field (docs/stereo-novelty.md).

    python tools/experiments_stereo.py runs  --out /tmp/fg-runs [--scale 0.5] [--warmup 120] [--frames 170]
    python tools/experiments_stereo.py table --runs /tmp/fg-runs [--scale 0.5] [--only day]
    python tools/experiments_stereo.py band  --runs /tmp/fg-runs
    python tools/experiments_stereo.py longrun --minutes 20 --out /tmp/fg-runs/long

``runs`` writes one run folder per scene (stubble-day, stubble-night): WARM-UP frames of the
same field with no obstacles under the same light (the vehicle drives the first metres of the
same pass; these frames have NO truth file, so they are never scored), then the obstacle
course frames with truth. The novelty model therefore has seen the field before the obstacles
appear, as the paper's vehicle had (it had been driving the field). The course frames are
bit-identical to ``fieldguard sim SCENE`` frames (same seed, same vehicle), only renumbered.

``table`` runs ``fieldguard eval RUN --pipeline P --config C --json`` for every row of the
paper's Figure 5 comparison and prints a markdown table with the command of each row.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FG = str(ROOT / ".venv" / "bin" / "fieldguard")


def make_run(scene: str, out: Path, warmup: int, frames: int, scale: float, seed: int = 0,
             sensors=("stereo", "laser")) -> Path:
    from drivers.runfolder import RunWriter
    from drivers.sim.field import SimField
    from drivers.sim.scenes import build_scene
    from hal.types import GateState
    from appliance.progress import Progress

    course = SimField(scene, seed=seed, sensors=sensors, stereo_scale=scale)
    warm = SimField(scene, seed=seed, sensors=sensors, stereo_scale=scale)
    warm.world = build_scene("stubble-empty", seed).world          # same field, no obstacles
    extra = {"sim": {"scene": scene, "seed": seed, "sensors": list(sensors),
                     "stereo_scale": scale, "warmup_frames": warmup, "course_frames": frames,
                     "warmup": "stubble-empty world under the scene's light, no truth",
                     "generator": "tools/experiments_stereo.py"}}
    dt = 100_000_000
    prog = Progress(f"{scene} warm-up+course", warmup + frames)
    with RunWriter(out, f"{scene}-warm{warmup}-{seed}", 10.0, stereo=course.stereo_calibration,
                   laser=course.laser_geometry, extra_run=extra, overwrite=True) as w:
        for i in range(warmup + frames):
            f = warm if i < warmup else course
            s = f.render(i * dt, i)
            w.write_frame(i, i * dt, vehicle=s.vehicle, stereo=s.stereo, laser=s.laser,
                          truth=None if i < warmup else s.truth, illumination=f.illumination)
            f.step(0.1, GateState.CLEAR)
            prog(i + 1, warmup + frames)
    return out


def write_config(path: Path, pipeline: str, **opts) -> Path:
    lines = ["[perception]", f'pipelines = ["{pipeline}"]']
    if opts:
        lines.append(f'[perception.{pipeline}]')
        for k, v in opts.items():
            lines.append(f"{k} = {json.dumps(v)}")
    path.write_text("\n".join(lines) + "\n")
    return path


def evaluate(run: Path, pipeline: str, cfg: Path | None) -> tuple[dict, str]:
    cmd = [FG, "eval", str(run), "--pipeline", pipeline, "--json"]
    if cfg is not None:
        cmd += ["--config", str(cfg)]
    t0 = time.time()
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    res = json.loads(r.stdout)
    res["wall_s"] = time.time() - t0
    shown = " ".join(c if c != FG else "fieldguard" for c in cmd if c != "--json")
    return res, shown


ROWS = [  # (label, pipeline, options)
    ("laser", "laser", {}),
    ("BM", "stereo", {"matcher": "bm"}),
    ("BM + novelty", "stereo-novelty", {"matcher": "bm"}),
    ("SGBM", "stereo", {"matcher": "sgbm"}),
    ("SGBM + novelty", "stereo-novelty", {"matcher": "sgbm"}),
]


def row_md(label: str, res: dict, cmd: str) -> str:
    pc = res.get("per_class", {})
    missed = [c for c, r in pc.items() if r["obstacles_detected"] < r["obstacles"]]
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    return (f"| {label} | {res['obstacles_detected']}/{res['obstacles']} | "
            f"{100 * (res['recall'] or 0):.1f}% | {res['false_positive_frames']}/{res['frames']} | "
            f"{fmt(res['fp_cells_per_frame'])} | {fmt(res['ms_per_frame'])} | "
            f"{', '.join(missed) or '-'} | `{cmd}` |")


HEADER = ("| pipeline | obstacles det/present | recall | FP frames | FP cells/frame | ms/frame | "
          "classes missed | command |\n|---|---|---|---|---|---|---|---|")


def cmd_runs(a):
    out = Path(a.out)
    for scene in a.scenes.split(","):
        p = out / f"{scene}-s{a.scale}-w{a.warmup}"
        make_run(scene, p, a.warmup, a.frames, a.scale, a.seed)
        print(f"wrote {p}")


def cmd_table(a):
    runs = Path(a.runs)
    cfgdir = runs / "configs"
    cfgdir.mkdir(parents=True, exist_ok=True)
    extra = json.loads(a.extra) if a.extra else {}
    for scene in a.scenes.split(","):
        run = runs / f"{scene}-s{a.scale}-w{a.warmup}"
        print(f"\n### {scene} (scale {a.scale}, warm-up {a.warmup} frames)\n\n{HEADER}")
        for label, pipe, opts in ROWS:
            if a.only and not any(s in label for s in a.only.split(",")):
                continue
            o = dict(opts)
            if pipe.startswith("stereo"):
                o.update(extra)
            cfg = write_config(cfgdir / f"{pipe}-{label.replace(' ', '').replace('+', '_')}.toml",
                               pipe, **o)
            res, cmd = evaluate(run, pipe, cfg)
            (cfgdir / f"{scene}-{label.replace(' ', '')}.json").write_text(json.dumps(res))
            print(row_md(label, res, cmd), flush=True)


def cmd_band(a):
    runs = Path(a.runs)
    cfgdir = runs / "configs"
    cfgdir.mkdir(parents=True, exist_ok=True)
    print(HEADER)
    for scene in a.scenes.split(","):
        run = runs / f"{scene}-s{a.scale}-w{a.warmup}"
        for lo in (0.5, 0.7, 0.9, 1.2):
            for pipe in ("stereo", "stereo-novelty"):
                cfg = write_config(cfgdir / f"band-{pipe}-{a.matcher}-{lo}.toml", pipe,
                                   matcher=a.matcher,
                                   band_min_m=lo)
                res, cmd = evaluate(run, pipe, cfg)
                print(row_md(f"{scene} {pipe} {a.matcher} band ≥ {lo} m", res, cmd), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("runs")
    r.add_argument("--out", default="/tmp/fg-runs")
    r.add_argument("--scenes", default="stubble-day,stubble-night")
    r.add_argument("--scale", type=float, default=0.5)
    r.add_argument("--warmup", type=int, default=120)
    r.add_argument("--frames", type=int, default=170)
    r.add_argument("--seed", type=int, default=0)
    r.set_defaults(func=cmd_runs)
    for name, fn in (("table", cmd_table), ("band", cmd_band)):
        t = sub.add_parser(name)
        t.add_argument("--runs", default="/tmp/fg-runs")
        t.add_argument("--scenes", default="stubble-day,stubble-night")
        t.add_argument("--scale", type=float, default=0.5)
        t.add_argument("--warmup", type=int, default=120)
        t.add_argument("--only", default="")
        t.add_argument("--matcher", default="sgbm")
        t.add_argument("--extra", default="", help="JSON options for the stereo pipelines")
        t.set_defaults(func=fn)
    a = ap.parse_args(argv)
    a.func(a)


if __name__ == "__main__":
    main()
