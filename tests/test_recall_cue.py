"""stereo-novelty's ``recall_frames`` (issue #14, "0 collisions"): the obstacle points of the
last frames, carried with the vehicle's motion and projected into the camera, raise their
novelty cells for matching (cue "recent"), so what was found once is looked at again.

Found on training stubble-thin 130 (thirty-eighth session, tools/why_missed.py): a head-on dog
0.55 m high, not novel, was matched only in the frames the depth cue happened to raise its
cells (5 of 50 on its way in from 12 m); its band hits never came two cycles running, the grid
never held it, and the vehicle drove into it."""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from appliance.perception import SensorInputs
from appliance.perception.stereo import match_factor
from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
from drivers.sim import SimField
from hal.types import GateState, VehicleState

NS = 100_000_000


@pytest.fixture(scope="module")
def course():
    """Rendered frames of a training stubble course (seed 1, 640x512) with the vehicle
    standing (speed 0): the first 6 to learn the field, then 3 with obstacles in view."""
    f = SimField("stubble-day", seed=1, sensors=("stereo",), stereo_scale=0.5)
    out = []
    for i in range(30):
        if i < 6 or i >= 27:
            s = f.render(i * NS, i)
            v = s.vehicle
            out.append(SensorInputs(s.stereo.stamp_ns, stereo=s.stereo,
                                    vehicle=dataclasses.replace(v, speed_mps=0.0,
                                                                yaw_rate_radps=0.0)))
        f.step(0.1, GateState.CLEAR)
    return out


def _pipe(**opts):
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", update_every_frames=2,
                            **opts)
    return StereoNoveltyPipeline(o, background=False)


def test_off_by_default_and_then_no_recent_cue(course):
    assert StereoNoveltyConfig().recall_frames == 0
    p = _pipe()
    try:
        for fr in course:
            d = p.process(fr)
            assert "recent" not in d.debug["cue_cells"]
    finally:
        p.close()


def test_a_frames_obstacle_points_raise_their_own_cells_in_the_next_frame(course):
    """The vehicle stands: every obstacle point of a frame projects back into the novelty cell
    its own pixel lies in, and that cell (at least) is raised as "recent" in the next frame."""
    p = _pipe(recall_frames=3, recall_dilate_cells=0)
    try:
        for fr in course[:-1]:
            p.process(fr)
        pts, px, h, keep, k = p.last_points
        assert keep.sum() > 20                         # the course: obstacle points
        res = p.last[0]
        rows, cols = res.mask.shape
        W = course[0].stereo.left.shape[1]
        kd = match_factor(W, p.options.descriptor_width_px)
        own = set()
        # pixels at matching resolution (1/k) -> descriptor resolution (1/kd) -> cells
        for u, v in px[keep]:
            ci, cj = int(v * k / kd // res.cell_px), int(u * k / kd // res.cell_px)
            if 0 <= ci < rows and 0 <= cj < cols:
                own.add((ci, cj))
        cue = p._recall_cue(course[-1].stereo, course[-1].vehicle, res, kd)
        assert cue is not None
        raised = {tuple(c) for c in np.argwhere(cue)}
        # projected back through the same pinhole: each lands in its own cell (a point on a
        # cell's edge may fall one cell over: allow the 3x3 around it)
        near = sum(1 for (ci, cj) in own
                   if any((ci + a, cj + b) in raised for a in (-1, 0, 1) for b in (-1, 0, 1)))
        assert near == len(own)
        exact = len(own & raised) / len(own)
        assert exact > 0.9
        d = p.process(course[-1])
        assert d.debug["cue_cells"].get("recent", 0) > 0
    finally:
        p.close()


def test_recalled_points_move_with_the_vehicle(course):
    """A point 8 m ahead, the vehicle driving at 2 m/s for 0.5 s: recalled 7 m ahead (the cell
    a point 7 m ahead projects to), not where it was."""
    fr = course[-1].stereo
    p = _pipe(recall_frames=10, recall_dilate_cells=0)
    try:
        res = SimpleNamespace(mask=np.zeros((32, 40), bool), cell_px=16)
        W = fr.left.shape[1]
        kd = match_factor(W, p.options.descriptor_width_px)
        assert (W // kd, fr.left.shape[0] // kd) == (640, 512)
        p._recall_ns = fr.stamp_ns - 500_000_000
        p._recall.append(np.array([[8.0, 0.0, 0.6]]))
        moving = VehicleState(fr.stamp_ns, fr.stamp_ns, 2.0, 0.0)
        got = p._recall_cue(fr, moving, res, kd)
        p._recall.clear()
        p._recall_ns = fr.stamp_ns
        p._recall.append(np.array([[7.0, 0.0, 0.6]]))
        want = p._recall_cue(fr, moving, res, kd)           # dt 0: not moved
        p._recall.clear()
        p._recall_ns = fr.stamp_ns
        p._recall.append(np.array([[8.0, 0.0, 0.6]]))
        stayed = p._recall_cue(fr, moving, res, kd)
        assert np.array_equal(got, want)
        assert not np.array_equal(got, stayed)
    finally:
        p.close()


def test_a_clock_step_back_or_a_gap_forgets_what_was_recalled(course):
    fr = course[-1].stereo
    p = _pipe(recall_frames=10)
    try:
        res = SimpleNamespace(mask=np.zeros((32, 40), bool), cell_px=16)
        kd = match_factor(fr.left.shape[1], p.options.descriptor_width_px)
        for step_ns in (-NS, 3_000_000_000):
            p._recall.append(np.array([[6.0, 0.0, 0.6]]))
            p._recall_ns = fr.stamp_ns - step_ns
            assert p._recall_cue(fr, course[-1].vehicle, res, kd) is None
            assert not len(p._recall)
    finally:
        p.close()


def test_only_wide_candidates_and_nothing_before_the_model_warms_up(course):
    """``recall_min_width_m``: only points on candidates at least that wide are recalled (none
    here at 20 m); ``recall_min_updates``: nothing before the model holds that many updates."""
    for opts in ({"recall_min_width_m": 20.0}, {"recall_min_updates": 1000}):
        p = _pipe(recall_frames=3, **opts)
        try:
            for fr in course:
                d = p.process(fr)
                assert d.debug["cue_cells"].get("recent", 0) == 0
            assert not any(len(x) for x in p._recall)
        finally:
            p.close()
    p = _pipe(recall_frames=3, recall_min_width_m=0.2)    # the course's wide things are kept
    try:
        for fr in course:
            p.process(fr)
        assert sum(len(x) for x in p._recall) > 0
    finally:
        p.close()
