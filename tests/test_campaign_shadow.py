"""The campaign's shadow (appliance/campaign_shadow.py): a second configuration judged on a
drive's own inputs every cycle, never driving. Real drives of the simulated greenhouse
(training seed 17: a true STOP for a person at 7.5 s; seed 7's crate at 18.4 s was driven
until 2026-12-07, twice as long)."""
import json

import pytest

from appliance.campaign import Campaign, CampaignError, make_spec, run_drive
from appliance.campaign_shadow import differences, paired

# a person in the path: the drive's true STOP at 7.5 s, at rest from 7.7 s, in STOP to the end.
# 8.0 simulated s (81 cycles); 10.2 s until 2026-12-08: the STOP went on unbroken, and the
# shadows with it (the own-pipelines shadow in STOP, the blind one with no miss), to the end --
# no onset, miss or difference to see in the last 2.2 s
SEED, MINUTES = 17, 0.135
EXCLUDE_ALL = ('[zones]\nexclusion = [{x_min_m = -5.0, x_max_m = 40.0, y_min_m = -20.0, '
               'y_max_m = 20.0}]\n')


def _stops(events):
    return [(e["t_s"], e["kind"]) for e in events if e["event"] == "stop"]


@pytest.fixture(scope="module")
def own_pipelines_shadow():
    """Greenhouse training seed 17, 8 simulated s; the shadow's perception differs from the
    drive's in a table the greenhouse's RGB-D box does not use (the laser's range), so it runs
    its own pipelines on the drive's inputs. (A shadow sharing the drive's detections is the
    blind shadow below: two drives, not three, for the suite's time; 2026-12-07.)"""
    spec = make_spec("greenhouse-coverage", SEED, MINUTES, 0.25)
    spec["shadow"] = {**spec["config"], "perception": {
        **spec["config"].get("perception", {}),
        "laser": {"max_range_m": 29.0}}}
    return run_drive(spec)


def test_a_shadow_of_the_drives_own_config_agrees_on_every_cycle(own_pipelines_shadow):
    """With its own pipelines run on the drive's inputs: the same stops, cycle for cycle."""
    run = own_pipelines_shadow
    r = run["result"]
    sh = r["shadow"]
    assert sh["perception"] == "own"
    stops = _stops(run["events"])
    assert len(stops) == 1 and stops[0][1] == "true" and 7.0 <= stops[0][0] <= 8.0  # person
    assert _stops(sh["events"]) == stops
    # the pipelines with points in the stop zone at each onset, named alike on both sides
    assert [e["pipelines"] for e in sh["events"] if e["event"] == "stop"] == \
        [e["pipelines"] for e in run["events"] if e["event"] == "stop"] == [["rgbd"]]
    assert (sh["true_stops"], sh["false_stops"], sh["missed_stops"]) == \
        (r["true_stops"], r["false_stops"], r["missed_stops"])
    assert sh["false_stops_primary_only"] == sh["false_stops_shadow_only"] == 0
    assert sh["true_stops_primary_only"] == sh["true_stops_shadow_only"] == 0


def test_a_shadow_never_drives_and_its_own_misses_are_its_own(own_pipelines_shadow, tmp_path):
    """A shadow that ignores everything (one exclusion box over the whole view; a zones key,
    so it shares the drive's detections): the drive is the same drive, stop for stop; the
    shadow makes no obstacle STOP, so the person's true stop is the drive's only. Through the
    campaign itself: the summary adds the shadow up."""
    f = tmp_path / "blind.toml"
    f.write_text(EXCLUDE_ALL)
    out = tmp_path / "camp"
    s = Campaign("greenhouse-coverage", str(SEED), MINUTES, out, workers=1, stereo_scale=0.25,
                 progress=False, report=False, shadow_file=str(f)).run()
    r = json.loads((out / "drives" / "greenhouse-coverage-17" / "result.json").read_text())
    events = json.loads((out / "drives" / "greenhouse-coverage-17" / "events.json").read_text())
    events = events if isinstance(events, list) else events.get("events", events)
    assert _stops(events) == _stops(own_pipelines_shadow["events"])   # it never drove
    assert r["distance_m"] == own_pipelines_shadow["result"]["distance_m"]
    sh = r["shadow"]
    assert sh["perception"] == "shared"
    assert sh["true_stops"] == 0 and not [e for e in sh["events"]
                                          if e["event"] == "stop" and e["kind"] != "fault"]
    assert sh["true_stops_primary_only"] == 1 and sh["true_stops_shadow_only"] == 0
    assert s["shadow"]["true_stops_primary_only"] == 1
    assert sh["true_stops_primary_only_t_s"] == [t for t, k in _stops(events) if k == "true"]
    assert [(d["drive"], d["what"]) for d in s["shadow"]["differences"]] == [
        ("greenhouse-coverage-17", "true stop only the drive's own config made")]
    assert s["provenance"]["shadow_file"] == str(f)
    from appliance.campaign import format_summary
    assert "shadow (" in format_summary(s) and "only the shadow's 0" in format_summary(s)
    assert "where the drive and its shadow parted" in format_summary(s)
    assert "true stop only the drive's own config made" in format_summary(s)


def test_a_bad_shadow_file_is_one_clear_error(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[zones]\nfront_x_m = 'far'\n")
    with pytest.raises(Exception, match="zones"):
        Campaign("greenhouse-coverage", "7", 0.1, tmp_path / "c", workers=1,
                 shadow_file=str(f))
    with pytest.raises(CampaignError, match="--shadow .*cannot read it"):
        Campaign("greenhouse-coverage", "7", 0.1, tmp_path / "c", workers=1,
                 shadow_file=str(tmp_path / "nowhere.toml"))


def test_paired_counts_what_only_one_side_said():
    primary = [{"t_s": 5.0, "kind": "false"}, {"t_s": 9.0, "kind": "true"},
               {"t_s": 20.0, "kind": "false"}]
    shadow = [{"t_s": 5.3, "kind": "false"}, {"t_s": 14.0, "kind": "false"}]
    times = {"primary": [5.0, 5.1, 9.0, 9.1, 20.0], "shadow": [5.3, 5.4, 14.0]}
    p = paired(primary, shadow, times)
    assert p["false_stops_primary_only"] == 1 and p["false_stops_primary_only_t_s"] == [20.0]
    assert p["false_stops_shadow_only"] == 1 and p["false_stops_shadow_only_t_s"] == [14.0]
    assert p["true_stops_primary_only"] == 1 and p["true_stops_shadow_only"] == 0
    assert p["true_stops_primary_only_t_s"] == [9.0] and p["true_stops_shadow_only_t_s"] == []


def test_differences_list_where_each_drive_and_its_shadow_parted():
    """Drive by drive (kind, then seed as a number), in time: the stops only one side made and
    the shadow's misses; a drive without a shadow, or whose shadow agreed, adds nothing; a
    result written before the true stops' times were kept still gives the rest."""
    sh8 = {"false_stops_primary_only_t_s": [30.0], "false_stops_shadow_only_t_s": [],
           "true_stops_primary_only_t_s": [12.5], "true_stops_shadow_only_t_s": [],
           "events": [{"t_s": 20.0, "event": "missed", "obstacle": "g2/crate",
                       "primary_state": "CLEAR"},
                      {"t_s": 25.0, "event": "missed", "obstacle": "g3/person",
                       "primary_state": "STOP"},
                      {"t_s": 12.5, "event": "stop", "kind": "true"}]}
    sh10 = {"false_stops_primary_only_t_s": [], "false_stops_shadow_only_t_s": [4.0],
            "events": []}                                       # older: no true-stop times
    agreed = {"false_stops_primary_only_t_s": [], "false_stops_shadow_only_t_s": [],
              "true_stops_primary_only_t_s": [], "true_stops_shadow_only_t_s": [], "events": []}
    results = [{"kind": "greenhouse-coverage", "seed": 10, "shadow": sh10},
               {"kind": "greenhouse-coverage", "seed": 8, "shadow": sh8},
               {"kind": "greenhouse-coverage", "seed": 9, "shadow": agreed},
               {"kind": "greenhouse-coverage", "seed": 11}]
    d = differences(results)
    assert [(x["drive"], x["t_s"]) for x in d] == [
        ("greenhouse-coverage-8", 12.5), ("greenhouse-coverage-8", 20.0),
        ("greenhouse-coverage-8", 25.0), ("greenhouse-coverage-8", 30.0),
        ("greenhouse-coverage-10", 4.0)]
    assert d[0]["what"] == "true stop only the drive's own config made"
    # a miss the drive shared is said to be one; a miss where the drive stopped is the shadow's
    assert d[1]["what"] == ("missed by the shadow, not stopped for by the drive either: "
                            "g2/crate (the drive said CLEAR)")
    assert d[2]["what"] == "missed by the shadow only: g3/person (the drive said STOP)"
    assert d[3]["what"] == "false stop only the drive's own config made"
    assert d[4]["what"] == "false stop only the shadow made"


def test_a_shadow_is_laid_over_the_defaults_not_over_config():
    """`--config A --shadow B`: B is merged over the drive's default config, as A is, not over
    A (the help says so; a shadow file names everything it differs in from the defaults)."""
    plain = make_spec("stubble-coverage", 1, 0.1, 0.25)
    spec = make_spec("stubble-coverage", 1, 0.1, 0.25,
                     {"perception": {"pipelines": ["laser"]}},
                     {"grid": {"hold_blind_look_frames": 3}})
    assert spec["config"]["perception"]["pipelines"] == ["laser"]
    assert spec["shadow"]["perception"]["pipelines"] == \
        plain["config"]["perception"]["pipelines"] != ["laser"]
    assert spec["shadow"]["grid"]["hold_blind_look_frames"] == 3
    assert "hold_blind_look_frames" not in spec["config"].get("grid", {})
