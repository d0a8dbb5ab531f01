"""The stereo paper's experiments on the simulated field (docs/stereo-novelty.md).

    python tools/experiments_stereo.py runs  --out /tmp/fg-runs [--scale 0.5] [--warmup 120] [--frames 170]
    python tools/experiments_stereo.py table --runs /tmp/fg-runs [--scale 0.5] [--only day]
    python tools/experiments_stereo.py band  --runs /tmp/fg-runs
    python tools/experiments_stereo.py night-cells --runs /tmp/fg-runs [--seed 0] [--extra JSON]

``runs`` writes one run folder per scene (stubble-day, stubble-night): WARM-UP frames of the
same field with no obstacles under the same light (the vehicle drives the first metres of the
same pass; these frames have NO truth file, so they are never scored), then the obstacle
course frames with truth. The novelty model therefore has seen the field before the obstacles
appear, as the paper's vehicle had (it had been driving the field). The course frames are
bit-identical to ``fieldguard sim SCENE`` frames (same seed, same vehicle), only renumbered.

``table`` runs ``fieldguard eval RUN --pipeline P --config C --json`` for every row of the
paper's Figure 5 comparison (plus the depth-cue rows, beyond the paper) and prints a markdown
table with the command of each row. ``--seed K`` picks the runs made with ``runs --seed K``.

``night-cells`` asks why night recall is low: it runs stereo-novelty over the night run and,
for the grid cells on each obstacle in the zone, compares the novelty score under the live
model with the score under the model frozen at the end of the warm-up (which never saw an
obstacle). If both call a cell normal, the obstacle looks like the field to the descriptor
(not "learnt too fast").
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


from appliance.perception.stereo_novelty import PRE_ISSUE_14 as _P14  # noqa: E402

ROWS = [  # (label, pipeline, options); the novelty rows pinned to the stages before issue #14
    ("laser", "laser", {"min_width_m": 0.0}),      # the paper's: every return
    ("BM", "stereo", {"matcher": "bm"}),
    ("BM + novelty", "stereo-novelty", {**_P14, "matcher": "bm", "depth_cue": "off"}),
    ("BM + novelty + depth cue", "stereo-novelty", {**_P14, "matcher": "bm", "depth_cue": "bm"}),
    ("SGBM", "stereo", {"matcher": "sgbm"}),
    ("SGBM + novelty", "stereo-novelty", {**_P14, "matcher": "sgbm", "depth_cue": "off"}),
    ("SGBM + novelty + depth cue", "stereo-novelty", {**_P14, "matcher": "sgbm",
                                                      "depth_cue": "bm"}),
    ("SGBM + novelty + depth cue + #14 front end", "stereo-novelty", {"matcher": "sgbm",
                                                                      "depth_cue": "bm"}),
]
try:                                       # LIBELAS, the paper's matcher: optional (GPLv3)
    import elas  # noqa: F401  (tools/install_elas.sh)
    ROWS += [
        ("ELAS", "stereo", {"matcher": "elas"}),
        ("ELAS + novelty", "stereo-novelty", {**_P14, "matcher": "elas", "depth_cue": "off"}),
        ("ELAS + novelty + depth cue", "stereo-novelty", {**_P14, "matcher": "elas",
                                                          "depth_cue": "bm"}),
    ]
except ImportError:
    pass


def run_dir(runs: Path, scene: str, scale: float, warmup: int, seed: int = 0) -> Path:
    return runs / (f"{scene}-s{scale}-w{warmup}" + (f"-seed{seed}" if seed else ""))


def options_for(pipe: str, opts: dict) -> dict:
    """``opts`` without the keys the pipeline's config does not have."""
    from dataclasses import fields
    from appliance.perception import pipeline_class
    cls = getattr(pipeline_class(pipe), "config_class", None)
    names = {f.name for f in fields(cls)} if cls is not None else set()
    return {k: v for k, v in opts.items() if k in names}


def row_md(label: str, res: dict, cmd: str) -> str:
    pc = res.get("per_class", {})
    missed = [c for c, r in pc.items() if r["obstacles_detected"] < r["obstacles"]]
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    la = pc.get("look-alike-drum")
    la_s = "-" if not la else f"{la['detected_obstacle_frames']}/{la['obstacle_frames']}"
    return (f"| {label} | {res['obstacles_detected']}/{res['obstacles']} | "
            f"{100 * (res['recall'] or 0):.1f}% | {la_s} | "
            f"{res['false_positive_frames']}/{res['frames']} | "
            f"{fmt(res['fp_cells_per_frame'])} | {fmt(res['ms_per_frame'])} | "
            f"{', '.join(missed) or '-'} | `{cmd}` |")


HEADER = ("| pipeline | obstacles det/present | recall | look-alike drum frames | FP frames | "
          "FP cells/frame | ms/frame | classes missed | command |\n"
          "|---|---|---|---|---|---|---|---|---|")


def cmd_runs(a):
    out = Path(a.out)
    for scene in a.scenes.split(","):
        p = run_dir(out, scene, a.scale, a.warmup, a.seed)
        make_run(scene, p, a.warmup, a.frames, a.scale, a.seed)
        print(f"wrote {p}")


def cmd_table(a):
    runs = Path(a.runs)
    cfgdir = runs / "configs"
    cfgdir.mkdir(parents=True, exist_ok=True)
    extra = json.loads(a.extra) if a.extra else {}
    tag = a.tag or ("" if not extra else "-" + "-".join(f"{k}{v}" for k, v in extra.items()))
    for scene in a.scenes.split(","):
        run = run_dir(runs, scene, a.scale, a.warmup, a.seed)
        print(f"\n### {scene} (scale {a.scale}, warm-up {a.warmup} frames, seed {a.seed})"
              f"\n\n{HEADER}")
        for label, pipe, opts in ROWS:
            if a.only and not any(s in label for s in a.only.split(",")):
                continue
            if a.exclude and any(s in label for s in a.exclude.split(",")):
                continue
            o = dict(opts)
            o.update(options_for(pipe, extra))
            name = label.replace(' ', '').replace('+', '_')
            cfg = write_config(cfgdir / f"{pipe}-{name}{tag}.toml", pipe, **o)
            res, cmd = evaluate(run, pipe, cfg)
            (cfgdir / f"{scene}-seed{a.seed}-{name}{tag}.json").write_text(json.dumps(res))
            print(row_md(label + (f" ({', '.join(f'{k}={v}' for k, v in extra.items())})"
                                  if extra else ""), res, cmd), flush=True)


def cmd_band(a):
    runs = Path(a.runs)
    cfgdir = runs / "configs"
    cfgdir.mkdir(parents=True, exist_ok=True)
    print(HEADER)
    for scene in a.scenes.split(","):
        run = run_dir(runs, scene, a.scale, a.warmup, a.seed)
        for lo in (0.5, 0.7, 0.9, 1.2):
            for pipe in ("stereo", "stereo-novelty"):
                opts = {"matcher": a.matcher, "band_min_m": lo}
                if pipe == "stereo-novelty":
                    opts["depth_cue"] = "off"           # the paper's system
                cfg = write_config(cfgdir / f"band-{pipe}-{a.matcher}-{lo}.toml", pipe, **opts)
                res, cmd = evaluate(run, pipe, cfg)
                print(row_md(f"{scene} {pipe} {a.matcher} band ≥ {lo} m", res, cmd), flush=True)


def cmd_night_cells(a):
    """Novelty scores of the cells on each obstacle: live model vs the model frozen at the end
    of the warm-up; and the cells' L (lightness) mean."""
    import copy

    import numpy as np

    from appliance.perception import SensorInputs
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    from drivers.runfolder import RunReader
    run = run_dir(Path(a.runs), a.scenes.split(",")[0], a.scale, a.warmup, a.seed)
    rr = RunReader(run)
    opts = {"matcher": a.matcher, "depth_cue": "off"}
    opts.update(json.loads(a.extra) if a.extra else {})
    o = StereoNoveltyConfig(**opts)
    nov = StereoNoveltyPipeline(o, background=False)
    thr = -np.log10(o.rho)
    frozen, rows = None, []
    for i in range(len(rr)):
        st = rr.stereo(i)
        nov.process(SensorInputs(st.stamp_ns, stereo=st, vehicle=rr.vehicle(i)))
        if i == a.warmup - 1:
            frozen = copy.copy(nov.novelty.model)       # the snapshot is immutable
        truth = rr.truth(i)
        if not truth:
            continue
        res = nov.last[0]
        cam, R, t = st.calib.camera, st.calib.mount.camera_to_vehicle(), st.calib.mount.position
        kd = st.left.shape[1] // (res.mask.shape[1] * res.cell_px) or 1
        for ob in truth:
            if not 2.0 <= ob["x_m"] <= 20.0:
                continue
            cells = set()
            for f in (0.3, 0.5, 0.7):                   # along the obstacle's axis
                q = R.T @ (np.array([ob["x_m"], ob["y_m"], ob["z_m"] + f * ob["height_m"]]) - t)
                if q[2] <= 0:
                    continue
                uv = np.array([cam.fx * q[0] / q[2] + cam.cx, cam.fy * q[1] / q[2] + cam.cy, kd])
                u, v = (uv[:2] / kd) if res.affine is None else res.affine @ np.append(
                    uv[:2] / kd, 1.0)
                r, c = int(v // res.cell_px), int(u // res.cell_px)
                if 0 <= r < res.mask.shape[0] and 0 <= c < res.mask.shape[1]:
                    cells.add((r, c))
            for r, c in cells:
                x = res.descriptors[r, c][None]
                live = -np.log10(max(nov.novelty.model.density(x)[0], 1e-300))
                froz = -np.log10(max(frozen.density(x)[0], 1e-300))
                rows.append((ob["class"], live, froz, x[0, 0], bool(res.mask[r, c])))
    nov.close()
    print(f"{run.name}: novel when score > {thr:.1f} (rho {o.rho:g}); score = -log10 density\n")
    print("| class | cells | in mask | novel (live model) | novel (model frozen after warm-up) "
          "| median L | median score live / frozen |\n|---|---|---|---|---|---|---|")
    for cls in sorted({r[0] for r in rows}):
        z = np.array([r[1:] for r in rows if r[0] == cls], float)
        print(f"| {cls} | {len(z)} | {z[:, 3].mean():.2f} | {(z[:, 0] > thr).mean():.2f} | "
              f"{(z[:, 1] > thr).mean():.2f} | {np.median(z[:, 2]):.3f} | "
              f"{np.median(z[:, 0]):.1f} / {np.median(z[:, 1]):.1f} |")


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
        t.add_argument("--extra", default="", help="JSON options for the stereo pipelines "
                       "(each pipeline gets the keys its config has)")
        t.add_argument("--exclude", default="")
        t.add_argument("--tag", default="", help="suffix of the written config files")
        t.add_argument("--seed", type=int, default=0)
        t.set_defaults(func=fn)
    n = sub.add_parser("night-cells")
    n.add_argument("--runs", default="/tmp/fg-runs")
    n.add_argument("--scenes", default="stubble-night")
    n.add_argument("--scale", type=float, default=0.5)
    n.add_argument("--warmup", type=int, default=120)
    n.add_argument("--seed", type=int, default=0)
    n.add_argument("--matcher", default="sgbm")
    n.add_argument("--extra", default="")
    n.set_defaults(func=cmd_night_cells)
    a = ap.parse_args(argv)
    a.func(a)


if __name__ == "__main__":
    main()
