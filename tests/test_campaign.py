"""fieldguard campaign: a tiny campaign of real closed-loop drives (the daemon with the laser
pipeline on the simulated field) run once without Ray and once on a local Ray with 2 workers
must give the same figures, drive for drive; a rerun skips finished drives; bad arguments are
one clear error, never a traceback."""
from __future__ import annotations

import csv
import json
import math
import sys

import numpy as np
import pytest

from appliance.campaign import (COMPARE_EXCLUDE, Campaign, CampaignError, aggregate,
                                parse_seeds, poisson_ci95)
from appliance.cli import main

KINDS = ["stubble-day"]        # the obstacle course: a person on the path ~13 m ahead
SEEDS = [1, 2]
MINUTES = 0.1                  # 60 cycles a drive: the box sees the person, the gate acts
LASER = '[perception]\npipelines = ["laser"]\n'


def _strip(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in COMPARE_EXCLUDE}


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray with 2 CPUs for the module (started as the campaign starts it; the
    campaign and eval use a Ray that is already up and leave it up)."""
    ray = pytest.importorskip("ray")
    from appliance.campaign import init_ray
    init_ray(2)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory, local_ray):
    base = tmp_path_factory.mktemp("campaign")
    cfg = base / "laser.toml"
    cfg.write_text(LASER)
    local = Campaign(KINDS, SEEDS, MINUTES, base / "local", workers=1, config_file=str(cfg),
                     stereo_scale=0.25, progress=False).run()
    on_ray = Campaign(KINDS, SEEDS, MINUTES, base / "ray", workers=2, config_file=str(cfg),
                      stereo_scale=0.25, progress=False).run()
    return base, cfg, local, on_ray


def test_ray_with_two_workers_equals_one_worker_without_ray(campaigns):
    base, _cfg, local, on_ray = campaigns
    assert local["engine"] == "local" and local["workers"] == 1
    assert on_ray["engine"] == "ray" and on_ray["workers"] == 2
    assert _strip(on_ray) == _strip(local)
    # the drives did something worth comparing: driven metres, a box that saw obstacles
    assert local["drives"] == 2 and local["distance_km"] > 0.005
    assert local["simulated_hours"] == pytest.approx(2 * MINUTES / 60, abs=1e-6)
    # and each drive's events and per-cycle record (all but the host's ms) are the same
    for s in SEEDS:
        a, b = (base / w / "drives" / f"stubble-day-{s}" for w in ("local", "ray"))
        assert json.loads((a / "events.json").read_text()) == \
            json.loads((b / "events.json").read_text())
        ra, rb = (list(csv.DictReader(open(d / "cycles.csv"))) for d in (a, b))
        assert len(ra) == len(rb) == 60
        keep = [k for k in ra[0] if not k.endswith("_ms")]
        assert [[r[k] for k in keep] for r in ra] == [[r[k] for k in keep] for r in rb]
        assert {r["state"] for r in ra} >= {"STOP", "CLEAR"}


def test_summary_keys_and_report(campaigns):
    base, _cfg, local, _ = campaigns
    for k in ("engine", "workers", "drives", "simulated_hours", "distance_km", "collisions",
              "false_stops", "false_stops_per_hour", "false_stops_per_hour_ci95",
              "true_stops", "missed_stops", "detection_distance_m", "per_scene"):
        assert k in local, k
    assert set(local["per_scene"]) == set(KINDS)
    one = local["per_scene"]["stubble-day"]
    for k in ("simulated_hours", "false_stops_per_hour_ci95", "detection_distance_m"):
        assert one[k] == local[k]
    lo, hi = local["false_stops_per_hour_ci95"]
    assert lo <= local["false_stops_per_hour"] <= hi
    assert json.loads((base / "local" / "summary.json").read_text()) == local
    report = (base / "local" / "report.md").read_text()
    for png in ("detection.png", "false_stops.png", "memory.png", "stages.png",
                "route-stubble-day-1.png"):
        assert f"plots/{png}" in report
        assert (base / "local" / "plots" / png).stat().st_size > 1000
    t = local["timing"]
    assert t["simulated_hours_per_cpu_hour"] > 0 and t["drives_run"] == 2


def test_rerun_skips_finished_drives_and_redrives_a_missing_one(campaigns):
    base, cfg, local, _ = campaigns
    out = base / "local"
    res = out / "drives" / "stubble-day-1" / "result.json"
    before = res.stat().st_mtime_ns
    again = Campaign(KINDS, SEEDS, MINUTES, out, workers=1, config_file=str(cfg),
                     stereo_scale=0.25, progress=False).run()
    assert again["timing"]["drives_run"] == 0 and again["timing"]["drives_skipped"] == 2
    assert _strip(again) == _strip(local)
    assert res.stat().st_mtime_ns == before
    # a drive that did not finish (no result.json: it is written last) is driven again
    (out / "drives" / "stubble-day-2" / "result.json").unlink()
    third = Campaign(KINDS, SEEDS, MINUTES, out, workers=1, config_file=str(cfg),
                     stereo_scale=0.25, progress=False).run()
    assert third["timing"]["drives_run"] == 1
    assert _strip(third) == _strip(local)
    assert not list(out.rglob(".*tmp*"))          # no temporary files left


def test_rerun_with_other_settings_is_refused(campaigns):
    base, cfg, _local, _ = campaigns
    with pytest.raises(CampaignError, match="other settings"):
        Campaign(KINDS, SEEDS, 2 * MINUTES, base / "local", workers=1, config_file=str(cfg),
                 stereo_scale=0.25, progress=False).run()


@pytest.mark.parametrize("args, message", [
    (["--scene", "stubble-nowhere", "--seeds", "1-2"], "unknown scene kind 'stubble-nowhere'"),
    (["--scene", "stubble-day", "--seeds", "5-3"], "--seeds: bad range '5-3'"),
    (["--scene", "stubble-day", "--seeds", "x-y"], "not a seed or a range"),
    (["--scene", "stubble-day", "--seeds", "1-2", "--workers", "0"], "--workers 0"),
    (["--scene", "stubble-day", "--seeds", "1-2", "--stereo-scale", "3"], "--stereo-scale 3"),
    (["--scene", "stubble-day", "--seeds", "1-2", "--config", "/nonexistent/x.toml"],
     "--config /nonexistent/x.toml: cannot read it"),
])
def test_bad_arguments_are_one_clear_error(tmp_path, capsys, args, message):
    rc = main(["campaign", *args, "--minutes", "1", "--out", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("fieldguard: error: ") and message in err
    assert "Traceback" not in err


def test_unwritable_out_dir_and_a_file_as_out(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    for out, message in ((f, "exists and is not a directory"),
                         (f / "sub", "cannot write there")):
        rc = main(["campaign", "--scene", "stubble-day", "--seeds", "1", "--minutes", "1",
                   "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and message in err and "Traceback" not in err


def test_bad_config_file_names_the_problem(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[perception\n")
    rc = main(["campaign", "--scene", "stubble-day", "--seeds", "1", "--minutes", "1",
               "--out", str(tmp_path / "c"), "--config", str(bad)])
    err = capsys.readouterr().err
    assert rc == 2 and "not valid TOML" in err
    bad.write_text('[perception]\npipelines = ["no-such-pipeline"]\n')
    rc = main(["campaign", "--scene", "stubble-day", "--seeds", "1", "--minutes", "1",
               "--out", str(tmp_path / "c"), "--config", str(bad)])
    err = capsys.readouterr().err
    assert rc == 2 and "no-such-pipeline" in err and "Traceback" not in err


def test_workers_without_ray_says_how_to_install_it(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)         # import ray -> ImportError
    cfg = tmp_path / "laser.toml"
    cfg.write_text(LASER)
    rc = main(["campaign", "--scene", "stubble-day", "--seeds", "1", "--minutes", "0.01",
               "--out", str(tmp_path / "c"), "--workers", "2", "--config", str(cfg)])
    err = capsys.readouterr().err
    assert rc == 2 and "needs Ray" in err and "pip install 'fieldguard[campaign]'" in err
    assert "--workers 1" in err and "Traceback" not in err


def test_seed_ranges():
    assert parse_seeds("1000-1003") == [1000, 1001, 1002, 1003]
    assert parse_seeds("7") == [7]
    assert parse_seeds("0-1,10") == [0, 1, 10]
    with pytest.raises(CampaignError, match="twice"):
        parse_seeds("1-3,2")
    with pytest.raises(CampaignError, match="not a seed"):
        parse_seeds("-1")


def test_poisson_interval_is_the_exact_one():
    # Garwood intervals: 0 events -> [0, 3.689], 1 -> [0.0253, 5.572], 10 -> [4.795, 18.39]
    assert poisson_ci95(0, 1.0) == [0.0, 3.689]
    assert poisson_ci95(1, 1.0) == [0.025, 5.572]
    assert poisson_ci95(10, 2.0) == [round(4.7954 / 2, 3), round(18.3904 / 2, 3)]
    assert poisson_ci95(3, 0.0) == [None, None]
    # and the chi-square form it is computed without (scipy.stats, 2.6 CPU-s to import)
    from scipy.stats import chi2
    for k in range(0, 201):
        for h in (0.4, 1.0, 7.3):
            lo = 0.0 if k == 0 else chi2.ppf(0.025, 2 * k) / 2.0
            hi = chi2.ppf(0.975, 2 * k + 2) / 2.0
            assert poisson_ci95(k, h) == [round(lo / h, 3), round(hi / h, 3)], (k, h)


def _result(kind, seed, sim_s, false, dets=()):
    return {"kind": kind, "seed": seed, "simulated_s": sim_s, "distance_m": 100.0,
            "collisions": 0, "false_stops": false, "true_stops": len(dets), "missed_stops": 0,
            "fault_stops": 0, "detours": 0, "overrides": false, "false_stop_s": 10.0 * false,
            "detections": [{"cls": c, "distance_m": d} for c, d in dets],
            "false_stops_by_place": {"lane": false}, "false_stops_by_cause": {"x": false},
            "model": {"samples_max": None, "bound": None}}


def test_aggregate_counts_rates_and_detection_distances():
    rs = [_result("a", 1, 1800.0, 2, [("person", 6.0), ("person", 9.0)]),
          _result("a", 2, 1800.0, 1, [("person", None), ("drum", 4.0), ("person", 7.5)])]
    s = aggregate(rs)
    assert s["simulated_hours"] == 1.0 and s["false_stops"] == 3
    assert s["false_stops_per_hour"] == 3.0
    assert s["false_stops_per_hour_ci95"] == poisson_ci95(3, 1.0)
    assert s["detection_distance_m"]["person"] == {"min": 6.0, "median": 7.5, "stops": 4,
                                                   "stopped_without_hold": 1}
    assert s["detection_distance_m"]["drum"]["median"] == 4.0
    assert s["false_stops_by_place"] == {"lane": 3}
    assert s["false_stops_boot"] is None and s["after_boot"] is None   # results before it


def test_false_stops_after_the_boot_are_reported_apart():
    """A drive boots the box; a 2-minute drive boots it 30 times an hour, a field box once a
    day: the false stops of each drive's first BOOT_S seconds are counted apart, and the rate
    after them is per hour of the time after them."""
    from appliance.campaign_drive import BOOT_S
    rs = [_result("a", 1, 120.0, 3), _result("a", 2, 120.0, 1), _result("a", 3, 5.0, 1)]
    for r, b in zip(rs, (2, 0, 1)):
        r["false_stops_boot"] = b
    s = aggregate(rs)
    after_h = (2 * (120.0 - BOOT_S) + 0.0) / 3600.0
    assert s["false_stops_boot"] == 3 and s["false_stops"] == 5
    assert s["after_boot"] == {"boot_s": BOOT_S, "false_stops": 2, "hours": round(after_h, 6),
                               "false_stops_per_hour": round(2 / after_h, 3),
                               "false_stops_per_hour_ci95": poisson_ci95(2, after_h)}


def test_eval_many_runs_on_ray_is_one_table_equal_to_one_by_one(tmp_path, capsys, local_ray):
    from appliance.campaign_eval import eval_many
    from drivers.sim.record import write_sim_run
    runs = [str(write_sim_run("stubble-day", 4, tmp_path / f"run{s}", seed=s,
                              sensors=("laser",))) for s in (1, 2)]
    one = eval_many(runs, "laser", workers=1)
    par = eval_many(runs, "laser", workers=2)
    strip = lambda r: {k: v for k, v in r.items() if not k.startswith("ms_")  # noqa: E731
                       and k not in ("ms_per_frame", "timed_frames")}
    assert [strip(r) for _, r, _ in par] == [strip(r) for _, r, _ in one]
    assert all(e is None for _, _, e in par)
    rc = main(["eval", *runs, "--pipeline", "laser", "--workers", "2"])
    out = capsys.readouterr().out
    assert rc == 0
    lines = out.strip().splitlines()
    assert lines[0].split()[:3] == ["run", "pipeline", "frames"]
    assert [ln.split()[0] for ln in lines[2:4]] == ["stubble-day-1", "stubble-day-2"]
    assert lines[-1].split()[:2] == ["all", "8"]
    # one bad folder: named, the others still scored, exit 2
    rc = main(["eval", runs[0], str(tmp_path / "nowhere"), "--workers", "1"])
    assert rc == 2 and "no such run folder" in capsys.readouterr().err


def test_interrupted_campaign_writes_the_finished_drives_summary(campaigns, tmp_path,
                                                                 monkeypatch):
    import shutil

    import appliance.campaign as campaign
    base, cfg, local, _ = campaigns
    out = tmp_path / "half"
    shutil.copytree(base / "local" / "drives", out / "drives")
    (out / "drives" / "stubble-day-2" / "result.json").unlink()

    def interrupted(spec, report=None, models=None):   # ^C / SIGTERM during the second drive
        raise KeyboardInterrupt
    monkeypatch.setattr(campaign, "run_drive", interrupted)
    with pytest.raises(CampaignError, match="interrupted: 1 of 2 drives finished"):
        Campaign(KINDS, SEEDS, MINUTES, out, workers=1, config_file=str(cfg),
                 stereo_scale=0.25, progress=False).run()
    s = json.loads((out / "summary.json").read_text())
    assert s["complete"] is False and s["drives"] == 1 and s["drives_planned"] == 2
    assert s["per_drive"] == [d for d in local["per_drive"] if d["seed"] == 1]


def test_a_boot_stop_that_goes_on_for_a_phantom_is_a_false_stop():
    """The box boots in STOP; if it never leaves it because something stands in the stop zone,
    the vehicle was stopped by that all the same. With nothing real there it is a false stop
    (before: only a change INTO STOP started an episode, so a drive that sat 12.8 s in such a
    STOP scored 0 false stops and showed only in false_stop_s)."""
    from types import SimpleNamespace as NS
    import numpy as np
    from appliance.campaign_drive import Drive, deep_merge, drive_config_data
    from hal.types import GateState
    data = deep_merge(drive_config_data("stubble-coverage", 1, stereo_scale=0.25),
                      {"perception": {"pipelines": ["laser"]}})
    drv = Drive("stubble-coverage", 1, 0.01, config_data=data).build()
    try:
        drv.truth = lambda stop_len_m, curvature_1pm=0.0: []                # nothing real anywhere
        def cycle(i, state, reason):
            drv.on_cycle(NS(index=i, output=NS(state=state, reason=reason),
                            verdict=NS(stop_len_m=3.8, nearest_m=1.2),
                            cells_xy=np.zeros((0, 2)), detections={},
                            faults=[reason] if reason.startswith("laser") else [],
                            wall_ms={}))
        cycle(0, GateState.STOP, "booting")
        for i in range(1, 6):
            cycle(i, GateState.STOP, "obstacle 1.2 m ahead in the stop zone (3.8 m)")
        for i in range(6, 9):
            cycle(i, GateState.CLEAR, "zone clear")
        stops = [e for e in drv.events if e["event"] == "stop"]
        assert drv.counts["false"] == 1 and len(stops) == 1, drv.events
        assert stops[0]["kind"] == "false" and stops[0]["duration_s"] == 0.5
        assert "phantom" in stops[0]["cause"]
        # ... and a boot's: it began in the drive's first BOOT_S seconds
        assert drv.result(1.0, 1.0)["false_stops_boot"] == 1
        # a STOP that is already an episode is not counted twice when its reason changes
        cycle(9, GateState.STOP, "laser: stale")
        cycle(10, GateState.STOP, "obstacle 1.2 m ahead in the stop zone (3.8 m)")
        assert drv.counts["false"] == 1 and drv.counts["fault"] == 1, drv.events
    finally:
        drv.daemon.shutdown()


def test_slow_for_nothing_counts_the_slow_seconds_with_nothing_real_in_the_zones():
    """A SLOW costs the user time as a false stop does, in smaller coin: the seconds the box
    said SLOW with nothing real in its stop or slow zone (and no walker about to meet the
    vehicle) are counted apart; a SLOW for something real is not, nor a STOP or a CLEAR."""
    from types import SimpleNamespace as NS
    import numpy as np
    from appliance.campaign import aggregate
    from appliance.campaign_drive import Drive, deep_merge, drive_config_data
    from hal.types import GateState
    data = deep_merge(drive_config_data("stubble-coverage", 1, stereo_scale=0.25),
                      {"perception": {"pipelines": ["laser"]}})
    drv = Drive("stubble-coverage", 1, 0.01, config_data=data).build()
    real = {"k": 0, "id": "c1", "cls": "crate", "ahead": 5.0, "ahead_straight": 5.0,
            "pts": np.zeros((0, 2)), "pts_vehicle": np.zeros((0, 2)), "d_zone": 1.2,
            "meets": False, "meets_slow": False, "in_stop": False, "in_slow": True,
            "deep": False}
    try:
        world = []
        drv.truth = lambda stop_len_m, curvature_1pm=0.0: world

        def cycle(i, state, reason):
            drv.on_cycle(NS(index=i, output=NS(state=state, reason=reason),
                            verdict=NS(stop_len_m=3.8, nearest_m=4.0),
                            cells_xy=np.zeros((0, 2)), detections={}, faults=[], wall_ms={}))
        for i in range(0, 12):                        # 1.2 s SLOW for nothing
            cycle(i, GateState.SLOW, "obstacle 4.0 m ahead in the slow zone")
        world.append(real)
        for i in range(12, 20):                       # 0.8 s SLOW for the crate: not counted
            cycle(i, GateState.SLOW, "obstacle 4.0 m ahead in the slow zone")
        world.clear()
        for i in range(20, 25):                       # CLEAR and STOP: not SLOW
            cycle(i, GateState.CLEAR if i < 22 else GateState.STOP, "zone clear")
        r = drv.result(2.5, 1.0)
        assert r["slow_for_nothing_s"] == 1.2
        assert aggregate([r, r])["slow_for_nothing_s"] == 2.4
        del r["slow_for_nothing_s"]                    # a result.json from before: none
        assert aggregate([r])["slow_for_nothing_s"] == 0.0
    finally:
        drv.daemon.shutdown()


def test_a_greenhouse_drive_runs_the_zones_run_sim_greenhouse_runs():
    """The campaign's greenhouse drives judged with the default 1.25 m half width put the bush
    rows beside the 0.8 m sprayer in the stop zone (every training phantom was at a bush edge);
    `run --sim greenhouse` runs 0.5 m. The two now run the same zones; stubble keeps the
    default width."""
    from appliance.campaign_drive import drive_config_data
    from appliance.config import SCENE_ZONES, parse_config
    gh = parse_config(drive_config_data("greenhouse-coverage", 1), "drive").zones
    assert (gh.front_x_m, gh.half_width_m) == (SCENE_ZONES["greenhouse"]["front_x_m"],
                                               SCENE_ZONES["greenhouse"]["half_width_m"])
    st = parse_config(drive_config_data("stubble-coverage", 1), "drive").zones
    assert st.half_width_m == 1.25 and st.front_x_m == 2.2
    # the body's tail behind the origin ([zones] follow_path sweeps it): the vehicle's own
    assert gh.body_rear_m == SCENE_ZONES["greenhouse"]["body_rear_m"] == 0.1
    assert st.body_rear_m == 0.4


def test_a_stop_for_a_walker_about_to_meet_the_vehicle_is_scored_true():
    """campaign_drive.meets_vehicle: the scorer's truth for a STOP made for a walker before it
    is in the stop zone ([tracking] movers). Vehicle at 2.5 m/s (rest 1.75 s + 0.5 s away),
    body from 0.4 m behind its origin to the front (2.6 m) + 0.5 m, |y| <= 1.25 + 0.2 m."""
    import numpy as np

    from appliance.campaign_drive import meets_vehicle
    from appliance.config import ZonesConfig
    z = ZonesConfig(front_x_m=2.6)

    def person(x, y):
        return np.array([[x + a, y + b] for a in (-0.15, 0.15) for b in (-0.22, 0.22)])
    # training seed 15's person: 3.3 m ahead of the front, 4.1 m to the right, walking in
    assert meets_vehicle(person(5.9, -4.1), (0.53, 1.18), 2.5, z, 0.4, 0.5, 0.2)
    # the same person walking away, or standing, or the vehicle standing (it walks past ahead)
    assert not meets_vehicle(person(5.9, -4.1), (0.53, -1.18), 2.5, z, 0.4, 0.5, 0.2)
    assert not meets_vehicle(person(5.9, -4.1), (0.0, 0.0), 2.5, z, 0.4, 0.5, 0.2)
    assert not meets_vehicle(person(5.9, -4.1), (0.53, 1.18), 0.0, z, 0.4, 0.5, 0.2)
    # crossing 17 m ahead: gone before the vehicle gets there
    assert not meets_vehicle(person(19.6, -3.0), (0.0, 1.5), 2.5, z, 0.4, 0.5, 0.2)
    # too far aside to get there in time (2.25 s at 1.2 m/s: 2.7 m)
    assert not meets_vehicle(person(4.0, -4.5), (0.0, 1.2), 2.5, z, 0.4, 0.5, 0.2)
    assert meets_vehicle(person(4.0, -3.5), (0.0, 1.2), 2.5, z, 0.4, 0.5, 0.2)


def test_contact_part_tells_front_side_and_rear():
    """Where an obstacle met the vehicle (rear 0.4 m behind the origin): from the path ahead
    (a forward box answers for it), or from beside or behind the body (the greenhouse
    training drives' two collisions: a walker out of a bush row, a person swept by a corner
    in a U-turn, never in the corridor ahead)."""
    from appliance.campaign_drive import contact_part
    sq = lambda x, y: np.array([[x + a, y + b] for a in (-0.15, 0.15)  # noqa: E731
                                for b in (-0.2, 0.2)])
    assert contact_part(sq(2.3, 0.0), 0.4, True) == "front"      # head on
    assert contact_part(sq(2.1, 0.8), 0.4, True) == "front"      # at a corner, came from ahead
    assert contact_part(sq(2.1, 0.8), 0.4, False) == "side"      # the same place, from beside
    assert contact_part(sq(1.2, 0.7), 0.4, False) == "side"
    assert contact_part(sq(-0.6, 0.0), 0.4, False) == "rear"


def test_a_collision_beside_the_body_is_reported_as_a_side_contact():
    """A real drive: an obstacle put beside the vehicle's body is hit in the next cycle; the
    event and the drive's result say "side", and the summary counts it."""
    from appliance.campaign_drive import Drive, deep_merge, drive_config_data
    data = deep_merge(drive_config_data("stubble-coverage", 1, stereo_scale=0.25),
                      {"perception": {"pipelines": ["laser"]}})
    drv = Drive("stubble-coverage", 1, 0.01, config_data=data).build()
    try:
        v = drv.vehicle
        x, y, yaw = v.pose()
        k, o = 0, drv.field.world.obstacles[0]
        # 1.0 m ahead of the origin, 0.45 m left: beside the 1.5 m-wide body, behind its front
        o.x = x + 1.0 * math.cos(yaw) - 0.45 * math.sin(yaw)
        o.y = y + 1.0 * math.sin(yaw) + 0.45 * math.cos(yaw)
        v.refresh_footprint(k)
        drv.n_cycles = 2
        res = drv.run()
    finally:
        drv.daemon.shutdown()
    hits = [e for e in drv.events if e["event"] == "collision"]
    assert [e["contact"] for e in hits] == ["side"], drv.events
    result = res["result"]
    assert result["collisions_by_contact"] == {"side": 1}
    assert aggregate([result])["collisions_by_contact"] == {"side": 1}


def _boot_drive(x_m: float, ahead_m: float, in_stop: bool):
    """A stubble-boot drive (the laser alone: nothing rendered for the camera) whose truth is
    only its person at boot, ``x_m`` ahead of the origin (``ahead_m`` of the front), and that
    person's truth row (change it to move them)."""
    import numpy as np
    from appliance.campaign_drive import Drive, deep_merge, drive_config_data
    data = deep_merge(drive_config_data("stubble-boot", 2, stereo_scale=0.25),
                      {"perception": {"pipelines": ["laser"]}})
    drv = Drive("stubble-boot", 2, 0.01, config_data=data).build()
    k = next(i for i, o in enumerate(drv.field.world.obstacles) if o.placement == "at-boot")
    o = drv.field.world.obstacles[k]
    foot = np.array([[x_m + a, b] for a in (-0.15, 0.15) for b in (-0.25, 0.25)])
    person = {"k": k, "id": o.id, "cls": o.cls, "ahead": ahead_m, "ahead_straight": ahead_m,
              "pts": foot, "pts_vehicle": foot, "d_zone": 0.0 if in_stop else 1.0,
              "meets": False, "meets_slow": False, "in_stop": in_stop, "in_slow": not in_stop,
              "deep": in_stop}
    drv.truth = lambda stop_len_m, curvature_1pm=0.0: [person]
    return drv, o, person


def test_the_person_standing_ahead_at_boot_is_scored_on_its_own():
    """stubble-boot: result.json's ``at_boot`` says, for the person standing in the path when
    the box started, when the box's cells first lay on it, whether the hold that ended in its
    stop began within the first second, and whether it was run into or missed; each
    detection gives the time its hold began (``held_from_s``)."""
    from types import SimpleNamespace as NS
    import numpy as np
    from hal.types import GateState
    drv, o, person = _boot_drive(7.0, 4.8, in_stop=False)
    try:
        on = np.array([[7.0, 0.0]])

        def cycle(i, state, reason, cells):
            drv.on_cycle(NS(index=i, output=NS(state=state, reason=reason),
                            verdict=NS(stop_len_m=3.8, nearest_m=4.8), cells_xy=cells,
                            detections={}, faults=[], wall_ms={}))
        cycle(0, GateState.STOP, "booting", np.zeros((0, 2)))
        cycle(1, GateState.STOP, "booting", on)             # held from 0.1 s ...
        cycle(2, GateState.STOP, "booting", np.zeros((0, 2)))   # ... lost once
        for i in range(3, 30):                               # held again from 0.3 s
            cycle(i, GateState.SLOW, "obstacle 4.8 m ahead in the slow zone", on)
        person.update(ahead=2.0, in_stop=True, in_slow=False)
        cycle(30, GateState.STOP, "obstacle 2.0 m ahead in the stop zone (3.8 m)", on)
        r = drv.result(1.0, 1.0)
        (b,) = r["at_boot"]
        assert b["obstacle"] == f"{o.id}/{o.cls}" and b["ahead_at_start_m"] == 4.8
        assert b["first_held_s"] == 0.1 and b["held_from_s"] == 0.3
        assert b["stopped"] and b["stop_t_s"] == 3.0 and b["held_from_first_s"]
        assert not b["collision"] and not b["missed"]
        assert r["detections"][0]["held_from_s"] == 0.3
        from appliance.campaign import aggregate
        a = aggregate([r, r])["at_boot"]
        assert a == {"obstacles": 2, "held_from_first_s": 2, "stopped": 2, "collisions": 0,
                     "missed": 0, "never_held": 0, "first_held_s_max": 0.1}
        del r["at_boot"]                      # a result.json from before: no such figure
        assert aggregate([r])["at_boot"] is None
    finally:
        drv.daemon.shutdown()


def test_a_person_at_boot_held_late_or_missed_says_so():
    """The same person held only from 1.5 s on, then the box says CLEAR with it deep in the
    stop zone: not held from the first second, not stopped for, missed."""
    from types import SimpleNamespace as NS
    import numpy as np
    from hal.types import GateState
    drv, o, person = _boot_drive(4.0, 1.8, in_stop=True)
    try:
        for i in range(0, 15):
            drv.on_cycle(NS(index=i, output=NS(state=GateState.STOP, reason="booting"),
                            verdict=NS(stop_len_m=3.8, nearest_m=None),
                            cells_xy=np.zeros((0, 2)), detections={}, faults=[],
                            wall_ms={}))
        for i in range(15, 20):
            drv.on_cycle(NS(index=i, output=NS(state=GateState.CLEAR, reason="zone clear"),
                            verdict=NS(stop_len_m=3.8, nearest_m=None),
                            cells_xy=np.array([[4.0, 0.0]]), detections={}, faults=[],
                            wall_ms={}))
        (b,) = drv.result(1.0, 1.0)["at_boot"]
        assert b["first_held_s"] == 1.5 and not b["stopped"] and b["held_from_s"] is None
        assert not b["held_from_first_s"] and b["missed"] and not b["collision"]
    finally:
        drv.daemon.shutdown()
