#!/usr/bin/env python3
"""Experiments of the RGB-D pipeline on the simulated greenhouse (docs/rgbd.md has the results).

    python tools/experiments_rgbd.py annotate RUN --out deploy/annotations/greenhouse.json
        emulate the paper's manual annotation (section 4.1) on 12 frames of a training run:
        re-render those frames with the simulator's material map and mark rectangles that lie
        wholly inside one class (bush leaves, red pepper, brown ground, white cover); never on
        an obstacle. The rectangles are written in the documented annotation format and the
        model is trained from them by `fieldguard train-classes` like any hand-made file.
    python tools/experiments_rgbd.py tables RUN [RUN...] [--step N] [--model M] [--json F]
                                            [--rule paper|ours|both]
        the protocol of the paper's Tables 2-4 on test runs (other seeds): per colour space,
        colour alone and colour + texture, with the paper's decision (PAPER_RULE) and with ours
        (the defaults), single-frame decisions (grid occupied_at = 1, decay = 0), scored with
        appliance.evaluation.score_frame: obstacles detected at least once out of those
        present, frame-level TP (detected obstacle-frames), FN (missed ones), FP (connected
        groups of false-positive cells), recall, precision = TP / (TP + FP).
    python tools/experiments_rgbd.py variants RUN [RUN...] [--step N] [--set NAME:k=v;k=v]
        against the default (ours, RGB): each of our changes taken back in turn, the paper's
        rule, failure modes (colour/depth misalignment: depth shifted by k px) and the paper's
        future work (multi-frame voting: the grid's two-hit rule; mixture-of-Gaussians colour
        models with --mog-model).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from appliance import rgbd_model  # noqa: E402
from appliance.config import SCENE_ZONES, GridConfig, default_config  # noqa: E402
from appliance.evaluation import score_frame, zone_for_run  # noqa: E402
from appliance.fusion import GridFusion, confirmed_points  # noqa: E402
from appliance.perception import SensorInputs  # noqa: E402

FRONT_X_M = SCENE_ZONES["greenhouse"]["front_x_m"]
from appliance.perception.rgbd import PAPER_RULE, RgbdPipeline, RgbdPipelineConfig  # noqa: E402
from appliance.perception.rgbd_colour import COLOUR_SPACES  # noqa: E402
from drivers.runfolder import RunReader  # noqa: E402

CLASSES = ("bush", "pepper", "ground", "cover")


# ---------------------------------------------------------------------------------------------
# annotation (emulating a person marking blocks on 12 frames)
# ---------------------------------------------------------------------------------------------
def _pure_rects(mask: np.ndarray, size: int, n: int, rng: np.random.Generator) -> list[list[int]]:
    """Up to n non-overlapping size x size rectangles wholly inside mask."""
    integ = cv2.integral(mask.astype(np.uint8))
    s = size
    full = (integ[s:, s:] - integ[:-s, s:] - integ[s:, :-s] + integ[:-s, :-s]) == s * s
    ys, xs = np.nonzero(full)
    out: list[list[int]] = []
    taken = np.zeros(mask.shape, bool)
    for k in rng.permutation(len(ys)):
        y, x = int(ys[k]), int(xs[k])
        if taken[y:y + s, x:x + s].any():
            continue
        out.append([x, y, s, s])
        taken[max(0, y - s):y + 2 * s, max(0, x - s):x + 2 * s] = True
        if len(out) >= n:
            break
    return out


def cmd_annotate(a) -> int:
    from drivers.sim.field import SimField
    from drivers.sim.world import MAT_BUSH, MAT_GROUND, MAT_SKY
    from hal.types import GateState
    info = RunReader(a.run).info
    sim = info.extra.get("run", {}).get("sim", {})
    seed = int(sim.get("seed", a.seed))
    n_frames = len(RunReader(a.run))
    picks = [int(round(i)) for i in np.linspace(5, n_frames - 5, a.frames)]
    field = SimField("greenhouse", seed=seed, sensors=("rgbd",))
    rng = np.random.default_rng(a.seed)
    frames = {}
    for i in range(max(picks) + 1):
        if i in picks:
            views: list = []
            fr = field.render_rgbd(i * 100_000_000, i, view_out=views)
            stored = cv2.imread(str(Path(a.run) / "rgbd" / "color" / f"{i:06d}.png"))
            if stored is None or not np.array_equal(stored, fr.color):
                raise SystemExit(f"frame {i}: re-rendered colour differs from the run's; is "
                                 f"{a.run} an open-loop greenhouse run of seed {seed}?")
            mat = views[0].mat
            img = fr.color.astype(np.int32)
            red = (img[..., 2] > 1.5 * img[..., 1]) & (img[..., 2] > 1.3 * img[..., 0])
            er = lambda m, k=3: cv2.erode(m.astype(np.uint8), np.ones((k, k), np.uint8)) > 0  # noqa
            regions = []
            for cls, mask, size, n in (
                    ("bush", er(mat == MAT_BUSH) & ~cv2.dilate(red.astype(np.uint8),
                                                               np.ones((9, 9), np.uint8)).astype(bool),
                     14, 6),
                    ("pepper", er(red & (mat == MAT_BUSH)), 4, 5),
                    ("ground", er(mat == MAT_GROUND), 14, 4),
                    ("cover", er(mat == MAT_SKY), 14, 3)):
                regions += [{"class": cls, "rect": r} for r in _pure_rects(mask, size, n, rng)]
            frames[f"{Path(a.run).name}/rgbd/color/{i:06d}.png"] = regions
        field.step(0.1, GateState.CLEAR)
    doc = {"format": rgbd_model.ANNOTATION_FORMAT, "version": 1, "classes": list(CLASSES),
           "source": f"emulated manual annotation of {len(picks)} frames of {info.name} "
                     f"(tools/experiments_rgbd.py annotate)",
           "frames": frames}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=1) + "\n")
    counts = {c: sum(r["class"] == c for rs in frames.values() for r in rs) for c in CLASSES}
    print(f"wrote {a.out}: {len(frames)} frames, rectangles {counts}")
    return 0


# ---------------------------------------------------------------------------------------------
# scoring runs
# ---------------------------------------------------------------------------------------------
def _fp_groups(cells: np.ndarray, truth: list[dict], zone, cell_m: float,
               unlisted: list[dict] = ()) -> tuple[int, int]:
    """(number of 8-connected groups of false-positive cells -- the paper's 'non-obstacles that
    were detected as obstacles' --, how many of those groups lie within 0.5 m of an obstacle
    the truth file leaves out: ``unlisted``, from the simulator)."""
    from appliance.evaluation import MATCH_M, footprint_distance
    if len(cells) == 0:
        return 0, 0
    cells = np.asarray(cells, np.float64)
    inz = zone.contains(cells)
    near = np.zeros(len(cells), bool)
    for ob in truth:
        near |= footprint_distance(cells, ob) <= MATCH_M + 1e-9
    fp = cells[inz & ~near]
    if len(fp) == 0:
        return 0, 0
    ij = np.round(fp / cell_m).astype(np.int64)
    ij -= ij.min(0)
    img = np.zeros(tuple(ij.max(0) + 1), np.uint8)
    img[ij[:, 0], ij[:, 1]] = 1
    n, labels = cv2.connectedComponents(img, connectivity=8)
    if not unlisted:
        return n - 1, 0
    hit = np.zeros(len(fp), bool)
    for ob in unlisted:
        hit |= footprint_distance(fp, ob) <= MATCH_M + 1e-9
    explained = np.unique(labels[ij[hit, 0], ij[hit, 1]])
    return n - 1, int((explained > 0).sum())


class SimTruthCheck:
    """For a simulated run: step the same open-loop simulator beside the frames and list, per
    frame, the obstacles on the scene that the truth file leaves out (their footprint centre is
    out of the camera's view or beyond its depth range while part of them is in view)."""

    def __init__(self, reader):
        from drivers.sim.field import SimField
        sim = reader.info.extra.get("run", {}).get("sim", {})
        if not sim or sim.get("stop_before_collisions", False):
            raise ValueError("not an open-loop simulated run")
        sensors = tuple(sim.get("sensors", ("rgbd",)))
        self.field = SimField(sim["scene"], seed=int(sim["seed"]), sensors=sensors)
        self.i = 0

    def unlisted(self, i: int, truth: list[dict]) -> list[dict]:
        from hal.types import GateState
        while self.i < i:
            self.field.step(0.1, GateState.CLEAR)
            self.i += 1
        Rwv, O = self.field.vehicle.world_from_vehicle()
        listed = {o["id"] for o in truth}
        out = []
        for o in self.field.world.obstacles:
            if o.id in listed:
                continue
            p = Rwv.T @ (np.array([o.x, o.y, o.z0]) - O)
            if -2.0 < p[0] < 12.0:
                out.append({"id": o.id, "class": o.cls, "x_m": float(p[0]), "y_m": float(p[1]),
                            "length_m": o.length_m, "width_m": o.width_m, "yaw_deg": o.yaw_deg})
        return out


@dataclasses.dataclass
class Tally:
    frames: int = 0
    tp: int = 0
    fn: int = 0
    fp: int = 0
    fp_frames: int = 0
    fp_unlisted: int = 0
    present: set = dataclasses.field(default_factory=set)
    detected: set = dataclasses.field(default_factory=set)
    ms: list = dataclasses.field(default_factory=list)

    def row(self) -> dict:
        rec = self.tp / (self.tp + self.fn) if self.tp + self.fn else None
        prec = self.tp / (self.tp + self.fp) if self.tp + self.fp else None
        ms = np.asarray(self.ms) if self.ms else np.zeros(1)
        return {"frames": self.frames, "obstacles": len(self.present),
                "obstacles_detected": len(self.detected), "tp": self.tp, "fp": self.fp,
                "fn": self.fn, "fp_frames": self.fp_frames, "fp_unlisted": self.fp_unlisted,
                "precision_unlisted_excluded": (self.tp / (self.tp + self.fp - self.fp_unlisted)
                                                if self.tp + self.fp - self.fp_unlisted else None),
                "recall": rec, "precision": prec,
                "ms_mean": round(float(ms.mean()), 2), "ms_p99": round(float(np.percentile(ms, 99)), 2)}


def _shift(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    out = np.zeros_like(img)
    h, w = img.shape[:2]
    ys, yd = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    xs, xd = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    out[yd, xd] = img[ys, xs]
    return out


def run_variants(runs: list[str], variants: dict[str, dict], step: int, model,
                 progress: bool = True) -> dict[str, dict]:
    """Score every variant (name -> {"options": RgbdPipelineConfig kwargs, "model": m,
    "grid": GridConfig kwargs, "shift_px": k}) on every step-th frame of the runs. Fusion is
    fed every frame's points only for the grid variants that need history (occupied_at > 1)."""
    pipes = {}
    for name, v in variants.items():
        opts = RgbdPipelineConfig(**v.get("options", {}))
        pipes[name] = RgbdPipeline(opts, model=v.get("model", model))
    for p in pipes.values():
        p.colour.wait_lut()                  # same classes either way; the times need the table
    tallies = {name: Tally() for name in variants}
    for run in runs:
        reader = RunReader(run)
        zone = zone_for_run(reader.info)
        fusions = {n: GridFusion(GridConfig(**v.get("grid", {"occupied_at": 1.0, "decay": 0.0})))
                   for n, v in variants.items()}
        try:
            check = SimTruthCheck(reader)
        except (ValueError, KeyError):
            check = None
        n = len(reader)
        t_run = time.time()
        for i in range(n):
            voting = [nm for nm, v in variants.items() if v.get("grid", {}).get(
                "occupied_at", 1.0) > 1.0]
            if i % step and not voting:
                continue
            truth = reader.truth(i) if i % step == 0 else None
            unlisted = check.unlisted(i, truth) if check is not None and truth is not None else []
            fr = reader.rgbd(i)
            vehicle = reader.vehicle(i)
            stamp = reader.frames[i].stamp_ns
            for name, v in variants.items():
                if i % step and name not in voting:
                    continue
                k = v.get("shift_px", 0)
                frame = fr if not k else dataclasses.replace(fr, depth_m=_shift(fr.depth_m, k, 0))
                t0 = time.perf_counter()
                det = pipes[name].process(SensorInputs(stamp_ns=stamp, rgbd=frame,
                                                       vehicle=vehicle))
                ms = (time.perf_counter() - t0) * 1e3
                g = fusions[name].cfg
                cells = fusions[name].update(det.points_xy, vehicle, stamp,
                                             # from the sprayer's front, as the daemon's
                                             # greenhouse zones
                                             confirmed_points({"rgbd": det}, g, FRONT_X_M))
                if truth is None:
                    continue
                t = tallies[name]
                s = score_frame(cells, truth, zone)
                t.frames += 1
                t.ms.append(ms)
                for ob in s.scored_obstacles:
                    key = (reader.info.name, ob.id)
                    t.present.add(key)
                    if ob.detected:
                        t.tp += 1
                        t.detected.add(key)
                    else:
                        t.fn += 1
                g, gu = _fp_groups(cells, truth, zone, 0.1, unlisted)
                t.fp += g
                t.fp_unlisted += gu
                t.fp_frames += int(g > 0)
        if progress:
            print(f"  {run}: {n} frames, {time.time() - t_run:.0f} s", file=sys.stderr)
    return {name: t.row() for name, t in tallies.items()}


def _pct(v):
    return "-" if v is None else f"{100 * v:.1f}"


def print_table(rows: dict[str, dict], title: str) -> None:
    print(f"\n{title}\n")
    print("| variant | obstacles detected | TP | FP | FN | recall % | precision % | FP frames | "
          "FP at unlisted obstacles | precision without those % | ms mean | ms p99 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {r['obstacles_detected']}/{r['obstacles']} | {r['tp']} | {r['fp']} | "
              f"{r['fn']} | {_pct(r['recall'])} | {_pct(r['precision'])} | "
              f"{r['fp_frames']}/{r['frames']} | {r['fp_unlisted']} | "
              f"{_pct(r['precision_unlisted_excluded'])} | {r['ms_mean']} | {r['ms_p99']} |")


def _model(a):
    return rgbd_model.load(a.model)


def cmd_tables(a) -> int:
    model = _model(a)
    variants = {}
    rules = {"paper": dict(PAPER_RULE), "ours": {}}
    for rule, base in rules.items():
        if a.rule not in (rule, "both"):
            continue
        for space in COLOUR_SPACES:
            # colour alone; colour + texture (the paper runs texture after colour, ours always)
            variants[f"{rule}: {space} colour"] = {"options": {**base, "colour_space": space,
                                                               "texture": "off"}}
            variants[f"{rule}: {space} colour+texture"] = {"options": {**base,
                                                                       "colour_space": space}}
    rows = run_variants(a.runs, variants, a.step, model)
    print_table(rows, f"Tables 2-4 protocol: {', '.join(a.runs)}, every {a.step} frame(s), "
                      f"single-frame decisions")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


def _parse_set(extra: str, base: dict) -> tuple[str, dict]:
    name, _, kv = extra.partition(":")
    opts = dict(base)
    for item in kv.split(";"):
        if not item.strip():
            continue
        k, _, v = item.partition("=")
        try:
            opts[k.strip()] = json.loads(v)
        except ValueError:
            opts[k.strip()] = v
        if isinstance(opts[k.strip()], list):
            opts[k.strip()] = tuple(opts[k.strip()])
    return name, opts


def cmd_variants(a) -> int:
    model = _model(a)
    base: dict = {}                                 # the defaults: ours
    variants = {
        "default (ours)": {"options": base},
        "paper's rule (PAPER_RULE), our slope": {"options": dict(PAPER_RULE)},
        "paper-literal (PAPER_RULE, 1-row slope, no median, no occlusion filter)": {
            "options": {**PAPER_RULE, "slope_step_px": 1, "depth_median_px": 0,
                        "occlusion_filter": False}},
        "- any level surface (ground_max_height_m = 0)": {
            "options": {**base, "ground_max_height_m": 0.0}},
        "- ground class not traversable (ground_classes = [])": {
            "options": {**base, "ground_classes": ()}},
        "- texture judges every suspected px (texture_scope = suspected)": {
            "options": {**base, "texture_scope": "suspected"}},
        "- undefined texture is evidence (texture_undefined = true)": {
            "options": {**base, "texture_undefined": True}},
        "- texture after colour only (texture = after-colour)": {
            "options": {**base, "texture": "after-colour"}},
        "- texture contact 3 rows (texture_contact_px = 0)": {
            "options": {**base, "texture_contact_px": 0}},
        "- no image-bottom grounding (bottom_grounded = false)": {
            "options": {**base, "bottom_grounded": False}},
        "- no minimum height (min_height_m = 0)": {"options": {**base, "min_height_m": 0.0}},
        "- the minimum height per group only, not per object (candidate_min_height = false)": {
            "options": {**base, "candidate_min_height": False}},
        "- min height 0.10 m": {"options": {**base, "min_height_m": 0.10}},
        "- no depth holes (holes = false)": {"options": {**base, "holes": False}},
        "- contact 3 rows (contact_px = 3)": {"options": {**base, "contact_px": 3}},
        "- colour threshold 3.5 (colour_threshold = 3.5)": {
            "options": {**base, "colour_threshold": 3.5}},
        "+ opening of the candidates (open_px = 3)": {"options": {**base, "open_px": 3}},
        "- raised level surfaces anywhere, not only at the image bottom (raised_bottom_only = "
        "false)": {"options": {**base, "raised_bottom_only": False}},
        "- no raised level surfaces (raised_surfaces = false)": {
            "options": {**base, "raised_surfaces": False}},
        "colour only (texture = off)": {"options": {**base, "texture": "off"}},
        "exact colour per pixel (colour_lut_bits = 0), every pixel projected": {
            "options": {**base, "colour_lut_bits": 0, "project_stride_px": 1}},
        "misaligned depth +4 px": {"options": base, "shift_px": 4},
        "misaligned depth +8 px": {"options": base, "shift_px": 8},
        # the grid's confirm_points is on by default since the twenty-second session: each
        # row names its own, so a default flip does not change what a row measures
        "multi-frame voting (grid two-hit: occupied_at 1.4, decay 0.5; confirm_points = 0)": {
            "options": base, "grid": {"occupied_at": 1.4, "decay": 0.5, "confirm_points": 0}},
        "multi-frame voting + large candidates at once beyond 1 m of the front (confirm_points "
        "= 300, confirm_min_ahead_m = 1.0: the daemon's grid)": {
            "options": base, "grid": {"occupied_at": 1.4, "decay": 0.5, "confirm_points": 300,
                                      "confirm_min_ahead_m": 1.0}},
        "multi-frame voting, no raised level surfaces (confirm_points = 0)": {
            "options": {**base, "raised_surfaces": False},
            "grid": {"occupied_at": 1.4, "decay": 0.5, "confirm_points": 0}},
    }
    if a.mog_model:
        variants["mixture of Gaussians colour (--mog-model)"] = {
            "options": base, "model": rgbd_model.load(a.mog_model)}
    if a.only:
        variants = {k: v for k, v in variants.items() if any(o in k for o in a.only)}
    for extra in a.set or []:
        name, opts = _parse_set(extra, base)
        variants[name] = {"options": opts}
    rows = run_variants(a.runs, variants, a.step, model)
    print_table(rows, f"Variants: {', '.join(a.runs)}, every {a.step} frame(s)")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("annotate")
    p.add_argument("run")
    p.add_argument("--out", required=True)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_annotate)
    for name, fn in (("tables", cmd_tables), ("variants", cmd_variants)):
        p = sub.add_parser(name)
        p.add_argument("runs", nargs="+")
        p.add_argument("--step", type=int, default=3, help="score every N-th frame")
        p.add_argument("--model", default=None, help="class model (default: the shipped one)")
        p.add_argument("--json", default=None)
        if name == "variants":
            p.add_argument("--mog-model", default=None, help="a mixture model to compare")
            p.add_argument("--set", action="append",
                           help="extra variant NAME:key=value;key=value on the default")
            p.add_argument("--only", action="append",
                           help="run only the built-in variants whose name contains this")
        else:
            p.add_argument("--rule", default="both", choices=("paper", "ours", "both"))
        p.set_defaults(func=fn)
    a = ap.parse_args(argv)
    return a.func(a)


if __name__ == "__main__":
    raise SystemExit(main())
