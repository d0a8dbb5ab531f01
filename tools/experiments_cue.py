#!/usr/bin/env python3
"""The learned cue's experiments (docs/learned-cue.md): data, training, tables.

    python tools/experiments_cue.py runs  [--out /tmp/cue-runs] [--fg-runs /tmp/fg-runs]
    python tools/experiments_cue.py train [--runs /tmp/cue-runs] [--out appliance/models]
    python tools/experiments_cue.py table [--runs /tmp/cue-runs] [--fg-runs /tmp/fg-runs]
                                          [--results /tmp/cue-final] [--reuse]
    python tools/experiments_cue.py real  [--results /tmp/cue-final]

``runs`` renders the training runs (stubble-day and stubble-lookalike seeds 1 and 2,
stubble-night seed 1, greenhouse seeds 0, 1, 4, 5, 6) and the test runs (greenhouse seeds 2
and 3; the stereo Figure 5 runs of seed 0 -- 120 warm-up frames of the empty field, then the
obstacle course -- for stubble-day, stubble-lookalike, stubble-night and stubble-empty (no
obstacle at all: every false-positive frame there is a false stop), made by
tools/experiments_stereo.py). No test run's seed is a training run's seed: the field, its
light and the obstacles' places differ; the kinds of obstacle are the same.

``train`` runs the two ``fieldguard train-cue`` commands that made the shipped models (the
stereo one with the top halves of the real grass and gravel photographs as negatives).

``table`` runs ``fieldguard eval RUN --pipeline P --config C --json`` with and without the cue
and prints the markdown tables of the doc (``--reuse``: read the JSON files a previous run
left in ``--results``). ``real`` scores the real photographs of tests/data/real with the
shipped stereo model (``fieldguard cue``) and prints the false-alarm rates.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
FG = str(ROOT / ".venv" / "bin" / "fieldguard")
PY = str(ROOT / ".venv" / "bin" / "python")
REAL = ROOT / "tests" / "data" / "real"

STEREO_TRAIN = [f"{sc}-{s}" for s in (1, 2) for sc in ("stubble-day", "stubble-lookalike")] + \
    ["stubble-night-1"]
RGBD_TRAIN = [f"greenhouse-{s}" for s in (0, 1, 4, 5, 6)]
RGBD_TEST = ["greenhouse-2", "greenhouse-3"]
STEREO_TEST = ["stubble-lookalike", "stubble-day", "stubble-night", "stubble-empty"]
CONFIGS = {
    "stereo-paper": '[perception]\npipelines = ["stereo-novelty"]\n'
                    '[perception.stereo-novelty]\ndepth_cue = "off"\n',
    "stereo-paper-cue": '[perception]\npipelines = ["stereo-novelty"]\n'
                        '[perception.stereo-novelty]\ndepth_cue = "off"\ncue = "required"\n',
    "stereo-default": '[perception]\npipelines = ["stereo-novelty"]\n',
    "stereo-default-cue": '[perception]\npipelines = ["stereo-novelty"]\n'
                          '[perception.stereo-novelty]\ncue = "required"\n',
    "rgbd": '[perception]\npipelines = ["rgbd"]\n',
    "rgbd-cue": '[perception]\npipelines = ["rgbd"]\n[perception.rgbd]\ncue = "required"\n',
}
LABELS = {"stereo-paper": "novelty (paper)", "stereo-paper-cue": "novelty + learned cue",
          "stereo-default": "novelty + depth cue (default)",
          "stereo-default-cue": "novelty + depth cue + learned cue",
          "rgbd": "rgbd (default)", "rgbd-cue": "rgbd + learned cue"}


def sh(*cmd) -> None:
    print("+", " ".join(cmd), file=sys.stderr)
    subprocess.run(cmd, check=True)


def cmd_runs(a) -> int:
    out = Path(a.out)
    for name in STEREO_TRAIN:
        sc, s = name.rsplit("-", 1)
        if not (out / name).exists():
            sh(FG, "sim", sc, "--frames", "150", "--seed", s, "--stereo-scale", "0.5",
               "--sensors", "stereo", "--out", str(out / name))
    for s, n in ((0, 400), (1, 400), (2, 400), (3, 400), (4, 300), (5, 300), (6, 300)):
        if not (out / f"greenhouse-{s}").exists():
            sh(FG, "sim", "greenhouse", "--frames", str(n), "--seed", str(s), "--out",
               str(out / f"greenhouse-{s}"))
    sh(PY, str(ROOT / "tools" / "experiments_stereo.py"), "runs", "--out", a.fg_runs,
       "--scenes", ",".join(STEREO_TEST), "--seed", "0")
    return 0


def _halves(tmp: Path) -> tuple[list[str], list[str]]:
    """Top halves (training negatives) and bottom halves (held out) of the real ground
    photographs."""
    tmp.mkdir(parents=True, exist_ok=True)
    top, bottom = [], []
    for n in ("grass", "gravel"):
        im = cv2.imread(str(REAL / "textures" / f"{n}.png"), cv2.IMREAD_COLOR)
        h = im.shape[0] // 2
        cv2.imwrite(str(tmp / f"{n}-top.png"), im[:h])
        cv2.imwrite(str(tmp / f"{n}-bottom.png"), im[h:])
        top.append(str(tmp / f"{n}-top.png"))
        bottom.append(str(tmp / f"{n}-bottom.png"))
    return top, bottom


def cmd_train(a) -> int:
    runs, out = Path(a.runs), Path(a.out)
    top, _ = _halves(Path(a.results) / "real")
    sh(FG, "train-cue", *[str(runs / r) for r in STEREO_TRAIN], "--negatives", *top,
       "--out", str(out / "cue-stubble.onnx"), "--every", "2", "--augment", "1")
    # the RGB-D model works on the image at 320 px with 8-px cells (the same 40x30 grid at
    # a quarter of the pixels: 3.5 ms instead of 8 ms in the pipeline, the same scores)
    sh(FG, "train-cue", *[str(runs / r) for r in RGBD_TRAIN],
       "--out", str(out / "cue-greenhouse.onnx"), "--every", "3", "--augment", "1",
       "--width", "320", "--cell-px", "8")
    return 0


def _eval(run: Path, pipeline: str, cfg: str, results: Path, reuse: bool) -> dict:
    results.mkdir(parents=True, exist_ok=True)
    res = results / f"res-{run.name}-{cfg}.json"
    if not (reuse and res.exists()):
        c = results / f"{cfg}.toml"
        c.write_text(CONFIGS[cfg])
        with open(res, "w") as fh:
            subprocess.run([FG, "eval", str(run), "--pipeline", pipeline, "--config", str(c),
                            "--json"], check=True, stdout=fh, stderr=subprocess.DEVNULL)
    return json.loads(res.read_text())


def _row(label: str, r: dict, classes: list[str]) -> str:
    pc = r["per_class"]
    cells = [f"{pc[c]['detected_obstacle_frames']}/{pc[c]['obstacle_frames']}" if c in pc
             else "-" for c in classes]
    rec = "-" if r["recall"] is None else f"{100 * r['recall']:.1f} %"
    return (f"| {label} | {r['obstacles_detected']}/{r['obstacles']} | {rec} | "
            + "".join(f"{c} | " for c in cells) + f"{r['false_positive_frames']}/{r['frames']} | "
            f"{r.get('false_positive_frames_clear', '?')} | {r['fp_cells_per_frame']:.2f} |")


def _table(title: str, rows: list[tuple[str, dict]]) -> None:
    classes = sorted({c for _, r in rows for c in r["per_class"]})
    print(f"\n### {title}\n")
    print("| pipeline | obstacles | recall | " + "".join(f"{c} | " for c in classes) +
          "FP frames | FP frames, zone clear | FP cells/frame |")
    print("|---" * (len(classes) + 6) + "|")
    for label, r in rows:
        print(_row(label, r, classes))


def cmd_table(a) -> int:
    results = Path(a.results)
    for run in RGBD_TEST:
        rows = [(LABELS[c], _eval(Path(a.runs) / run, "rgbd", c, results, a.reuse))
                for c in ("rgbd", "rgbd-cue")]
        _table(f"{run} (rgbd)", rows)
    for scene in STEREO_TEST:
        run = Path(a.fg_runs) / f"{scene}-s0.5-w120"
        rows = [(LABELS[c], _eval(run, "stereo-novelty", c, results, a.reuse))
                for c in ("stereo-paper", "stereo-paper-cue", "stereo-default",
                          "stereo-default-cue")]
        _table(f"{scene}, seed 0 (stereo-novelty, SGBM, 640 px)", rows)
    return 0


def cmd_real(a) -> int:
    results = Path(a.results)
    _, bottom = _halves(results / "real")
    imgs = bottom + [str(REAL / "middlebury_aloe" / "aloeL.jpg"),
                     str(REAL / "textures" / "brick.png")]
    out = results / "real-cue"
    sh(FG, "cue", *imgs, "--out", str(out), "--json")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("runs")
    r.add_argument("--out", default="/tmp/cue-runs")
    r.add_argument("--fg-runs", default="/tmp/fg-runs")
    r.set_defaults(func=cmd_runs)
    t = sub.add_parser("train")
    t.add_argument("--runs", default="/tmp/cue-runs")
    t.add_argument("--out", default=str(ROOT / "appliance" / "models"))
    t.add_argument("--results", default="/tmp/cue-final")
    t.set_defaults(func=cmd_train)
    b = sub.add_parser("table")
    b.add_argument("--runs", default="/tmp/cue-runs")
    b.add_argument("--fg-runs", default="/tmp/fg-runs")
    b.add_argument("--results", default="/tmp/cue-final")
    b.add_argument("--reuse", action="store_true")
    b.set_defaults(func=cmd_table)
    q = sub.add_parser("real")
    q.add_argument("--results", default="/tmp/cue-final")
    q.set_defaults(func=cmd_real)
    a = ap.parse_args(argv)
    return a.func(a)


if __name__ == "__main__":
    sys.exit(main())
