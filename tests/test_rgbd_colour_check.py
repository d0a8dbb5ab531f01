"""The rgbd pipeline's colour-model check (issue #14): the shipped greenhouse class model says
nothing on a stubble field, so there the pipeline decides on geometry alone; in the greenhouse
it changes nothing. Real rendered frames from the simulator (training seeds)."""
import logging

import numpy as np

from appliance.perception import SensorInputs
from appliance.perception.rgbd import RgbdPipeline, RgbdPipelineConfig


def _frames(scene, seed, n, step_s):
    from drivers.sim import SimField
    f = SimField(scene, seed=seed, sensors=("rgbd",))
    out = []
    for _ in range(n):
        s = f.render(0, 0)
        out.append((s.rgbd, s.vehicle))
        f.step(step_s)
    return out


def test_default_eval_of_a_stubble_run_with_stereo_and_rgbd_is_not_wrecked_by_the_rgbd(
        tmp_path, caplog):
    """`fieldguard eval RUN` (no --pipeline) on a stubble-day run with stereo and RGB-D fuses
    stereo-novelty and rgbd. Before the check the greenhouse colour model called the stubble
    'no traversable class' and every frame had ~100 false-positive cells and a false stop."""
    from appliance.evaluation import evaluate_run, format_table
    from drivers.sim.record import write_sim_run
    run = write_sim_run("stubble-day", 12, tmp_path / "run", seed=2,
                        sensors=("stereo", "rgbd"), stereo_scale=0.25)
    with caplog.at_level(logging.WARNING, logger="fieldguard.perception.rgbd"):
        res = evaluate_run(run)
    assert res["pipeline"] == "fused(stereo-novelty+rgbd)"
    # measured: 1.1 FP cells a frame, no false stop (before the check: 105 cells a frame in
    # 11 of the 12 frames, 11 false stops)
    assert res["fp_cells_per_frame"] < 5.0, res["fp_cells_per_frame"]
    assert res["false_stop_frames"] == 0, res["false_stop_frame_indices"]
    assert res["missed_stop_frames"] == 0
    # the rgbd said why, once in the log, and in the result and the table
    assert res["geometry_only_frames"] == {"rgbd": 12}
    assert "geometry alone" in res["pipeline_notes"]["rgbd"]["colour_model"]
    said = [r for r in caplog.records if "geometry alone" in r.getMessage()]
    assert len(said) == 1                                  # once, not every frame
    assert "note: rgbd: the class model explains" in format_table(res)

def test_greenhouse_frames_keep_the_colour_model_and_the_same_points():
    frames = _frames("greenhouse", 1, 6, 0.7)
    on = RgbdPipeline(RgbdPipelineConfig(colour_lut_bits=0))
    off = RgbdPipeline(RgbdPipelineConfig(colour_lut_bits=0, colour_check=False))
    try:
        for rgbd, vehicle in frames:
            a = on.process(SensorInputs(0, rgbd=rgbd, vehicle=vehicle))
            b = off.process(SensorInputs(0, rgbd=rgbd, vehicle=vehicle))
            assert a.debug["colour_model"] == "applies"
            assert a.debug["colour_share"] > 0.9
            assert np.array_equal(a.points_xy, b.points_xy)
        assert on.notes().get("colour_model") is None and on.geometry_frames == 0
    finally:
        on.close()
        off.close()


def test_stubble_frames_switch_to_geometry_and_back_with_hysteresis():
    frames = _frames("stubble-day", 2, 3, 0.4)
    p = RgbdPipeline(RgbdPipelineConfig(colour_lut_bits=0))
    try:
        d = p.process(SensorInputs(0, rgbd=frames[0][0]))
        assert d.debug["colour_model"] == "geometry-only"
        assert d.debug["colour_share"] < 0.7
        assert d.debug["groups_texture"] == 0 and d.debug["groups_holes"] == 0
        assert "geometry alone" in p.notes()["colour_model"]
        # no candidate says colour: the classes were not used
        assert all("colour" not in c.sources for c in d.candidates)
        # back in a scene the model explains: a running share just over the minimum (0.8) is
        # not enough to switch back, over it by the hysteresis margin (0.1) it is
        greenhouse = _frames("greenhouse", 1, 1, 0.7)[0][0]
        p.colour_share = 0.82
        p.process(SensorInputs(0, rgbd=greenhouse))       # 0.7 * 0.82 + 0.3 * ~0.99 = ~0.87
        assert 0.8 < p.colour_share < 0.9 and not p.colour_applies
        p.process(SensorInputs(0, rgbd=greenhouse))       # ~0.91
        assert p.colour_share >= 0.9 and p.colour_applies
        assert p.notes().get("colour_model") is None
    finally:
        p.close()
