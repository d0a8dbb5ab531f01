"""Obstacle candidates from obstacle points (appliance/perception/candidates.py)."""
import numpy as np
import pytest

from appliance.perception.candidates import cluster_candidates, low_clusters


def _blob(rng, x, y, n, r=0.2, h=(0.5, 1.8)):
    return (np.stack([x + rng.uniform(-r, r, n), y + rng.uniform(-r, r, n)], axis=1),
            rng.uniform(*h, n))


def test_two_objects_two_candidates_with_their_attributes():
    rng = np.random.default_rng(0)
    a, ha = _blob(rng, 10.0, 0.0, 200)
    b, hb = _blob(rng, 15.0, 3.0, 40, r=0.1, h=(1.6, 2.0))      # floating: no contact
    xy, h = np.concatenate([a, b]), np.concatenate([ha, hb])
    conf = np.concatenate([np.full(200, 0.9), np.full(40, 0.5)])
    cue = np.concatenate([np.zeros(200, bool), np.ones(40, bool)])
    c = cluster_candidates(xy, h, conf, {"novelty": cue}, pipeline="stereo")
    assert len(c) == 2
    big, small = c
    assert big.points == 200 and small.points == 40
    assert abs(big.x_m - 10.0) < 0.05 and abs(big.y_m) < 0.05
    assert 0.3 < big.length_m <= 0.41 and 0.3 < big.width_m <= 0.41
    assert 1.6 < big.height_m < 1.8
    assert big.ground_contact and not small.ground_contact
    assert big.sources == ("geometry",) and small.sources == ("geometry", "novelty")
    assert big.confidence > small.confidence
    assert 0.85 < big.confidence <= 0.9
    assert big.pipeline == "stereo"


def test_gap_of_one_cell_joins_and_two_cells_split():
    xy = np.array([[5.0, 0.0], [5.0, 0.05], [5.0, 0.1],
                   [5.0, 0.45], [5.0, 0.5], [5.0, 0.55],     # 1 empty 0.2 m cell between
                   [5.0, 1.5], [5.0, 1.55], [5.0, 1.6]])     # far apart
    c = cluster_candidates(xy, np.full(9, 1.0), min_points=3)
    assert sorted(cd.points for cd in c) == [3, 6]


def test_stray_points_are_no_candidate_and_bad_values_are_ignored():
    xy = np.array([[5.0, 0.0], [np.nan, 1.0], [np.inf, 0.0], [8.0, 2.0]])
    assert cluster_candidates(xy, np.ones(4)) == ()
    assert cluster_candidates(np.zeros((0, 2))) == ()


def test_confidence_grows_with_support():
    rng = np.random.default_rng(1)
    few, hf = _blob(rng, 5, 0, 4)
    many, hm = _blob(rng, 5, 0, 80)
    assert cluster_candidates(few, hf)[0].confidence < cluster_candidates(many, hm)[0].confidence


def _reference_groups(xy, idx, cell_m):
    """Plain clustering of points ``idx`` of ``xy``: a dict of cells, a flood fill over the
    dilated occupancy; the point indices of each cluster."""
    cells = {}
    for i in idx:
        cells.setdefault(tuple(np.floor(xy[i] / cell_m).astype(int)), []).append(i)
    # components of the cells where a gap of one empty cell still joins (the 3x3 dilation)
    grown = {(a + da, b + db) for a, b in cells for da in (-1, 0, 1) for db in (-1, 0, 1)}
    comp, k = {}, 0
    for c0 in sorted(grown):
        if c0 in comp:
            continue
        k += 1
        stack = [c0]
        comp[c0] = k
        while stack:
            a, b = stack.pop()
            for da in (-1, 0, 1):
                for db in (-1, 0, 1):
                    n = (a + da, b + db)
                    if n in grown and n not in comp:
                        comp[n] = k
                        stack.append(n)
    groups = {}
    for c, pts in cells.items():
        groups.setdefault(comp[c], []).extend(pts)
    return list(groups.values())


def _reference_candidates(xy, h, conf, flags, cell_m=0.2, min_points=3, contact_m=0.8,
                          max_range_m=60.0):
    """The module's rules written plainly (a dict of cells, a flood fill over the dilated
    occupancy, each cluster's heights sorted): what the vectorised code must give."""
    xy = np.asarray(xy, float)
    ok = np.isfinite(xy).all(1) & (np.abs(xy) <= max_range_m).all(1)
    idx = np.flatnonzero(ok)
    if len(idx) < min_points:
        return []
    groups = {k: g for k, g in enumerate(_reference_groups(xy, idx, cell_m))}
    out = []
    for pts in groups.values():
        pts = np.array(sorted(pts))
        n = len(pts)
        if n < min_points:
            continue
        p = xy[pts]
        hs = np.sort(h[pts])
        c = 1.0 if conf is None else float(np.clip(conf[pts], 0, 1).mean())
        src = ("geometry",) + tuple(name for name, f in flags.items() if f[pts].sum() >= 0.2 * n)
        out.append(dict(points=n, x=(p[:, 0].min() + p[:, 0].max()) / 2,
                        y=(p[:, 1].min() + p[:, 1].max()) / 2,
                        length=max(np.ptp(p[:, 0]), cell_m), width=max(np.ptp(p[:, 1]), cell_m),
                        height=hs[int(round(0.95 * (n - 1)))],
                        contact=bool(hs[int(round(0.05 * (n - 1)))] <= contact_m),
                        conf=c * (1 - np.exp(-n / 10.0)), sources=src))
    return out


@pytest.mark.parametrize("seed", range(12))
def test_clusters_agree_with_a_plain_reference(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 1500))
    xy = np.concatenate([rng.normal(rng.uniform(-8, 8, 2), rng.uniform(0.1, 3), (n, 2)),
                         rng.uniform(-70, 70, (5, 2))])       # some beyond max_range_m
    xy[rng.integers(0, len(xy), 3)] = np.nan
    h = np.round(rng.uniform(-0.3, 2.0, len(xy)), 1)          # ties between heights
    conf = rng.uniform(0, 1.2, len(xy)) if seed % 2 else None
    flags = {"novelty": rng.random(len(xy)) < 0.3}
    got = cluster_candidates(xy, h, conf, flags, min_points=3, max_candidates=10_000)
    want = _reference_candidates(xy, h, conf, flags)
    assert len(got) == len(want) > 0
    key = lambda d: (d["points"], d["x"], d["y"])            # noqa: E731
    for c, w in zip(sorted(got, key=lambda c: (c.points, c.x_m, c.y_m)), sorted(want, key=key)):
        assert (c.points, c.sources, c.ground_contact) == (w["points"], w["sources"], w["contact"])
        assert c.height_m == w["height"]
        assert np.allclose([c.x_m, c.y_m, c.length_m, c.width_m], [w["x"], w["y"], w["length"],
                                                                   w["width"]], rtol=0, atol=1e-12)
        assert abs(c.confidence - w["conf"]) <= 5e-5          # (rounded to 4 places)


@pytest.mark.parametrize("seed", range(6))
def test_low_clusters_are_the_clusters_whose_top_is_below_the_limit(seed):
    """low_clusters marks exactly the points of the clusters (whatever their size) whose 95th
    percentile height -- a candidate's height_m -- is below the limit: against the plain
    reference clustering."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(50, 800))
    xy = np.concatenate([rng.normal(rng.uniform(-5, 5, 2), rng.uniform(0.1, 2), (n, 2)),
                         rng.uniform(-5, 5, (30, 2))])
    h = np.round(rng.uniform(0.0, 0.4, len(xy)), 2)
    xy[rng.integers(0, len(xy), 2)] = np.nan
    low = low_clusters(xy, h, 0.2, cell_m=0.1)
    want = np.zeros(len(xy), bool)
    for g in _reference_groups(xy, np.flatnonzero(np.isfinite(xy).all(1)), 0.1):
        hs = np.sort(h[g])
        want[g] = hs[int(round(0.95 * (len(g) - 1)))] < 0.2
    assert 0 < want.sum() < len(xy)
    assert low.tolist() == want.tolist()


def test_low_clusters_by_hand():
    # a leaf patch 8 cm tall 0.5 m beside a 0.4 m crate face: two clusters, one low
    leaf = np.array([[2.0, 0.60], [2.02, 0.62], [2.05, 0.61]])
    crate = np.array([[2.0, -0.1], [2.0, 0.0], [2.0, 0.1]])
    xy = np.concatenate([leaf, crate])
    h = np.array([0.05, 0.08, 0.07, 0.1, 0.4, 0.38])
    assert low_clusters(xy, h, 0.15).tolist() == [True] * 3 + [False] * 3
    # joined to the crate (one empty cell between them joins): one cluster, not low
    xy2 = np.concatenate([leaf - [0, 0.4], crate])
    assert not low_clusters(xy2, h, 0.15).any()
    # no limit, or nothing finite: nothing is low
    assert not low_clusters(xy, h, 0.0).any()
    assert not low_clusters(np.full((3, 2), np.nan), np.zeros(3), 0.15).any()
    assert low_clusters(np.zeros((0, 2)), np.zeros(0), 0.15).shape == (0,)


def test_laser_pipeline_gives_a_candidate_per_object():
    from appliance.perception import SensorInputs
    from appliance.perception.laser import LaserPipeline
    from hal.types import LaserGeometry, LaserScan, Mount
    geo = LaserGeometry(-45.0, 0.5, 181, 30.0, Mount(x_m=1.0, z_m=0.7))
    r = np.full(181, np.nan, np.float32)
    ang = geo.angles_rad()
    for centre, dist in ((0.0, 8.0), (20.0, 5.0)):               # two posts
        near = np.abs(np.degrees(ang) - centre) <= 1.5
        r[near] = dist
    det = LaserPipeline().process(SensorInputs(0, laser=LaserScan(0, 0, r, geo)))
    assert len(det.points_xy) == int(np.isfinite(r).sum())
    c = sorted(det.candidates, key=lambda cd: cd.x_m)
    assert len(c) == 2 and all(cd.sources == ("laser",) for cd in c)
    assert abs(c[1].x_m - 9.0) < 0.1 and abs(c[1].y_m) < 0.2
    assert abs(c[0].x_m - (1.0 + 5.0 * np.cos(np.radians(20)))) < 0.2
    assert all(cd.height_m == 0.7 and cd.ground_contact for cd in c)


def test_rgbd_pipeline_candidates_on_the_simulated_greenhouse():
    from appliance.perception import SensorInputs, make_pipeline
    from drivers.sim import SimField
    f = SimField("greenhouse", seed=1, sensors=("rgbd",))
    for _ in range(40):                                  # drive until the crate is ~3 m ahead
        s = f.render(0, 0)
        crate = [t for t in s.truth if t["class"] == "crate" and t["x_m"] < 4.0]
        if crate:
            break
        f.step(0.5)
    assert crate
    p = make_pipeline("rgbd")
    try:
        det = p.process(SensorInputs(0, rgbd=s.rgbd, vehicle=s.vehicle))
    finally:
        p.close()
    ob = crate[0]
    near = [cd for cd in det.candidates if abs(cd.x_m - ob["x_m"]) < 0.6
            and abs(cd.y_m - ob["y_m"]) < 0.6]
    assert near, (ob, det.candidates)
    cd = max(near, key=lambda c: c.points)
    assert "geometry" in cd.sources and cd.pipeline == "rgbd" and cd.ground_contact
    assert 0.15 < cd.height_m < ob["height_m"] + 0.2


def test_fused_pipeline_hands_on_every_part_s_candidates():
    from appliance.perception import SensorInputs
    from appliance.perception.fused import FusedPipeline
    from appliance.perception.laser import LaserPipeline
    from hal.types import LaserGeometry, LaserScan, Mount
    geo = LaserGeometry(-10.0, 0.5, 41, 30.0, Mount(x_m=1.0, z_m=0.7))
    r = np.full(41, np.nan, np.float32)
    r[18:23] = 6.0
    f = FusedPipeline([LaserPipeline(), LaserPipeline()])
    det = f.process(SensorInputs(0, laser=LaserScan(0, 0, r, geo)))
    assert len(det.candidates) == 2 and all(c.pipeline == "laser" for c in det.candidates)


def test_new_front_end_options_are_validated():
    from appliance.config import parse_config
    from hal.errors import ConfigError
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"], "stereo-novelty": {
        "support_min": 0.3, "pad_left": False, "boot_guard": False, "model_state": "off",
        "dark_level": 12, "ground_fit": True}}})
    from appliance.config import pipeline_options
    o = pipeline_options(cfg, "stereo-novelty")
    assert (o.support_min, o.pad_left, o.boot_guard, o.model_state, o.ground_fit) == \
        (0.3, False, False, "off", True)
    for bad in ({"support_min": 2.0}, {"dark_level": -1}, {"boot_min_points": 0}):
        with pytest.raises(ConfigError) as e:
            parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                         "stereo-novelty": bad}})
        assert next(iter(bad)) in str(e.value)


def test_new_ground_and_support_options_are_validated():
    from appliance.config import parse_config, pipeline_options
    from hal.errors import ConfigError
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"], "stereo-novelty": {
        "ground_local": True, "ground_local_cell_m": 1.0, "ground_local_percentile": 20,
        "ground_local_erode": 2, "ground_local_max_dev_m": 0.4, "support_known_min": 0.5}}})
    o = pipeline_options(cfg, "stereo-novelty")
    assert (o.ground_local, o.ground_local_cell_m, o.ground_local_percentile,
            o.ground_local_erode, o.ground_local_max_dev_m, o.support_known_min) == \
        (True, 1.0, 20, 2, 0.4, 0.5)
    for bad in ({"ground_local_cell_m": 0.0}, {"ground_local_percentile": 80},
                {"ground_local_erode": -1}, {"support_known_min": 1.5}):
        with pytest.raises(ConfigError) as e:
            parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                         "stereo-novelty": bad}})
        assert next(iter(bad)) in str(e.value)


def _support_setup():
    """A level camera 1.5 m up (640x512, f 400, baseline 0.2 m) and a disparity image: a
    standing surface 4 m ahead (rows 150-330, down to its foot) and a floating blob of the
    same disparity (rows 150-170) above a column with no disparity at all, as a mismatch on
    a strobe-lit tuft top far away whose column below was never matched."""
    from appliance.perception.ground import GroundModel
    from hal.types import Mount, PinholeCalibration, StereoCalibration
    cal = StereoCalibration(PinholeCalibration(640, 512, 400.0, 400.0, 320.0, 256.0), 0.2,
                            Mount(x_m=0.0, z_m=1.5))
    d = 400.0 * 0.2 / 4.0                                       # 20 px at 4 m
    disp = np.zeros((512, 640), np.float32)
    foot = int(256 + 400.0 * 1.5 / 4.0) + 2                     # the ground row 4 m ahead
    disp[150:foot, 100:140] = d                                 # a surface standing there
    disp[150:170, 400:440] = d                                  # floating
    px = np.array([[120.0, 160.0], [420.0, 160.0]])
    z = 4.0
    pts = np.array([[z, -(u - 320.0) * z / 400.0, 1.5 - (160.0 - 256.0) * z / 400.0]
                    for u in (120.0, 420.0)])
    return disp, px, pts, cal, GroundModel.level()


def test_support_known_min_drops_a_floating_match_over_an_unmatched_column():
    from appliance.perception.stereo import vertical_support
    disp, px, pts, cal, g = _support_setup()
    # default: unknown samples say nothing, both points pass
    assert list(vertical_support(disp, px, pts, cal, g)) == [1.0, 1.0]
    sup = vertical_support(disp, px, pts, cal, g, known_min=0.5)
    assert sup[0] == 1.0           # the standing surface keeps its support
    assert sup[1] == 0.0           # the floating match has none
