"""Safe from boot (issue #14): the novelty model never learns what the box cannot vouch for,
and it persists across restarts in the state directory without ever taking the box down."""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from appliance import novelty_store
from appliance.perception import SensorInputs
from appliance.perception.novelty import NoveltyDetector
from appliance.perception.stereo_novelty import (PRE_ISSUE_14, StereoNoveltyConfig,
                                                 StereoNoveltyPipeline)
from drivers.sim import SimField
from drivers.sim.world import Obstacle


def _person_at_boot(x=12.2, y=4.0):
    """The empty stubble field by day with one hi-vis person standing ~11 m ahead (the
    camera is 1.2 m forward of the vehicle origin), 4 m to the left: the issue's case."""
    f = SimField("stubble-empty", seed=7, sensors=("stereo",), stereo_scale=0.5)
    o = Obstacle("p", "person", "person", x, y, 90.0, 0.3, 0.5, 1.8, (0.10, 0.45, 0.95),
                 (0.35, 0.20, 0.12))
    o.z0 = float(f.world.ground(np.float32(o.x), np.float32(o.y)))
    f.world.obstacles[:] = [o]
    f.vehicle._footprints = [f.vehicle._footprint_points(o)]
    return f


@pytest.fixture(scope="module")
def boot_frames():
    f = _person_at_boot()
    frames = []
    for i in range(2):
        s = f.render(i * 100_000_000, i)
        frames.append((s.stereo, s.vehicle, s.truth))
    return frames


def _person_cells(pipe, truth_xy, frame, vehicle, z=0.4):
    """The novelty cell (stabilised grid) of the person's point ``z`` m up (default: the
    legs, well below the horizon), from the truth position."""
    cal = frame.calib
    res = pipe.last[0]
    p = np.array([truth_xy[0], truth_xy[1], z])
    R = cal.mount.camera_to_vehicle()
    q = R.T @ (p - cal.mount.position)                     # optical frame
    u = cal.camera.fx * q[0] / q[2] + cal.camera.cx
    v = cal.camera.fy * q[1] / q[2] + cal.camera.cy
    kd = frame.left.shape[1] // (res.mask.shape[1] * res.cell_px) or 1
    return int(v / kd // res.cell_px), int(u / kd // res.cell_px)


def _run(frames, **opts):
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", **opts)
    pipe = StereoNoveltyPipeline(o, background=False)
    out = []
    for st, veh, truth in frames:
        det = pipe.process(SensorInputs(stamp_ns=st.stamp_ns, stereo=st, vehicle=veh))
        out.append((det, pipe.last[0]))
    return pipe, out


def _near(points, ob, m=0.5):
    from appliance.evaluation import footprint_distance
    return bool(len(points)) and bool((footprint_distance(points, ob) <= m).any())


def test_left_blind_strip_hid_the_person(boot_frames):
    """The issue's miss: at 640 px with 144 disparities OpenCV leaves the left 144 columns
    without disparity, and the person 4 m left at 11 m stands in them."""
    st, veh, _ = boot_frames[0]
    ob = boot_frames[0][2][0]
    found = {}
    for pad in (False, True):
        pipe, out = _run(boot_frames[:1], boot_guard=True, depth_cue="off", pad_left=pad)
        found[pad] = _near(out[0][0].points_xy, ob, 0.3)
        pipe.close()
    assert found == {False: False, True: True}


def test_person_ahead_at_boot_is_held_and_never_learnt(boot_frames):
    ob = boot_frames[0][2][0]
    assert 11.5 < ob["x_m"] < 12.5 and 3.5 < ob["y_m"] < 4.5      # 11 m from the camera
    # the paper's start (no boot guard, no depth cue): the first update learns the person
    pipe, out = _run(boot_frames, boot_guard=False, depth_cue="off", pad_left=True)
    r, c = _person_cells(pipe, (ob["x_m"], ob["y_m"]), boot_frames[1][0], boot_frames[1][1])
    assert not out[1][1].raw[r, c], "without the guard the person is learnt as field"
    pipe.close()
    # with the guard: an obstacle of the first frame, kept out of the first update, so still
    # novel (and detected) on the next frame
    pipe, out = _run(boot_frames, boot_guard=True, depth_cue="off", pad_left=True)
    det0 = out[0][0]
    assert det0.debug["boot"]["candidates"] >= 1 and det0.debug["boot"]["excluded_cells"] > 0
    assert _near(det0.points_xy, ob)
    assert any(abs(cd.x_m - ob["x_m"]) < 1.0 and abs(cd.y_m - ob["y_m"]) < 1.0
               and cd.height_m > 1.2 and cd.ground_contact for cd in det0.candidates)
    assert out[1][1].raw[r, c], "the person's cells must not be learnt at boot"
    # (only below the horizon: the cell of the chest, 0.9 m up at 11 m, is one cell under the
    # horizon row and is learnt, as the sky and the skyline are; see boot_horizon_cells)
    assert out[1][0].debug["boot"] is None            # the guard ran until the first update
    assert _near(out[1][0].points_xy, ob)
    pipe.close()


def test_warm_up_learns_the_field_every_other_frame_and_never_the_person_ahead():
    """``warmup_updates`` (off by default): the model's first updates come every
    ``warmup_every_frames`` frames instead of every 40. Booted with the person ahead and the
    vehicle standing, 10 updates in 2 s: the person is held in every frame and its cells are
    still novel after them."""
    f = _person_at_boot()
    frames = []
    for i in range(21):
        s = f.render(i * 100_000_000, i)
        frames.append((s.stereo, s.vehicle, s.truth))
    ob = frames[0][2][0]
    pipe, out = _run(frames, pad_left=True, warmup_updates=10, warmup_every_frames=2)
    try:
        assert pipe.novelty.model.updates == 10          # frame 1, then 2, 4, ... 18
        assert all(_near(det.points_xy, ob) for det, _ in out)
        r, c = _person_cells(pipe, (ob["x_m"], ob["y_m"]), frames[-1][0], frames[-1][1])
        assert out[-1][1].raw[r, c], "the person's cells must not be learnt by the warm-up"
    finally:
        pipe.close()


def test_warm_up_schedule_and_a_loaded_model_is_no_young_one():
    d = _detector(warmup_updates=3, warmup_every_frames=2, update_every_frames=40)
    res = type("R", (), {"valid": np.ones(4, bool),
                         "descriptors": np.random.default_rng(0).uniform(
                             0, 1, (4, 8)).astype(np.float32)})()
    handed = [i + 1 for i in range(100) if d.learn(res)]
    assert handed == [1, 2, 4, 40, 80]                  # first, two more every 2, then every 40
    # off (the paper's): first, then every 40
    d = _detector(update_every_frames=40, **{k: v for k, v in PRE_ISSUE_14.items()
                                             if k.startswith("warmup")})
    assert [i + 1 for i in range(100) if d.learn(res)] == [1, 40, 80]
    # a model restored from the state directory has learnt: no warm-up
    d = _detector(warmup_updates=3, warmup_every_frames=2, update_every_frames=40)
    d.import_state(_trained().export_state())
    assert [i + 1 for i in range(100) if d.learn(res)] == [40, 80]


def test_warm_up_never_learns_what_the_boot_check_kept_out():
    """What the boot check kept out of the first update (``first_exclude``) stays out of the
    warm-up's updates too, whatever this frame's own exclusion says (a thing standing in view
    at boot that the frame's obstacle points miss -- far, thin -- would otherwise be learnt
    at 2-frame intervals: training seed 1's day run lost 4 of 49 pole frames so); after the
    warm-up the paper's rule (only this frame's exclusion) is back."""
    d = _detector(warmup_updates=3, warmup_every_frames=2, update_every_frames=40)
    handed = []
    d.model.update = lambda samples: handed.append(len(samples))
    res = type("R", (), {"valid": np.ones(4, bool),
                         "descriptors": np.arange(32, dtype=np.float32).reshape(4, 8)})()
    boot = np.array([True, False, False, False])
    frames = [i + 1 for i in range(40)
              if d.learn(res, exclude=np.zeros(4, bool), first_exclude=boot)]
    assert frames == [1, 2, 4, 40] and handed == [3, 3, 3, 4]
    # no boot check (boot_guard off, or a model loaded from the state directory): no change
    d = _detector(warmup_updates=3, warmup_every_frames=2, update_every_frames=40)
    handed.clear()
    d.model.update = lambda samples: handed.append(len(samples))
    assert [i + 1 for i in range(40) if d.learn(res)] == [1, 2, 4, 40] and handed == [4] * 4


# ---- persistence -----------------------------------------------------------------------------
def _detector(**kw):
    o = dataclasses.replace(StereoNoveltyConfig(), **kw)
    return NoveltyDetector(o, background=False)


def _trained():
    d = _detector()
    rng = np.random.default_rng(0)
    d.model.update(rng.uniform(0, 1, (500, 8)).astype(np.float32))
    d.model.update(rng.uniform(0, 1, (300, 8)).astype(np.float32))
    return d


def test_model_round_trips_through_the_state_file(tmp_path):
    d = _trained()
    path = tmp_path / "novelty-stereo-novelty.npz"
    novelty_store.save(path, d.export_state())
    assert path.exists() and not (tmp_path / "novelty-stereo-novelty.npz.tmp").exists()
    e = _detector()
    assert not e.first_sent
    e.import_state(novelty_store.read(path))
    q = np.random.default_rng(1).uniform(0, 1, (50, 8)).astype(np.float32)
    np.testing.assert_allclose(e.model.density(q), d.model.density(q))
    assert e.model.updates == d.model.updates and e.first_sent


@pytest.mark.parametrize("content", [b"", b"garbage not a zip file", b"PK\x03\x04truncated"])
def test_corrupt_file_is_a_log_line_and_a_fresh_start(tmp_path, caplog, content):
    path = tmp_path / "m.npz"
    path.write_bytes(content)
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.read(path) is None
    assert "unreadable" in caplog.text and "empty model" in caplog.text


def test_truncated_real_file_is_a_fresh_start(tmp_path, caplog):
    path = tmp_path / "m.npz"
    novelty_store.save(path, _trained().export_state())
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.read(path) is None
    assert "unreadable" in caplog.text


def test_foreign_files_are_refused_with_a_reason(tmp_path, caplog):
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros((3, 8)))                    # another program's npz
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.read(other) is None
    assert "not a fieldguard novelty model" in caplog.text
    st = _trained().export_state()
    e = _detector(sigma=0.07)                              # other settings
    with pytest.raises(ValueError, match="other settings"):
        e.import_state(st)
    assert e.model.empty and not e.first_sent
    with pytest.raises(ValueError, match="version"):
        _detector().import_state(dict(st, version=99))
    bad = dict(st, w=np.full(len(st["w"]), np.nan))
    with pytest.raises(ValueError, match="non-finite"):
        _detector().import_state(bad)
    with pytest.raises(ValueError, match="shapes"):
        _detector().import_state(dict(st, x=st["x"][:, :5]))


def test_pipelines_load_and_save_through_the_state_directory(tmp_path, caplog):
    env = {"STATE_DIRECTORY": str(tmp_path)}
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="auto")
    p = StereoNoveltyPipeline(o, background=False)
    assert novelty_store.save_from([p], env) == []          # an empty model is not written
    p.novelty.model.update(np.random.default_rng(2).uniform(0, 1, (100, 8)))
    saved = novelty_store.save_from([p], env)
    assert saved == [str(tmp_path / "novelty-stereo-novelty.npz")]
    q = StereoNoveltyPipeline(o, background=False)
    assert novelty_store.load_into([q], env) == saved
    assert q.novelty.model.size == 100 and q.novelty.first_sent
    # a foreign model (other sigma): a clear log line, the pipeline starts empty
    r = StereoNoveltyPipeline(dataclasses.replace(o, sigma=0.08), background=False)
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.load_into([r], env) == []
    assert "not used" in caplog.text and r.novelty.model.empty
    # no state directory, or off: nothing read or written
    assert novelty_store.state_path("auto", "stereo-novelty", {}) is None
    assert novelty_store.state_path("off", "stereo-novelty", env) is None
    # an unwritable place: logged, never raised
    ro = dataclasses.replace(o, model_state=str(tmp_path / "f" / "x.npz"))
    (tmp_path / "f").write_text("a file where a directory should be")
    s = StereoNoveltyPipeline(ro, background=False)
    s.novelty.model.update(np.random.default_rng(3).uniform(0, 1, (10, 8)))
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.save_from([s], env) == []
    assert "not saved" in caplog.text
    for x in (p, q, r, s):
        x.close()


def test_near_search_ranges_a_person_standing_in_the_stop_zone():
    """A person standing 3.0 m ahead of the vehicle origin (0.4 m beyond its front, 1.8 m from
    the camera) is nearer than min_depth_m (3 m): with the near search off (the default) no
    point lies within 0.5 m of them (measured: 0; at 3.3 m, 7). With near_min_depth_m = 1.6
    the strips that see the near ground search far enough and their points lie on the person
    (measured: 17; 24 at 3.3 m)."""
    from appliance.evaluation import footprint_distance
    f = _person_at_boot(x=3.0, y=0.0)
    s = f.render(0, 0)
    ob = s.truth[0]

    def near_points(**opts):
        o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", **opts)
        pipe = StereoNoveltyPipeline(o, background=False)
        det = pipe.process(SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo,
                                        vehicle=s.vehicle))
        pipe.close()
        xy = np.asarray(det.points_xy, float).reshape(-1, 2)
        return int((footprint_distance(xy, ob) <= 0.5).sum()) if len(xy) else 0

    assert near_points() == 0                               # off (default): ends at 3 m
    assert near_points(near_min_depth_m=1.6) >= 10


# ---- the light a saved model was learnt under (thirtieth session) ----------------------------
def _fake_result(seed=0, n=6):
    return type("R", (), {"valid": np.ones(n, bool),
                          "descriptors": np.random.default_rng(seed).uniform(
                              0, 1, (n, 8)).astype(np.float32)})()


def test_a_saved_model_says_the_light_most_of_its_newest_updates_were_learnt_under(tmp_path):
    d = _detector(update_every_frames=1)
    assert d.light is None and d.export_state() is None
    for i in range(18):
        d.learn(_fake_result(i), light="night-strobe")
    for i in range(2):                          # the strobe's unlit probe frames at night
        d.learn(_fake_result(100 + i), light="day")
    assert d.light == "night-strobe"
    path = tmp_path / "m.npz"
    novelty_store.save(path, d.export_state())
    state = novelty_store.read(path)
    assert state["light"] == "night-strobe"
    e = _detector(update_every_frames=1)
    e.import_state(state)
    assert e.loaded_light == "night-strobe" and e.light == "night-strobe"
    # a file saved before the light was recorded loads as before, its light unknown
    old = dict(state)
    del old["light"]
    f = _detector()
    f.import_state(old)
    assert f.loaded_light is None and f.light is None and f.model.size == e.model.size
    with pytest.raises(ValueError, match="light"):
        _detector().import_state({**state, "light": 3})


def test_a_day_model_is_set_aside_at_a_strobe_lit_boot_and_only_then():
    d = _detector(update_every_frames=1)
    for i in range(5):
        d.learn(_fake_result(i), light="day")
    day = d.export_state()
    night = {**day, "light": "night-strobe"}

    def loaded(state):
        e = _detector(update_every_frames=1)
        e.import_state(state)
        return e
    e = loaded(day)
    assert not e.set_aside_other_light("day")            # by day: kept
    assert e.model.size == d.model.size and e.first_sent
    assert e.set_aside_other_light("night-strobe")       # at night: set aside
    assert e.model.empty and not e.first_sent and e.light is None
    assert not e.set_aside_other_light("night-strobe")   # once
    # a night model by day (and a night boot's unlit first frames): kept
    e = loaded(night)
    assert not e.set_aside_other_light("day") and e.model.size == d.model.size
    # a model of unrecorded light: kept
    e = loaded({k: v for k, v in day.items() if k != "light"})
    assert not e.set_aside_other_light("night-strobe") and e.first_sent
    # past the boot (30 frames after the load): a strobe switched on at dusk keeps the model
    e = loaded(day)
    for i in range(31):
        e.learn(_fake_result(i), light="day")
    assert not e.set_aside_other_light("night-strobe") and e.first_sent


def test_a_pipeline_booting_at_night_with_a_day_model_learns_afresh_with_the_boot_check(
        boot_frames, caplog):
    """The pipeline, on the person-at-boot frames: a day model loaded, the next frame lit by
    the strobe (relabelled): the model is set aside with a log line and the boot check runs on
    that frame, so the person ahead is held and kept out of the first update."""
    pipe, _ = _run(boot_frames[:1], boot_guard=True, pad_left=True)
    state = pipe.novelty.export_state()
    pipe.close()
    assert state["light"] == "day"
    st, veh, truth = boot_frames[1]
    for light, set_aside in (("day", False), ("night-strobe", True)):
        o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", boot_guard=True,
                                pad_left=True)
        pipe = StereoNoveltyPipeline(o, background=False)
        try:
            pipe.novelty.import_state(state)
            frame = dataclasses.replace(st, illumination=light)
            caplog.clear()
            with caplog.at_level(logging.WARNING):
                det = pipe.process(SensorInputs(stamp_ns=frame.stamp_ns, stereo=frame,
                                                vehicle=veh))
            said = "learnt by day and the strobe lights these frames" in caplog.text
            assert said == set_aside, caplog.text
            assert (det.debug["boot"] is not None) == set_aside
            if set_aside:
                assert det.debug["boot"]["candidates"] >= 1
                assert _near(det.points_xy, truth[0])
                assert pipe.novelty.light == "night-strobe"   # its first update's
        finally:
            pipe.close()


def test_a_tie_of_lights_goes_to_the_newer():
    d = _detector(update_every_frames=1)
    for i, light in enumerate(["day"] * 10 + ["night-strobe"] * 10):
        d.learn(_fake_result(i), light=light)
    assert d.light == "night-strobe"
    d.learn(_fake_result(50), light="day")    # the oldest day fell out: 10 and 10, day newer
    assert d.light == "day"


# ---- one model per light (thirty-first session) ---------------------------------------------
def _lit(light, n=5, seed=0):
    d = _detector(update_every_frames=1)
    for i in range(n):
        d.learn(_fake_result(seed + i), light=light)
    return d


def test_a_day_model_met_by_the_strobe_gives_way_to_the_kept_night_model():
    day, night = _lit("day").export_state(), _lit("night-strobe", n=7, seed=50).export_state()
    e = _detector(update_every_frames=1)
    e.import_state(day)
    e.keep_night_model(night)
    assert e.set_aside_other_light("day") is None              # by day: the day model stays
    assert e.model.size == len(day["w"])
    assert e.set_aside_other_light("night-strobe") == "night model"
    assert e.model.size == len(night["w"]) and e.first_sent and e.light == "night-strobe"
    x, _w, _u = e.model.state()
    assert np.allclose(np.sort(x, axis=0), np.sort(night["x"], axis=0))
    assert e.set_aside_other_light("night-strobe") is None     # once: a night model stays
    # nothing kept: set aside for an empty model, as before
    f = _detector(update_every_frames=1)
    f.import_state(day)
    assert f.set_aside_other_light("night-strobe") == "empty" and f.model.empty
    # only a strobe-lit model of this detector's settings is kept; nothing kept otherwise
    g = _detector(update_every_frames=1)
    g.import_state(day)
    with pytest.raises(ValueError, match="day light, not night-strobe"):
        g.keep_night_model(day)
    with pytest.raises(ValueError, match="other settings"):
        g.keep_night_model({**night, "fingerprint": "x"})
    assert g.set_aside_other_light("night-strobe") == "empty"


def test_the_state_directory_keeps_the_night_model_through_a_day_save(tmp_path, caplog):
    env = {"STATE_DIRECTORY": str(tmp_path)}
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="auto", update_every_frames=1)
    latest = tmp_path / "novelty-stereo-novelty.npz"
    night_file = tmp_path / "novelty-stereo-novelty.night-strobe.npz"
    assert novelty_store.light_path(latest, "night-strobe") == night_file

    def pipe_lit(light, n, seed):
        p = StereoNoveltyPipeline(o, background=False)
        for i in range(n):
            p.novelty.learn(_fake_result(seed + i), light=light)
        return p
    p = pipe_lit("night-strobe", 7, 50)             # a night's work: both files
    assert novelty_store.save_from([p], env) == [str(latest), str(night_file)]
    assert novelty_store.read(night_file)["light"] == "night-strobe"
    q = pipe_lit("day", 5, 0)                        # the next day's: the latest only
    novelty_store.save_from([q], env)
    assert novelty_store.read(latest)["light"] == "day"
    assert novelty_store.read(night_file)["light"] == "night-strobe"
    # booting: the day model is loaded, the night one kept for a strobe-lit boot
    r = StereoNoveltyPipeline(o, background=False)
    with caplog.at_level(logging.INFO, "fieldguard.novelty"):
        assert novelty_store.load_into([r], env) == [str(latest)]
    assert "kept for a strobe-lit boot" in caplog.text
    assert r.novelty.loaded_light == "day" and r.novelty.model.size == q.novelty.model.size
    assert r.novelty.set_aside_other_light("night-strobe") == "night model"
    assert r.novelty.model.size == p.novelty.model.size
    # a damaged night file: said, not kept; the strobe-lit boot learns afresh, as before
    night_file.write_bytes(b"not a model")
    s = StereoNoveltyPipeline(o, background=False)
    caplog.clear()
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.load_into([s], env) == [str(latest)]
    assert f"{night_file} unreadable" in caplog.text
    assert "not kept for a strobe-lit boot" in caplog.text and "empty model" not in caplog.text
    assert s.novelty.set_aside_other_light("night-strobe") == "empty"
    # the night file cannot be written (a directory in its place): said; the latest is saved
    night_file.unlink()
    night_file.mkdir()
    caplog.clear()
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        assert novelty_store.save_from([p], env) == [str(latest)]
    assert f"{night_file} not saved" in caplog.text
    assert not list(tmp_path.glob("*.tmp"))                 # nothing half-written left
    assert novelty_store.read(latest)["light"] == "night-strobe"
    for x in (p, q, r, s):
        x.close()


def test_a_pipeline_booting_at_night_with_a_day_model_swaps_in_the_night_model(
        boot_frames, tmp_path, caplog):
    """The pipeline, on the person-at-boot frames relabelled strobe-lit: a day model loaded
    from the state directory and a night model beside it: the night model is used (a log
    line), as a loaded model is (no boot pass: it is no young model)."""
    pipe, _ = _run(boot_frames[:1], boot_guard=True, pad_left=True)
    day = pipe.novelty.export_state()
    pipe.close()
    night = {**day, "light": "night-strobe", "x": day["x"][::2], "w": day["w"][::2]}
    latest = tmp_path / "m.npz"
    novelty_store.save(latest, day)
    novelty_store.save(novelty_store.light_path(latest, "night-strobe"), night)
    st, veh, _truth = boot_frames[1]
    o = dataclasses.replace(StereoNoveltyConfig(), model_state=str(latest), boot_guard=True,
                            pad_left=True)
    pipe = StereoNoveltyPipeline(o, background=False)
    try:
        assert novelty_store.load_into([pipe]) == [str(latest)]
        frame = dataclasses.replace(st, illumination="night-strobe")
        with caplog.at_level(logging.WARNING):
            det = pipe.process(SensorInputs(stamp_ns=frame.stamp_ns, stereo=frame, vehicle=veh))
        assert "set aside for the strobe-lit model saved beside it" in caplog.text
        assert det.debug["boot"] is None
        assert pipe.novelty.loaded_light == "night-strobe"
        assert pipe.novelty.model.size == len(night["w"])
    finally:
        pipe.close()
