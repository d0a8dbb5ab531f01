"""Was the person standing ahead at boot learnt as field? (issue #14: "never learnt as field")

    python tools/boot_learnt.py CAMPAIGN [--json]

CAMPAIGN is a ``fieldguard campaign`` folder of ``stubble-boot`` / ``stubble-boot-night`` drives
run with ``--save-models`` (each drive keeps its novelty model as it was at the drive's end, as
the box saves it). For each drive, the drive's first frame (the vehicle at its start, the person
standing ahead) is rendered again and judged twice by the stereo-novelty pipeline:

- **never seen**: a fresh pipeline's first update made from the same view with the person taken
  out of the world, then the frame with the person: what novelty can say of them at all;
- **after the boot**: a fresh pipeline's first update (the boot check keeping what it vouches
  for out of it) and the next frame's raw novelty: what the model holds from the start;
- **at the drive's end**: a pipeline loaded with the drive's saved model.

Per drive it prints the share of the person's novelty cells (cells at least half covered by the
person in the renderer's own material mask) that are novel, and the share of the field's cells
(no pixel of the person) that are, under each model. A person whose cells are novel after the
boot and not at the end was learnt during the drive; ``tools/why_missed.py``-style replays (a
drive in-process with the model's state sampled) say when.

Needs the simulator (drivers.sim) and the campaign's saved models; prints one line per drive and
a summary. ``--json`` prints the rows as JSON instead.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

BOOT_KINDS = ("stubble-boot", "stubble-boot-night")


def _cell_shares(mask_px: np.ndarray, rows: int, cols: int, cell_px: int) -> np.ndarray:
    """Per novelty cell (``rows`` x ``cols`` cells of ``cell_px`` image pixels): the share of its
    pixels where ``mask_px`` holds."""
    h, w = rows * cell_px, cols * cell_px
    m = np.zeros((h, w), np.float32)
    src = mask_px[:h, :w]
    m[:src.shape[0], :src.shape[1]] = src
    return m.reshape(rows, cell_px, cols, cell_px).mean(axis=(1, 3))


def _novel_shares(pipe, person_px: np.ndarray) -> tuple[float, float, int]:
    """(person's cells novel, field's cells novel, person's cells) for the pipeline's last
    result (``pipe.last``), the person's pixels ``person_px`` of the camera's image."""
    res = pipe.last[0]
    raw = np.asarray(res.raw, bool)
    rows, cols = raw.shape
    kd = person_px.shape[1] // (cols * res.cell_px) or 1
    share = _cell_shares(person_px.astype(np.float32), rows, cols, res.cell_px * kd)
    person = share >= 0.5
    field = share <= 0.0
    p = float(raw[person].mean()) if person.any() else float("nan")
    return p, float(raw[field].mean()) if field.any() else float("nan"), int(person.sum())


def person_pixels(f, k: int) -> np.ndarray:
    """The pixels of obstacle ``k`` in the left camera's image of the field ``f`` as it stands
    (the renderer's own material mask)."""
    from drivers.sim.render import render_view
    from drivers.sim.world import MAT_OBSTACLE
    cal = f.stereo_calibration
    c, r, _ = f._sensor_pose(cal.mount)
    view = render_view(f.world, f.lighting, c, r, cal.camera, t_max=80.0, rel_step=0.0057)
    return view.mat == MAT_OBSTACLE + k


def judge(frames, person_px: np.ndarray, opts=None, state: dict | None = None
          ) -> tuple[tuple[float, float, int], int]:
    """A fresh stereo-novelty pipeline (options ``opts``; loaded with the saved ``state`` when
    given) run over ``frames`` (simulator samples); the last frame's
    :func:`_novel_shares` and the model's samples."""
    from appliance.perception import SensorInputs
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    o = opts or dataclasses.replace(StereoNoveltyConfig(), model_state="off")
    p = StereoNoveltyPipeline(o, background=False)
    try:
        if state is not None:
            p.novelty.import_state(state)
        for s in frames:
            p.process(SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo,
                                   vehicle=s.vehicle))
        return _novel_shares(p, person_px), int(p.novelty.model.size)
    finally:
        p.close()


def judge_drive(kind: str, seed: int, model_file: Path, stereo_scale: float = 0.5) -> dict:
    """The row for one drive (see the module's docstring)."""
    from appliance import novelty_store
    from drivers.sim import SimField

    f = SimField(kind, seed, sensors=("stereo",), stereo_scale=stereo_scale)
    boot = [i for i, o in enumerate(f.world.obstacles) if o.placement == "at-boot"]
    if not boot:
        raise SystemExit(f"{kind} {seed}: no obstacle placed at boot (not a stubble-boot scene)")
    k = boot[0]
    ob = f.world.obstacles[k]
    s0 = f.render(0, 0)
    s1 = f.render(100_000_000, 1)           # the vehicle stands at the start: the same view
    person_px = person_pixels(f, k)
    (boot_p, boot_f, cells), _ = judge([s0, s1], person_px)
    # a model that never saw them: the first update from the same view with the person taken
    # out of the world, judging the frame with the person (what novelty can say of them at all)
    g = SimField(kind, seed, sensors=("stereo",), stereo_scale=stereo_scale)
    g.set_obstacles([o for i, o in enumerate(g.world.obstacles) if i != k], on_ground=False)
    (never_p, _, _), _ = judge([g.render(0, 0), s1], person_px)
    state = novelty_store.read(model_file, then="drive skipped")
    if state is None:
        raise SystemExit(f"{model_file}: no readable novelty model")
    (end_p, end_f, _), samples = judge([s0], person_px, state=state)
    return {"drive": f"{kind}-{seed}", "cls": ob.cls, "tone": getattr(ob, "tone", ""),
            "person_cells": cells, "never_saw_person_novel": never_p,
            "boot_person_novel": boot_p, "boot_field_novel": boot_f,
            "end_person_novel": end_p, "end_field_novel": end_f,
            "end_updates": int(state.get("updates", 0)), "end_samples": samples}


def drives(campaign: Path) -> list[tuple[str, int, Path]]:
    """(kind, seed, saved model file) of the campaign's boot drives that kept their model."""
    from appliance.campaign import MODEL_DIR, MODEL_FILE
    out = []
    for d in sorted((campaign / "drives").glob("*")):
        kind, _, seed = d.name.rpartition("-")
        if kind not in BOOT_KINDS or not seed.isdigit():
            continue
        m = d / MODEL_DIR / MODEL_FILE
        if m.is_file():
            out.append((kind, int(seed), m))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("campaign", type=Path)
    ap.add_argument("--stereo-scale", type=float, default=0.5)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if not (a.campaign / "drives").is_dir():
        print(f"boot_learnt: {a.campaign}: not a campaign folder (no drives/ in it)",
              file=sys.stderr)
        return 2
    todo = drives(a.campaign)
    if not todo:
        print(f"boot_learnt: {a.campaign}: no stubble-boot drive with a saved model (run the "
              "campaign with --save-models)", file=sys.stderr)
        return 2
    rows = []
    for kind, seed, m in todo:
        row = judge_drive(kind, seed, m, a.stereo_scale)
        rows.append(row)
        if not a.json:
            print(f"{row['drive']:<24s} {row['cls']:<7s} {row['tone']:<15s} "
                  f"{row['person_cells']:3d} cells | never seen: "
                  f"{100 * row['never_saw_person_novel']:5.1f} % | after the boot: person "
                  f"{100 * row['boot_person_novel']:5.1f} % novel, field "
                  f"{100 * row['boot_field_novel']:4.1f} % | at the drive's end "
                  f"({row['end_updates']} updates): person {100 * row['end_person_novel']:5.1f} "
                  f"% novel, field {100 * row['end_field_novel']:4.1f} %", flush=True)
    if a.json:
        print(json.dumps(rows, indent=1))
        return 0
    novel_never = [r for r in rows if r["never_saw_person_novel"] >= 0.5]
    novel_boot = [r for r in rows if r["boot_person_novel"] >= 0.5]
    kept = [r for r in novel_boot if r["end_person_novel"] >= 0.5]
    print(f"{len(rows)} drives; the person novel (half its cells or more) to a model that "
          f"never saw them in {len(novel_never)}, after the boot in "
          f"{len(novel_boot)}, of which still novel at the drive's end in {len(kept)}; "
          f"mean share of its cells novel: never seen "
          f"{100 * np.nanmean([r['never_saw_person_novel'] for r in rows]):.1f} %, after the boot "
          f"{100 * np.nanmean([r['boot_person_novel'] for r in rows]):.1f} %, at the end "
          f"{100 * np.nanmean([r['end_person_novel'] for r in rows]):.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
