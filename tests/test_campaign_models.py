"""fieldguard campaign --save-models / --models-from: a campaign keeps each drive's novelty model
at its end, and a second campaign of the same drives boots each with it (as an installed box
boots with the model it saved); real (tiny) drives, without Ray."""
from __future__ import annotations

import csv
import json

import pytest

from appliance.campaign import MODEL_DIR, MODEL_FILE, Campaign, CampaignError
from appliance.cli import main
from appliance.novelty_store import light_path, read
from appliance.perception.novelty import NIGHT_LIGHT

SCENES = "stubble-coverage,stubble-coverage-night"
SL = '[perception]\npipelines = ["stereo-novelty", "laser"]\n'
# 42 cycles: the model's updates come on frame 1 (the boot's) and every 40th frame
# (stereo-novelty update_every_frames), so frame 40 (t 3.9 s) is each drive's one update after
# the first -- what the saved model has learnt on top of the boot's, and what a booted drive
# learns on top of the saved model. (0.1 min and stereo scale 0.25 until 2026-12-08: the 18
# frames after the update and the larger frames added nothing a test looks at; the novelty
# light is the scene's, not the picture's.)
MINUTES, SCALE = 0.07, 0.15


def _campaign(out, cfg, **kw):
    return Campaign(SCENES, "3", MINUTES, out, workers=1, config_file=str(cfg),
                    stereo_scale=SCALE, progress=False, report=False, **kw)


def _samples(folder, kind) -> list[int]:
    """The novelty model's samples, cycle by cycle, of a drive (cycles.csv)."""
    with open(folder / "drives" / f"{kind}-3" / "cycles.csv", newline="") as f:
        return [int(r["model_samples"]) for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    base = tmp_path_factory.mktemp("models")
    cfg = base / "sl.toml"
    cfg.write_text(SL)
    saved = _campaign(base / "saved", cfg, save_models=True)
    saved.run()
    booted = _campaign(base / "booted", cfg, models_from=str(base / "saved"))
    summary = booted.run()
    return base, cfg, summary


def test_each_drive_keeps_its_model_as_the_box_saves_it(pair):
    base = pair[0]
    for kind, light in (("stubble-coverage", "day"), ("stubble-coverage-night", NIGHT_LIGHT)):
        m = base / "saved" / "drives" / f"{kind}-3" / MODEL_DIR
        state = read(m / MODEL_FILE)
        assert state is not None and state["light"] == light, (kind, state and state["light"])
        assert int(state["updates"]) > 0
        night = light_path(m / MODEL_FILE, NIGHT_LIGHT)
        # the strobe-lit model is also kept apart (a day save would not replace it)
        assert night.exists() == (light == NIGHT_LIGHT), sorted(p.name for p in m.iterdir())
    # the campaign that did not ask keeps none
    assert not list((base / "booted" / "drives").glob(f"*/{MODEL_DIR}"))


def test_a_second_campaign_boots_each_drive_with_its_saved_model(pair):
    base, _, summary = pair
    for kind in SCENES.split(","):
        empty, loaded = _samples(base / "saved", kind), _samples(base / "booted", kind)
        saved = read(base / "saved" / "drives" / f"{kind}-3" / MODEL_DIR / MODEL_FILE)
        # from empty the box learns its first frame (the boot guard's update); booted, it
        # starts with what the first campaign's drive had learnt at its end (the daemon loaded
        # it at start), and learns on from there
        assert empty[0] < len(saved["x"]) == empty[-1], (empty[0], len(saved["x"]), empty[-1])
        assert loaded[0] == len(saved["x"]) < loaded[-1], (loaded[0], loaded[-1])
        r = json.loads((base / "booted" / "drives" / f"{kind}-3" / "result.json").read_text())
        src = r["spec"]["models_from"]
        assert src["folder"].endswith(f"saved/drives/{kind}-3/{MODEL_DIR}")
        assert MODEL_FILE in src["sha256"]
    assert summary["provenance"]["models_from"].endswith("saved")
    assert summary["provenance"]["save_models"] is False


def test_a_rerun_skips_the_booted_drives_and_other_models_drive_again(pair, tmp_path):
    base, cfg, _ = pair
    again = _campaign(base / "booted", cfg, models_from=str(base / "saved"))
    assert len(again.finished()) == 2
    # the same folder, booted from empty this time: refused, not mixed
    with pytest.raises(CampaignError, match="other settings"):
        _campaign(base / "booted", cfg).finished()


def test_models_from_a_campaign_without_them_is_one_clear_error(pair, tmp_path, capsys):
    base, cfg, _ = pair
    with pytest.raises(CampaignError, match=r"no saved model for 2 of 2 drives "
                                            r"\(stubble-coverage-3, stubble-coverage-night-3\)"):
        _campaign(tmp_path / "x", cfg, models_from=str(base / "booted"))
    with pytest.raises(CampaignError, match="not a campaign folder"):
        _campaign(tmp_path / "x", cfg, models_from=str(tmp_path))
    laser = tmp_path / "laser.toml"
    laser.write_text('[perception]\npipelines = ["laser"]\n')
    with pytest.raises(CampaignError, match="runs no novelty model"):
        _campaign(tmp_path / "y", laser, save_models=True)
    # from the command line: one line, no traceback, exit 2
    rc = main(["campaign", "--scene", SCENES, "--seeds", "3", "--minutes", "0.1", "--out",
               str(tmp_path / "z"), "--workers", "1", "--config", str(cfg),
               "--models-from", str(base / "booted")])
    err = capsys.readouterr().err
    assert rc == 2 and "no saved model" in err and "Traceback" not in err, err
    assert not (tmp_path / "z" / "drives").exists()


def test_a_shadow_boots_with_the_model_its_config_names(pair, tmp_path):
    """With --models-from a drive's shadow gets the same model file in its config
    (run_drive); the shadow loads it as the daemon does, and never writes it."""
    from appliance.campaign_drive import deep_merge, drive_config_data
    from appliance.campaign_shadow import Shadow
    from appliance.config import parse_config
    from appliance.daemon import sim_config
    base = pair[0]
    f = tmp_path / MODEL_FILE
    f.write_bytes((base / "saved" / "drives" / "stubble-coverage-3" / MODEL_DIR /
                   MODEL_FILE).read_bytes())
    data = drive_config_data("stubble-coverage", 3, stereo_scale=SCALE, extra=deep_merge(
        {"perception": {"pipelines": ["stereo-novelty", "laser"]}},
        {"perception": {"stereo-novelty": {"model_state": str(f), "model_save_s": 0.0}}}))
    before = f.read_bytes()
    sh = Shadow(sim_config(parse_config(data, "<test>"), "stubble-coverage"))
    try:
        nov = [p.novelty for p in sh.pipelines if hasattr(p, "novelty")]
        assert len(nov) == 1 and nov[0].model.size == len(read(f)["x"]) > 0
    finally:
        sh.close()
    assert f.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [MODEL_FILE]


def test_campaign_compare_says_which_campaign_booted_with_saved_models(pair):
    from appliance.campaign_compare import compare, format_compare
    base = pair[0]
    c = compare(base / "saved", base / "booted")
    assert c["a_models_from"] is None and c["b_models_from"].endswith("saved")
    head = format_compare(c).splitlines()[:2]
    assert "booted with" not in head[0] and head[1].endswith(
        f"; booted with the models of {c['b_models_from']})"), head
    # the same scenes and seeds, paired drive by drive
    assert [(d["kind"], d["seed"]) for d in c["drives"]] == [
        ("stubble-coverage", 3), ("stubble-coverage-night", 3)]
