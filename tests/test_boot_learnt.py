"""tools/boot_learnt.py: was the person standing ahead at boot learnt as field? (issue #14)

A saved model that learnt the first frame whole (the paper's start: no boot check) must be
told apart from one whose first update the boot check guarded."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import boot_learnt  # noqa: E402


def _saved_model(folder: Path, kind: str, seed: int, boot_guard: bool) -> Path:
    """A campaign folder holding, for ``kind``-``seed``, the model of a pipeline that saw the
    drive's first frame (the person ahead) and made its first update from it."""
    from appliance import novelty_store
    from appliance.campaign import MODEL_DIR, MODEL_FILE
    from appliance.perception import SensorInputs
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    from drivers.sim import SimField
    f = SimField(kind, seed, sensors=("stereo",), stereo_scale=0.5)
    s = f.render(0, 0)
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", boot_guard=boot_guard)
    p = StereoNoveltyPipeline(o, background=False)
    try:
        p.process(SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo, vehicle=s.vehicle))
        d = folder / "drives" / f"{kind}-{seed}" / MODEL_DIR
        d.mkdir(parents=True)
        novelty_store.save(d / MODEL_FILE, p.novelty.export_state())
        return d / MODEL_FILE
    finally:
        p.close()


def test_a_model_that_learnt_the_person_is_told_from_one_that_did_not(tmp_path, capsys):
    # training seed 3: a small child in "other" clothes 4.1 m ahead of the front
    guarded = _saved_model(tmp_path / "guarded", "stubble-boot", 3, boot_guard=True)
    whole = _saved_model(tmp_path / "whole", "stubble-boot", 3, boot_guard=False)
    g = boot_learnt.judge_drive("stubble-boot", 3, guarded)
    w = boot_learnt.judge_drive("stubble-boot", 3, whole)
    assert g["cls"] == "child" and g["person_cells"] >= 5
    # after the boot (the box's own start, the boot check on) the child is novel...
    assert g["boot_person_novel"] >= 0.9 and g["boot_field_novel"] <= 0.02
    assert w["boot_person_novel"] == g["boot_person_novel"]
    # ... a saved model whose first update the boot check guarded still calls it novel; one
    # that learnt the first frame whole does not
    assert g["end_person_novel"] >= 0.9
    assert w["end_person_novel"] <= 0.2
    # the command: one line per drive and the summary
    assert boot_learnt.main([str(tmp_path / "whole")]) == 0
    out = capsys.readouterr().out
    assert "stubble-boot-3" in out and "still novel at the drive's end in 0" in out


def test_a_folder_without_boot_drives_is_one_clear_line(tmp_path, capsys):
    assert boot_learnt.main([str(tmp_path)]) == 2
    assert "not a campaign folder" in capsys.readouterr().err
    (tmp_path / "drives" / "stubble-coverage-1").mkdir(parents=True)
    assert boot_learnt.main([str(tmp_path)]) == 2
    assert "--save-models" in capsys.readouterr().err


def test_boot_above_horizon_keeps_a_standing_persons_head_out_of_the_first_update():
    """``boot_above_horizon`` (on by default since the thirty-ninth session; docs/front-end.md
    "The person at boot, driven"): without it the boot check keeps only cells under the horizon
    out of the first update, so a person 8 m ahead has the top of their body learnt at boot
    (training stubble-boot-night 8: a hi-vis adult, 41 % of their cells novel after the boot,
    100 % to a model that never saw them). With it the boot candidates' own cells above the
    horizon are kept out too, for candidates within 2 m of the centre line."""
    from drivers.sim import SimField
    from appliance.perception.stereo_novelty import StereoNoveltyConfig
    assert StereoNoveltyConfig().boot_above_horizon is True
    assert StereoNoveltyConfig().boot_above_horizon_half_width_m == 2.0
    f = SimField("stubble-boot-night", 8, sensors=("stereo",), stereo_scale=0.5)
    k = next(i for i, o in enumerate(f.world.obstacles) if o.placement == "at-boot")
    frames = [f.render(0, 0), f.render(100_000_000, 1)]
    person_px = boot_learnt.person_pixels(f, k)
    got = {on: boot_learnt.judge(frames, person_px, dataclasses.replace(
        StereoNoveltyConfig(), model_state="off", boot_above_horizon=on))[0]
        for on in (False, True)}
    (off_p, off_f, n), (on_p, on_f, _) = got[False], got[True]
    assert n >= 10
    assert off_p <= 0.6 and on_p >= 0.9, (off_p, on_p)
    assert abs(on_f - off_f) <= 0.005              # the field's cells: as before
