"""The tracker: candidates from points, world-frame association, evidence, confirmation."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from appliance.config import (ConfigError, GridConfig, SourceWeights, TrackingConfig,
                              parse_config)
from appliance.perception import Candidate, Detections
from appliance.tracking import Tracker, cluster_points, measurements, merge_touching
from hal.types import VehicleState

S = 10**9
DT = S // 10


def vs(speed=0.0, yaw_rate=0.0):
    return VehicleState(0, 0, speed_mps=speed, yaw_rate_radps=yaw_rate)


def blob(x, y, n=3, step=0.1):
    """An n x n patch of points (one per 0.1 m cell) centred near (x, y)."""
    o = (np.arange(n) - (n - 1) / 2) * step
    return np.array([[x + a, y + b] for a in o for b in o])


def test_clustering_joins_near_cells_and_keeps_far_apart():
    cfg = TrackingConfig(cluster_gap_m=0.3)
    # cell centres: a 3x3 patch at y -0.05..0.15, one cell at 0.55 (three empty cells = 0.3 m
    # between), one 0.5 m further off at 1.15 (four empty cells: apart), a patch far away
    pts = np.r_[blob(5.05, 0.05), blob(5.05, 0.55, n=1), blob(5.05, 1.15, n=1),
                blob(8.05, 2.05)]
    ms = cluster_points({"stereo": (pts, ("geometry",))}, GridConfig(), cfg)
    assert len(ms) == 3
    near = min(ms, key=lambda m: (m.x_m, m.y_m))
    assert near.points == 10 and near.width_m == pytest.approx(0.7, abs=1e-6)
    assert near.length_m == pytest.approx(0.3, abs=1e-6)
    assert near.sources == ("geometry",) and near.pipelines == ("stereo",)


def test_one_labelling_over_pipelines_gives_one_candidate_with_both_sources():
    cfg = TrackingConfig()
    ms = cluster_points({"laser": (blob(6.0, 0.0, n=1), ("laser",)),
                         "stereo": (blob(6.1, 0.0), ("geometry",))}, GridConfig(), cfg)
    assert len(ms) == 1 and ms[0].sources == ("laser", "geometry")
    # the laser hit one cell, stereo nine: the strengths say so
    assert ms[0].strength["laser"] < ms[0].strength["geometry"]


def test_front_end_candidates_are_used_and_merged_with_point_clusters():
    c = Candidate(x_m=6.0, y_m=0.0, length_m=0.4, width_m=0.4, height_m=1.7, points=200,
                  confidence=0.9, sources=("geometry", "novelty"), pipeline="stereo-novelty")
    dets = {"stereo-novelty": Detections(points_xy=blob(6.0, 0.0), candidates=(c,)),
            "laser": Detections(points_xy=blob(5.85, 0.0, n=1))}
    ms = measurements(dets, GridConfig(), TrackingConfig())
    assert len(ms) == 1             # the candidate (its points not clustered again) + laser
    m = ms[0]
    assert set(m.sources) == {"geometry", "novelty", "laser"} and m.height_m == 1.7
    assert set(m.pipelines) == {"stereo-novelty", "laser"}
    assert len(merge_touching([m], 0.3)) == 1


def run(tracker, frames, speed=0.0):
    """frames: list of {pipeline: points}; returns the views after each frame."""
    out = []
    for k, f in enumerate(frames):
        dets = {n: Detections(points_xy=np.asarray(p, float).reshape(-1, 2)) for n, p in f.items()}
        out.append(tracker.update(dets, vs(speed), k * DT))
    return out


def test_a_post_is_confirmed_while_the_vehicle_drives_at_it_and_stays_put_in_the_world():
    tr = Tracker(TrackingConfig())
    frames = [{"stereo": blob(12.0 - 0.25 * k, 0.0)} for k in range(8)]
    views = run(tr, frames, speed=2.5)
    conf = [any(v.confirmed for v in vv) for vv in views]
    assert not conf[0] and conf[-1]
    (t,) = [v for v in views[-1] if v.confirmed]
    assert abs(t.vx_mps) < 0.3 and abs(t.vy_mps) < 0.3     # still over ground
    assert t.x_m == pytest.approx(12.0 - 0.25 * 7, abs=0.15)
    assert t.sources == ("geometry",)


def test_fewer_frames_near_and_large_more_far_and_small():
    tr = Tracker(TrackingConfig(confirm_frames_min=2, confirm_frames_max=6))
    assert tr.frames_needed(3.0, 1.5) == 2
    assert tr.frames_needed(25.0, 0.1) == 6
    assert 2 < tr.frames_needed(25.0, 1.5) < 6


def test_something_that_moves_with_the_vehicle_is_not_confirmed():
    """A stereo artefact (or the vehicle's shadow) stays at 7 m ahead while the vehicle drives
    2 m/s: it moves over ground with the vehicle and never becomes an obstacle."""
    tr = Tracker(TrackingConfig(max_speed_mps=10.0))     # only the co-moving test applies
    views = run(tr, [{"stereo": blob(7.0, 0.0)} for _ in range(20)], speed=2.0)
    assert not any(v.confirmed for v in views[-1])
    # the same patch with the vehicle standing: a real obstacle
    tr = Tracker(TrackingConfig(max_speed_mps=10.0))
    views = run(tr, [{"stereo": blob(7.0, 0.0)} for _ in range(20)], speed=0.0)
    assert any(v.confirmed for v in views[-1])


def test_random_speckle_is_never_confirmed():
    rng = np.random.default_rng(3)
    tr = Tracker(TrackingConfig())
    frames = [{"stereo": np.c_[rng.uniform(3, 20, 15), rng.uniform(-6, 6, 15)]}
              for _ in range(60)]
    views = run(tr, frames, speed=2.5)
    assert sum(v.confirmed for vv in views for v in vv) == 0


def test_one_noisy_cue_alone_does_not_confirm_two_that_agree_do():
    # a weak cue: capped below the confirmation threshold on its own
    # (laser_fast off: the evidence model itself; with it the laser confirms on its own)
    cfg = TrackingConfig(weights=SourceWeights(laser=0.3, geometry=0.3), confirm_logodds=2.0,
                         source_cap_frames=5.0, laser_fast=False)
    tr = Tracker(cfg)
    views = run(tr, [{"laser": blob(8.0, 0.0)} for _ in range(15)])
    assert not any(v.confirmed for v in views[-1])
    tr = Tracker(cfg)
    views = run(tr, [{"laser": blob(8.0, 0.0), "stereo": blob(8.0, 0.0)} for _ in range(15)])
    (t,) = [v for v in views[-1] if v.confirmed]
    assert t.sources == ("laser", "geometry")


def test_a_walking_person_gets_a_velocity():
    tr = Tracker(TrackingConfig())
    # crossing from the left at 1.2 m/s, 8 m ahead, vehicle standing
    views = run(tr, [{"stereo": blob(8.0, 3.0 - 0.12 * k)} for k in range(15)])
    (t,) = [v for v in views[-1] if v.confirmed]
    assert t.vy_mps == pytest.approx(-1.2, abs=0.25) and abs(t.vx_mps) < 0.3


def test_coasting_is_bounded():
    cfg = TrackingConfig(coast_s=0.3)
    tr = Tracker(cfg)
    frames = [{"stereo": blob(8.0, 0.0)} for _ in range(6)] + [{} for _ in range(6)]
    views = run(tr, frames)
    held = [any(v.confirmed for v in vv) for vv in views]
    assert held[5] and held[6] and held[7] and held[8]     # 0.1, 0.2, 0.3 s unseen: held
    assert not held[9]                                     # 0.4 s: gone
    assert [v.coasting for v in views[7] if v.confirmed] == [True]
    # the held track's cells are its footprint
    assert len(tr.confirmed_cells()) == 0
    tr2 = Tracker(cfg)
    run(tr2, frames[:7])
    assert len(tr2.confirmed_cells()) > 0


def test_a_gap_in_time_clears_the_tracks():
    tr = Tracker(TrackingConfig())
    run(tr, [{"stereo": blob(8.0, 0.0)} for _ in range(6)])
    assert tr.tracks
    tr.update({}, vs(), 10 * S)
    assert not tr.tracks


def test_tracking_config_is_validated():
    with pytest.raises(ConfigError, match=r"tracking.*far_m"):
        parse_config({"tracking": {"near_m": 20.0, "far_m": 10.0}})
    with pytest.raises(ConfigError, match=r"tracking.weights.laser"):
        parse_config({"tracking": {"weights": {"laser": -1.0}}})
    with pytest.raises(ConfigError, match=r"tracking.bogus"):
        parse_config({"tracking": {"bogus": 1}})
    c = parse_config({"tracking": {"enabled": True, "weights": {"novelty": 0.2}}})
    assert c.tracking.enabled and c.tracking.weights.novelty == 0.2
    assert dataclasses.replace(c.tracking, enabled=False).weights.novelty == 0.2
    # the movers' keys: ranges, choices and the one cross-check
    with pytest.raises(ConfigError, match=r"tracking.*movers_max_mps must exceed"):
        parse_config({"tracking": {"movers": True, "movers_min_mps": 2.0,
                                   "movers_max_mps": 1.0}})
    with pytest.raises(ConfigError, match=r"tracking.movers_input"):
        parse_config({"tracking": {"movers_input": "everything"}})
    with pytest.raises(ConfigError, match=r"tracking.movers_min_run"):
        parse_config({"tracking": {"movers_min_run": 2}})
    m = parse_config({"tracking": {"movers": True, "movers_range_m": 20.0}})
    assert m.tracking.movers and m.tracking.movers_range_m == 20.0


def test_a_candidates_cells_are_its_points_not_its_filled_footprint():
    big = Candidate(x_m=10.0, y_m=0.0, length_m=6.0, width_m=5.0, height_m=0.4, points=900,
                    confidence=0.9, sources=("geometry",), pipeline="stereo")
    pts = blob(9.05, 0.05)
    (m,) = measurements({"stereo": Detections(points_xy=pts, candidates=(big,))},
                        GridConfig(), TrackingConfig())
    assert len(m.cells_xy) == 9 and m.length_m == 6.0     # 9 cells, not 60 x 50
    # with the grid's occupied mask: only points in occupied cells; none -> not this cycle
    occ = np.zeros((320, 300), bool)
    assert measurements({"stereo": Detections(points_xy=pts, candidates=(big,))},
                        GridConfig(), TrackingConfig(), occ) == []
    # a front end that gives candidates and no points: their footprints
    (m,) = measurements({"x": Detections(candidates=(big,))}, GridConfig(), TrackingConfig(), occ)
    assert len(m.cells_xy) > 1000


def test_a_track_the_laser_and_stereo_both_saw_can_be_held_longer_unseen():
    """coast_fused_s (off by default, docs/tracking.md): a still track seen by the laser and
    a camera cue is held unseen that long whatever its evidence; one cue alone is not."""
    cfg = TrackingConfig(coast_fused_s=1.0)
    both = [{"laser": blob(8.0, 0.0, n=1), "stereo": blob(8.0, 0.0)} for _ in range(6)]
    views = run(Tracker(cfg), both + [{} for _ in range(12)])
    held = [any(v.confirmed for v in vv) for vv in views]
    assert held[5] and held[15] and not held[16]         # 1.0 s unseen: held; 1.1 s: gone
    views = run(Tracker(TrackingConfig()), both + [{} for _ in range(12)])
    assert not any(v.confirmed for v in views[11])       # default: coast_s at most
    alone = [{"stereo": blob(8.0, 0.0)} for _ in range(6)]
    views = run(Tracker(cfg), alone + [{} for _ in range(12)])
    assert not any(v.confirmed for v in views[11])


def test_motion_fit_a_walker_fits_a_line_a_hopping_track_does_not():
    """Tracker.motion_fit (the movers' test, docs/tracking.md 'Movers'): the centres of the
    present run of hits, a straight line at constant speed. A walker at (0.5, 1.2) m/s fits it
    to the grid's rounding; a track that hops between two tufts 0.4 m apart does not; a miss
    ends the run, and fewer than 3 centres fit nothing."""
    tr = Tracker(TrackingConfig(laser_fast=True), GridConfig())
    for k in range(8):
        tr.update({"laser": Detections(points_xy=blob(6.0 + 0.05 * k, -3.0 + 0.12 * k))},
                  vs(0.0), k * DT)
    (t,) = tr.tracks
    vx, vy, rms, span, n = tr.motion_fit(t)
    assert n == 8 and t.run == 8 and span == pytest.approx(0.7)
    assert vx == pytest.approx(0.5, abs=0.1) and vy == pytest.approx(1.2, abs=0.1)
    assert rms < 0.04
    tr.update({}, vs(0.0), 8 * DT)                      # a miss: the run starts again
    assert t.run == 0 and tr.motion_fit(t)[4] == 0
    hop = Tracker(TrackingConfig(laser_fast=True), GridConfig())
    for k in range(8):
        hop.update({"laser": Detections(points_xy=blob(6.0, -3.0 + 0.4 * (k % 2)))},
                   vs(0.0), k * DT)
    (h,) = hop.tracks
    assert h.run == 8 and hop.motion_fit(h)[2] > 0.15
    few = Tracker(TrackingConfig(), GridConfig())
    few.update({"laser": Detections(points_xy=blob(6.0, 0.0))}, vs(0.0), 0)
    assert few.motion_fit(few.tracks[0]) == (0.0, 0.0, 0.0, 0.0, 1)


def test_unique_cells_is_np_unique_on_the_cell_centres():
    """tracking._unique_cells (the fast path of a candidate's cells) gives exactly what
    np.unique(centres, axis=0) gave, negative coordinates and duplicates included."""
    from appliance.tracking import _unique_cells
    rng = np.random.default_rng(4)
    pts = np.r_[rng.uniform(-30, 30, (500, 2)), rng.uniform(-0.3, 0.3, (200, 2))]
    for cell in (0.1, 0.25):
        want = np.unique((np.floor(pts / cell) + 0.5) * cell, axis=0)
        got = _unique_cells(pts, cell)
        assert got.shape == want.shape and np.allclose(got, want, atol=1e-9)
    assert _unique_cells(np.zeros((0, 2)), 0.1).shape == (0, 2)


def test_a_non_finite_speed_or_yaw_rate_leaves_the_world_frame_where_it_was():
    """Defence in depth, as the grid's (tests/test_follow_turn.py): a NaN that slips past the
    links must not make every track NaN (nor raise: with movers on by default, that would be a
    'fusion failed' STOP every cycle it lasts). The post stays where it is, confirmed."""
    import math
    for bad in (dict(speed_mps=math.nan), dict(yaw_rate_radps=math.inf)):
        tr = Tracker(TrackingConfig())
        run(tr, [{"stereo": blob(8.0, 0.0)} for _ in range(6)])
        dets = {"stereo": Detections(points_xy=blob(8.0, 0.0))}
        views = tr.update(dets, VehicleState(0, 0, **{"speed_mps": 0.0, "yaw_rate_radps": 0.0,
                                                     **bad}), 6 * DT)
        (t,) = [v for v in views if v.confirmed]
        assert np.isfinite(tr.pose).all() and t.x_m == pytest.approx(8.0, abs=0.1)
