"""The rgbd pipeline in the daemon, closed loop on the simulated greenhouse."""
import dataclasses
import types

from appliance.config import default_config
from appliance.daemon import Daemon, sim_config
from appliance.perception.rgbd import RgbdPipelineConfig
from hal import GateState


def test_greenhouse_sprayer_stops_for_the_crate_on_its_path():
    cfg = default_config()
    cfg = dataclasses.replace(
        cfg,
        # the greenhouse sprayer: 1.2 m long, 0.8 m wide; the bushes start 0.6 m off the centre
        zones=dataclasses.replace(cfg.zones, front_x_m=1.1, half_width_m=0.5),
        # the default rgbd options (texture on every frame, depth holes): the paper's rule with
        # texture would stop it ~1.4 m ahead for leaves overhanging the path (docs/rgbd.md)
        perception=dataclasses.replace(cfg.perception, pipelines=("rgbd",), extra=types.MappingProxyType(
            {"rgbd": RgbdPipelineConfig()})))
    d = Daemon(sim_config(cfg, "greenhouse"), mode="sim", pace=0.0, serve_status=False)
    d.start()
    log = []
    d.loop.on_cycle.append(lambda r: log.append(r))
    try:
        d.run(max_cycles=90)          # 9 s: it slows, then stops short of the crate
        st = d.status()
    finally:
        d.shutdown()
    assert st["sim"]["collisions"] == 0
    stops = [r for r in log if r.output.state is GateState.STOP and "stop zone" in r.output.reason]
    assert stops, [r.output.reason for r in log[-3:]]
    # the crate stands ~4 m ahead of the start: the stop is for it (the nearest cell is at its
    # face, measured from the vehicle's front), not for a bush beside the path
    clearance = st["sim"]["clearance_m"]
    nearest = stops[-1].output.nearest_m
    assert abs(nearest - clearance) < 0.5, (nearest, clearance)
    assert st["sim"]["distance_m"] < 1.0 and log[-1].output.state is GateState.STOP
    assert all("pipeline" not in r.output.reason for r in log)


def _greenhouse_daemon(rgbd_options):
    cfg = default_config()
    cfg = dataclasses.replace(
        cfg, zones=dataclasses.replace(cfg.zones, front_x_m=1.1, half_width_m=0.5),
        perception=dataclasses.replace(cfg.perception, pipelines=("rgbd",),
                                       extra=types.MappingProxyType({"rgbd": rgbd_options})))
    return Daemon(sim_config(cfg, "greenhouse"), mode="sim", pace=0.0, serve_status=False)


def _run(d, cycles):
    """(cycle results, daemon status, loop status) of ``cycles`` cycles."""
    d.start()
    log = []
    d.loop.on_cycle.append(lambda r: log.append(r))
    try:
        d.run(max_cycles=cycles)
        return log, d.status(), d.loop.status()
    finally:
        d.shutdown()


def test_greenhouse_with_the_learned_cue_required_stops_for_the_crate():
    log, st, loop_st = _run(_greenhouse_daemon(RgbdPipelineConfig(cue="required")), 90)
    notes = loop_st["pipeline_notes"]["rgbd"]
    assert notes["cue"] == "on (required)" and notes["cue_model"].endswith("cue-greenhouse.onnx")
    assert notes["cue_runs"] > 0
    assert st["sim"]["collisions"] == 0
    assert any(r.output.state is GateState.STOP and "stop zone" in r.output.reason for r in log)
    assert all("pipeline" not in r.output.reason for r in log)


def test_greenhouse_with_a_required_cue_whose_model_is_gone_never_drives(tmp_path):
    log, st, _ = _run(_greenhouse_daemon(RgbdPipelineConfig(
        cue="required", cue_model=str(tmp_path / "gone.onnx"))), 20)
    assert all(r.output.state is GateState.STOP for r in log)
    assert "learned cue required but unavailable" in log[-1].output.reason
    assert "gone.onnx" in log[-1].output.reason
    # it starts at cruise speed (0.7 m/s) and brakes on the first STOP: ~0.1 m, never more
    assert st["sim"]["distance_m"] < 0.3 and st["sim"]["speed_mps"] == 0.0
