"""drivers/sim scenes drawn from distributions: the campaign API, reproducibility per seed,
variation across seeds, walkers, terrain with pitch and roll following the ground."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim import SimField
from drivers.sim.scenes import COVERAGE_LANES, SCENE_KINDS, SCENES, build_scene
from hal.types import GateState

COVERAGE = ("stubble-coverage", "stubble-coverage-night", "greenhouse-coverage")


def _sig(sc):
    w = sc.world
    return (repr(sc.params), [(o.id, o.cls, o.shape, o.placement, o.pose, round(o.x, 6),
                               round(o.y, 6), o.colour) for o in w.obstacles],
            w.waves.tobytes(), w.banks.tobytes())


def test_kinds_are_listed_with_descriptions_and_old_names_still_work():
    assert SCENES is SCENE_KINDS
    assert set(SCENE_KINDS) >= {"stubble-day", "stubble-night", "greenhouse", "stubble-empty",
                                "stubble-lookalike", "stubble-coverage-classic", *COVERAGE}
    assert all(isinstance(v, str) and len(v) > 20 for v in SCENE_KINDS.values())
    with pytest.raises(ValueError, match="greenhouse-coverage"):
        build_scene("moon-base", 1)


@pytest.mark.parametrize("kind", COVERAGE)
def test_same_seed_same_scene_other_seed_differs(kind):
    assert _sig(build_scene(kind, 7)) == _sig(build_scene(kind, 7))
    assert _sig(build_scene(kind, 7)) != _sig(build_scene(kind, 8))


def test_day_and_night_coverage_share_the_field_and_obstacles():
    d, n = build_scene("stubble-coverage", 3), build_scene("stubble-coverage-night", 3)
    assert _sig(d)[1:] == _sig(n)[1:]
    assert d.illumination == "day" and n.illumination == "night-strobe"
    assert d.sun is not None and n.sun is None


def test_the_distributions_vary_with_the_seed():
    seeds = range(20)
    scs = [build_scene("stubble-coverage", s) for s in seeds]
    for key, lo, hi in (("row_spacing_m", 0.5, 1.0), ("stubble_height", 0.5, 1.4),
                        ("sun_elevation_deg", 6.0, 70.0), ("undulation_m", 0.05, 0.45)):
        v = np.array([sc.params[key] for sc in scs])
        assert v.min() >= lo and v.max() <= hi
        assert np.ptp(v) > 0.4 * (hi - lo), (key, v)          # the range is used
    assert len({sc.params["straw_bgr"] for sc in scs}) == 20
    assert any(sc.params["cloud"] == 0 for sc in scs) and any(sc.params["cloud"] > 0.5 for sc in scs)
    assert any(sc.params["dusk"] > 0 for sc in scs)
    assert any(len(sc.world.banks) == 0 for sc in scs) and any(len(sc.world.banks) >= 2 for sc in scs)
    obs = [o for sc in scs for o in sc.obstacles]
    classes = {o.cls for o in obs}
    assert classes >= {"person", "person-crouching", "person-lying", "drum", "crate", "vehicle"}
    assert classes & {"dog", "sheep", "cattle", "kangaroo"}
    assert {o.placement for o in obs} == {"in-path", "beside", "between-lanes", "headland",
                                          "crossing"}
    assert {o.tone for o in obs if o.cls.startswith("person")} >= {"hi-vis", "field-coloured"}
    heights = [o.height_m for o in obs if o.cls == "person"]
    assert min(heights) < 1.6 and max(heights) > 1.85
    g = [build_scene("greenhouse-coverage", s) for s in seeds]
    assert np.ptp([sc.params["path_half_width_m"] for sc in g]) > 0.1
    assert {o.placement for sc in g for o in sc.obstacles} >= {"in-path", "beside", "headland"}


def test_route_lanes_headlands_and_in_path_obstacles():
    sc = build_scene("stubble-coverage", 5)
    assert sc.route is sc.path and sc.route_s[0] == 0.0
    assert sc.route_length_m == pytest.approx(sc.route_s[-1])
    assert len(sc.lanes) == 14
    # a lane's middle is "lane", a turn is "headland", lane ends count as headland
    a, b = sc.lanes[3]
    assert sc.zone_at((a + b) / 2) == "lane" and sc.lane_at((a + b) / 2) == 3
    assert sc.zone_at(b + 1.0) == "headland" and sc.lane_at(b + 1.0) is None
    assert sc.zone_at(a + 0.5 * sc.headland_m) == "headland"
    assert sc.route_s_of(*sc.path[100]) == pytest.approx(sc.route_s[100], abs=1e-6)
    ids = set(sc.in_path_ids())
    for o in sc.obstacles:
        if o.placement in ("in-path", "crossing"):
            assert o.id in ids, o
        if o.placement in ("beside", "between-lanes"):
            assert o.id not in ids, o
        assert sc.obstacle_class(o.id) == o.cls
    # headland obstacles are where the route is in a headland
    for o in sc.obstacles:
        if o.placement == "headland":
            assert sc.zone_of_point(o.x, o.y) == "headland"
    # the vehicle hits exactly... at least one in-path obstacle if it never stops
    # 70 s: it hits c1 at 43.8 s and c2 at 66.5 s, and nothing more until 120 s (the 1200
    # steps of before)
    f = SimField("stubble-coverage", 5, sensors=())
    for _ in range(700):
        f.step(0.1, GateState.CLEAR)
    assert set(f.stats()["obstacles_hit"]) <= ids and f.stats()["collisions"] >= 1


def _walker_field(kind="stubble-coverage"):
    for seed in range(50):
        sc = build_scene(kind, seed)
        w = [o for o in sc.obstacles if o.moving]
        if w:
            return seed, w[0]
    raise AssertionError("no walker in 50 seeds")


def test_walkers_walk_when_the_vehicle_comes_and_truth_follows_them():
    seed, w0 = _walker_field()
    f = SimField("stubble-coverage", seed, sensors=("stereo",), stereo_scale=0.25)
    k = next(i for i, o in enumerate(f.world.obstacles) if o.id == w0.id)
    o = f.world.obstacles[k]
    x0, y0 = o.x, o.y
    f.vehicle.s = o.walk_trigger_s - 5.0
    f.step(0.1)
    assert (o.x, o.y) == (x0, y0)                              # not yet
    f.vehicle.s = o.walk_trigger_s
    f.step(0.1)
    t0 = f.world.time_s
    for _ in range(20):
        f.vehicle.speed = 0.0                                  # hold the vehicle: watch it walk
        f.step(0.1, GateState.STOP)
    dt = f.world.time_s - t0
    assert o.x - x0 == pytest.approx(o.vx_mps * dt, abs=1e-6)
    assert o.y - y0 == pytest.approx(o.vy_mps * dt, abs=1e-6)
    assert o.z0 == pytest.approx(float(f.world.ground(np.float32(o.x), np.float32(o.y))), abs=1e-6)
    # the vehicle's footprint test moved with it
    fp = f.vehicle._footprints[k]
    assert np.hypot(fp[:, 0].mean() - o.x, fp[:, 1].mean() - o.y) < 0.05
    # truth: where it is now, with its velocity in the vehicle frame
    t = [d for d in f.truth() if d["id"] == o.id]
    if t:
        Rwv, O = f.vehicle.world_from_vehicle()
        p = Rwv.T @ (np.array([o.x, o.y, o.z0]) - O)
        assert t[0]["x_m"] == pytest.approx(p[0], abs=1e-3)
        assert t[0]["y_m"] == pytest.approx(p[1], abs=1e-3)
        yaw = f.vehicle.pose()[2]
        assert math.hypot(t[0]["vx_mps"], t[0]["vy_mps"]) == pytest.approx(
            math.hypot(o.vx_mps, o.vy_mps), abs=2e-3)
        assert t[0]["vx_mps"] == pytest.approx(o.vx_mps * math.cos(yaw) + o.vy_mps * math.sin(yaw),
                                               abs=2e-3)
    # once across it stands still
    for _ in range(int(o.walk_time_s * 10) + 5):
        f.step(0.1, GateState.STOP)
    assert o.velocity_now(f.world.time_s) == (0.0, 0.0)
    assert math.hypot(o.x - o.x_start, o.y - o.y_start) == pytest.approx(
        math.hypot(o.vx_mps, o.vy_mps) * o.walk_time_s, rel=1e-6)


def test_pitch_and_roll_follow_the_ground_over_a_contour_bank():
    def steep_bank(s):
        for b in build_scene("stubble-coverage", s).world.banks:
            nx, ny, off, hb, sg = (float(v) for v in b)
            if 10.0 < off / nx < 240.0 and hb * abs(nx) / sg > 0.12:
                return b
        return None
    seed = next(s for s in range(100) if steep_bank(s) is not None)
    nx, ny, off, hb, sg = steep_bank(seed)
    f = SimField("stubble-coverage", seed, sensors=())
    sc = f.scene
    sc.bounce_deg = 0.0                                        # the ground alone
    xb = float(off / nx)                                       # where it crosses lane 0 (y = 0)
    pitches = []
    for s in np.arange(max(xb - 8.0, 1.0), min(xb + 8.0, 249.0), 0.25):
        f.vehicle.s = float(s)
        roll, pitch, z = f.vehicle.attitude()
        x, y, yaw = f.vehicle.pose()
        wb, tr = sc.wheelbase_m, sc.track_m / 2
        g = lambda px, py: float(sc.world.ground(np.float32(px), np.float32(py)))  # noqa: E731
        front = (g(x + wb, tr) + g(x + wb, -tr)) / 2
        rear = (g(x, tr) + g(x, -tr)) / 2
        assert pitch == pytest.approx(math.atan2(rear - front, wb), abs=1e-6)
        left, right = (g(x, tr) + g(x + wb, tr)) / 2, (g(x, -tr) + g(x + wb, -tr)) / 2
        assert roll == pytest.approx(math.atan2(left - right, 2 * tr), abs=1e-6)
        pitches.append(pitch)
        st = f.vehicle_state(0, 0)
        assert (st.pitch_rad, st.roll_rad) == (pitch, roll)
    # climbing the bank: nose up (negative pitch), then nose down
    assert min(pitches) < -math.radians(2.0) and max(pitches) > math.radians(2.0)


def test_greenhouse_placements_agree_with_the_geometry():
    for seed in range(10):
        sc = build_scene("greenhouse-coverage", seed)
        ids = set(sc.in_path_ids())
        for o in sc.obstacles:
            if o.placement in ("in-path", "crossing"):
                assert o.id in ids
            elif o.placement == "beside":
                assert o.id not in ids


def _bush_penetration(sc) -> float:
    """How far the vehicle's footprint, driven along the whole route, reaches into a bush row
    (rows of the greenhouse world: |y - row centre| < 0.5 between the lanes, x in the rows'
    range); <= 0 when it never does."""
    w = sc.world
    period, (x0, x1) = w.bush_period_m, w.bush_x_range
    path = sc.path
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
    ss = np.arange(0.0, s[-1], 0.05)
    px, py = np.interp(ss, s, path[:, 0]), np.interp(ss, s, path[:, 1])
    yaw = np.arctan2(np.gradient(py), np.gradient(px))[:, None]
    rear, length, width = sc.footprint
    u, v = np.meshgrid(np.linspace(-rear, length - rear, 13), np.linspace(-width / 2, width / 2, 9))
    u, v = u.ravel()[None], v.ravel()[None]
    x = px[:, None] + u * np.cos(yaw) - v * np.sin(yaw)
    y = py[:, None] + u * np.sin(yaw) + v * np.cos(yaw)
    centre = (np.floor(y / period) + 0.5) * period          # the nearest row centre below
    rows = (x > x0) & (x < x1) & (centre > 0) & (centre < path[:, 1].max())
    return float(np.where(rows, 0.5 - np.abs(y - centre), -1.0).max())


def test_greenhouse_u_turns_keep_the_vehicle_out_of_the_bush_rows():
    """The passes run on 1.2 m past the rows' ends before turning: turning at the row's end,
    the sprayer's front swept 18-26 cm into the next row late in every U-turn (seeds 1-3),
    and the box's stops there for the bush were scored as false stops."""
    for seed in (1, 2, 3):
        sc = build_scene("greenhouse-coverage", seed)
        assert _bush_penetration(sc) <= 0.0, seed
        # the lanes (with their run-outs) are where the route is straight
        for s0, s1 in sc.lanes:
            assert s1 - s0 >= sc.params["lane_length_m"] + 2 * 1.2 - 1.0


def test_thin_scene_is_the_coverage_field_with_thin_short_things_in_the_path():
    """stubble-thin: the stubble-coverage field of the seed (the stalk rule's false stops are
    tufts of that field) with stakes, children and dogs facing the vehicle in the path: what
    a rule against tufts must not drop."""
    c, t, n = (build_scene(k, 5) for k in ("stubble-coverage", "stubble-thin",
                                            "stubble-thin-night"))
    assert {k: v for k, v in t.params.items() if k not in ("obstacles", "walkers")} == \
        {k: v for k, v in c.params.items() if k not in ("obstacles", "walkers")}
    assert t.world.waves.tobytes() == c.world.waves.tobytes()
    assert t.world.banks.tobytes() == c.world.banks.tobytes()
    assert _sig(t)[1:] == _sig(n)[1:] and n.illumination == "night-strobe"
    assert t.illumination == "day" and _sig(t) == _sig(build_scene("stubble-thin", 5))
    obs = [o for s in range(6) for o in build_scene("stubble-thin", s).obstacles]
    assert {o.cls for o in obs} == {"stake", "child", "dog-head-on"}
    assert all(o.placement == "in-path" and not o.moving for o in obs)
    across = {"stake": (0.08, 0.14), "child": (0.25, 0.32), "dog-head-on": (0.25, 0.35)}
    tall = {"stake": (0.6, 1.3), "child": (0.95, 1.25), "dog-head-on": (0.45, 0.7)}
    for o in obs:
        assert across[o.cls][0] <= o.width_m <= across[o.cls][1], (o.cls, o.width_m)
        assert tall[o.cls][0] <= o.height_m <= tall[o.cls][1], (o.cls, o.height_m)
    for o in obs:
        if o.cls == "dog-head-on":      # its length along the lane: narrow to the vehicle
            assert abs(math.cos(math.radians(o.yaw_deg))) > math.cos(math.radians(16))
    assert set(t.in_path_ids()) == {o.id for o in t.obstacles}


def test_crossing_scene_is_the_coverage_field_with_only_walkers_crossing_each_lane():
    """stubble-crossing: the stubble-coverage field of the seed with 2-3 walkers a lane, drawn
    as stubble-coverage's walkers (what a decision on movers is measured on)."""
    c, x, n = (build_scene(k, 3) for k in ("stubble-coverage", "stubble-crossing",
                                            "stubble-crossing-night"))
    assert {k: v for k, v in x.params.items() if k not in ("obstacles", "walkers")} == \
        {k: v for k, v in c.params.items() if k not in ("obstacles", "walkers")}
    assert x.world.waves.tobytes() == c.world.waves.tobytes()
    assert _sig(x)[1:] == _sig(n)[1:] and n.illumination == "night-strobe"
    assert x.illumination == "day" and _sig(x) == _sig(build_scene("stubble-crossing", 3))
    length, spacing, passes = COVERAGE_LANES
    for seed in range(4):
        sc = build_scene("stubble-crossing", seed)
        obs = sc.obstacles
        assert sc.params["walkers"] == len(obs)
        assert all(o.moving and o.placement == "crossing" for o in obs)
        assert all(o.cls == "person" or o.tone == "animal" for o in obs)
        for o in obs:
            assert 0.6 - 1e-9 <= math.hypot(o.vx_mps, o.vy_mps) <= 3.0 + 1e-9
        per_lane = {}
        for o in obs:
            x_cross = o.x_start + o.vx_mps * o.walk_time_s / 2
            y_cross = o.y_start + o.vy_mps * o.walk_time_s / 2
            lane = int(round(y_cross / spacing))
            assert abs(y_cross - lane * spacing) < 1e-6            # mid-walk on its lane
            assert 4.0 - 1e-6 <= abs(o.y_start - y_cross) <= 9.0 + 1e-6   # from 4-9 m aside
            per_lane.setdefault(lane, []).append(x_cross)
        assert set(per_lane) == set(range(passes))
        for xs in per_lane.values():
            xs = sorted(xs)
            assert 2 <= len(xs) <= 3 and all(b - a >= 40.0 - 1e-6 for a, b in zip(xs, xs[1:]))


def test_greenhouse_crossing_is_the_coverage_house_with_people_crossing_each_path():
    """greenhouse-crossing: the greenhouse-coverage house of the seed with only people stepping
    through the bush row across the path, 1-2 a path (where the RGB-D box's movers are
    measured; the coverage drives met too few walkers to say anything)."""
    c, x = build_scene("greenhouse-coverage", 2), build_scene("greenhouse-crossing", 2)
    assert {k: v for k, v in x.params.items() if k not in ("obstacles", "walkers")} == \
        {k: v for k, v in c.params.items() if k not in ("obstacles", "walkers")}
    assert x.world.waves.tobytes() == c.world.waves.tobytes() and x.illumination == "greenhouse"
    assert x.path.tobytes() == c.path.tobytes()
    assert _sig(x) == _sig(build_scene("greenhouse-crossing", 2))
    for seed in range(4):
        sc = build_scene("greenhouse-crossing", seed)
        period, passes = sc.world.bush_period_m, sc.params["paths"]
        obs = sc.obstacles
        assert sc.params["walkers"] == len(obs)
        assert all(o.moving and o.placement == "crossing" and o.cls == "person" for o in obs)
        per_path = {}
        for o in obs:
            assert 0.6 - 1e-9 <= math.hypot(o.vx_mps, o.vy_mps) <= 1.6 + 1e-9
            x_cross = o.x_start + o.vx_mps * o.walk_time_s / 2
            y_cross = o.y_start + o.vy_mps * o.walk_time_s / 2
            path = int(round(y_cross / period))
            assert abs(y_cross - path * period) < 1e-6                  # mid-walk on its path
            assert 0.9 - 1e-6 <= abs(o.y_start - y_cross) <= 1.4 + 1e-6
            per_path.setdefault(path, []).append(x_cross)
        assert set(per_path) == set(range(passes))
        for xs in per_path.values():
            xs = sorted(xs)
            assert 1 <= len(xs) <= 2 and all(b - a >= 10.0 - 1e-6 for a, b in zip(xs, xs[1:]))


def test_a_thin_stake_is_drawn_by_the_stereo_camera_at_8_m():
    """The renderer marches in steps of ~0.6 % of the range: the scene's thinnest stake (8 cm)
    must still be a solid column of pixels where the stalk rule looks (8 m)."""
    f = SimField("stubble-thin", 5, sensors=("stereo",), stereo_scale=0.5)
    sc = f.scene
    stake = min((o for o in sc.obstacles if o.cls == "stake"), key=lambda o: o.width_m)
    f.vehicle.s = sc.route_s_of(stake.x, stake.y) - 8.0 - 1.6   # the camera ~8 m from it
    from drivers.sim.render import render_view
    from drivers.sim.world import MAT_OBSTACLE
    cal = f.stereo_calibration
    c, r, _ = f._sensor_pose(cal.mount)
    v = render_view(f.world, f.lighting, c, r, cal.camera, t_max=80.0, rel_step=0.0057)
    k = sc.obstacles.index(stake)
    cols = np.flatnonzero((v.mat == MAT_OBSTACLE + k).any(axis=0))
    rows = np.flatnonzero((v.mat == MAT_OBSTACLE + k).any(axis=1))
    assert len(cols) and len(rows)
    # its width in pixels at its range, and every row of it drawn over that width
    rng_m = float(np.median(v.zdepth[v.mat == MAT_OBSTACLE + k]))
    want = stake.width_m * cal.camera.fx / rng_m
    assert 7.0 < rng_m < 10.0
    assert len(cols) >= 0.7 * want
    hit_rows = (v.mat[rows.min():rows.max() + 1] == MAT_OBSTACLE + k).any(axis=1)
    assert hit_rows.mean() > 0.9


def test_no_greenhouse_obstacle_under_the_vehicle_at_its_start():
    """Until 2026-12 an end-bay obstacle could be drawn where the sprayer stands at its start
    (11 of 300 seeds): a collision at 0.2 s no box could avoid. Such a one is drawn and left
    out; every other draw and id stays as it was."""
    from drivers.sim.scenes import build_scene
    from drivers.sim.vehicle import Vehicle
    for seed in [58, 92, 152, 1011, 1014, 1025, 1026, 1060, 1072, 1075, 1081] + list(range(12)):
        sc = build_scene("greenhouse-coverage", seed)
        v = Vehicle(sc, seed)
        assert not any(v._overlaps(k, 0.0) for k in range(len(sc.world.obstacles))), seed
    ids = [o.id for o in build_scene("greenhouse-coverage", 1026).world.obstacles]
    assert ids == ["g1", "g2", "g3", "g4", "g5"]          # g6 (under the vehicle) left out
    o = [o for o in build_scene("greenhouse-coverage", 1065).world.obstacles if o.id == "g7"]
    assert o and abs(o[0].y - 0.77) < 0.01              # beside the vehicle at its start: kept


def test_boot_scene_is_the_coverage_field_and_obstacles_with_a_person_ahead_at_start():
    """stubble-boot: the stubble-coverage field and obstacles of the seed, and one person (an
    adult standing, or a small child) in the path 5-15 m ahead of the vehicle's origin when the
    box starts (issue #14: "booted with a person 5-15 m ahead in the path"); the night kind is
    the same field, obstacles and person under the strobe."""
    c, b, n = (build_scene(k, 4) for k in ("stubble-coverage", "stubble-boot",
                                            "stubble-boot-night"))
    assert {k: v for k, v in b.params.items() if k not in ("obstacles", "walkers")} == \
        {k: v for k, v in c.params.items() if k not in ("obstacles", "walkers")}
    assert b.world.waves.tobytes() == c.world.waves.tobytes()
    assert _sig(b)[1:] == _sig(n)[1:] and n.illumination == "night-strobe"
    assert b.illumination == "day" and _sig(b) == _sig(build_scene("stubble-boot", 4))
    # the coverage obstacles as they are, and one more
    assert _sig(b)[1][:-1] == _sig(c)[1]
    start = b.path[0]
    classes = set()
    for seed in range(12):
        sc = build_scene("stubble-boot", seed)
        boot = [o for o in sc.obstacles if o.placement == "at-boot"]
        assert len(boot) == 1
        o = boot[0]
        classes.add(o.cls)
        assert o.cls in ("person", "child") and o.pose == "standing" and not o.moving
        assert 5.0 <= o.x - start[0] <= 15.0 and abs(o.y - start[1]) <= 0.6
        in_path = set(sc.in_path_ids())
        assert o.id in in_path
        # nothing else in the first lane's path in its first 60 m: the boot person is what
        # the vehicle meets there
        others = [q for q in sc.obstacles if q is not o and q.id in in_path
                  and 0 <= q.x <= 60 and abs(q.y) < 1.5]
        assert not others, [(q.id, q.x, q.y) for q in others]
    assert classes == {"person", "child"}
    # the safety driver waits 30 s at the stop for the person before steering round (the
    # model updates with the person in view, still); the other kinds keep 5 s
    assert b.detour_after_s == n.detour_after_s == 30.0 and c.detour_after_s == 5.0
    fb = SimField("stubble-boot", 4, sensors=("laser",))
    fc = SimField("stubble-coverage", 4, sensors=("laser",))
    assert fb.vehicle.detour_after_s == 30.0 and fc.vehicle.detour_after_s == 5.0
    # the vehicle stands when the box starts (the other kinds start at cruise)
    assert fb.vehicle.speed == 0.0 and fc.vehicle.speed == 2.5
