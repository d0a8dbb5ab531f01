"""The decision core (appliance/decision.py): one path from detections to the gate, used by
the loop and by the evaluator; the decision on tracks."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from appliance.config import Config, GateConfig, GridConfig, TrackingConfig, ZonesConfig
from appliance.decision import DecisionCore, assess_tracks
from appliance.loop import ApplianceLoop
from appliance.perception import Detections, make_pipeline
from appliance.tracking import TrackView
from hal import GateState, ManualClock
from hal.types import VehicleState
from tests.fakes import HandLaser, HandLink

S = 10**9
DT = S // 10


def blob(x, y, n=3):
    o = (np.arange(n) - (n - 1) / 2) * 0.1
    return np.array([[x + a, y + b] for a in o for b in o])


def tracks_cfg(**kw) -> Config:
    return Config(gate=GateConfig(hold_off_s=0.3), tracking=TrackingConfig(enabled=True, **kw))


def view(x, y, vx=0.0, vy=0.0, confirmed=True, size=0.4, tid=1):
    return TrackView(id=tid, x_m=x, y_m=y, length_m=size, width_m=size, height_m=1.7,
                     vx_mps=vx, vy_mps=vy, confidence=0.95, sources=("geometry",),
                     confirmed=confirmed, coasting=False, hits=10, age_s=1.0)


def test_a_confirmed_track_in_the_stop_zone_stops_a_tentative_one_does_not():
    cfg = tracks_cfg()
    # at standstill the stop zone is 2.6 .. 4.6 m ahead, |y| <= 1.25
    v = assess_tracks([view(4.0, 0.0)], np.zeros((0, 2)), 0.0, cfg)
    assert v.in_stop == 1 and "track 1 (geometry)" in v.stop_reason and v.track_ids == (1,)
    v = assess_tracks([view(4.0, 0.0, confirmed=False)], np.zeros((0, 2)), 0.0, cfg)
    assert v.in_stop == 0 and v.in_slow == 0 and v.nearest_m is None
    v = assess_tracks([view(7.0, 0.5)], np.zeros((0, 2)), 0.0, cfg)
    assert v.in_stop == 0 and v.in_slow == 1 and "slow zone" in v.slow_reason
    # beside the path: the footprint's edge decides (1.25 + 0.2 = 1.45)
    assert assess_tracks([view(4.0, 1.40)], np.zeros((0, 2)), 0.0, cfg).in_stop == 1
    assert assess_tracks([view(4.0, 1.50)], np.zeros((0, 2)), 0.0, cfg).in_stop == 0


def test_a_person_walking_towards_the_path_is_predicted_into_the_stop_zone():
    cfg = tracks_cfg()     # reaction time 0.5 s
    walking = view(4.0, 2.0, vy=-1.5)         # edge at 1.8: 0.55 m out, 0.37 s away
    v = assess_tracks([walking], np.zeros((0, 2)), 0.0, cfg)
    assert v.in_stop == 1 and "predicted into the stop zone" in v.stop_reason
    away = view(4.0, 2.0, vy=+1.5)
    assert assess_tracks([away], np.zeros((0, 2)), 0.0, cfg).in_stop == 0
    far_out = view(4.0, 3.5, vy=-1.5)         # 2.05 m out: 1.4 s away, beyond the horizon
    assert assess_tracks([far_out], np.zeros((0, 2)), 0.0, cfg).in_stop == 0
    # slower than predict_min_mps: the noise of a still object is not extrapolated
    creeping = view(4.0, 1.5, vy=-0.3)
    assert assess_tracks([creeping], np.zeros((0, 2)), 0.0, cfg).in_stop == 0


def test_exclusion_boxes_still_hold_for_tracks():
    from appliance.config import ExclusionZone
    cfg = dataclasses.replace(tracks_cfg(), zones=ZonesConfig(exclusion=(
        ExclusionZone(x_min_m=3.0, x_max_m=5.0, y_min_m=-1.0, y_max_m=1.0),)))
    assert assess_tracks([view(4.0, 0.0)], np.zeros((0, 2)), 0.0, cfg).in_stop == 0


def test_cells_decision_is_unchanged_when_tracking_is_off():
    """enabled = false: the obstacle picture is the grid's occupied cells, as before (a laser
    cell stopping on its first occupied cycle, as it did by default before 2026-12-04)."""
    cfg = Config(grid=GridConfig(occupied_at=1.0, stop_recur_now=("laser",)))
    core = DecisionCore(cfg)
    assert core.tracker is None
    pic = core.perceive({"laser": Detections(points_xy=np.array([[4.05, 0.05]]))},
                        VehicleState(0, 0), 0)
    assert len(pic.cells_xy) == 1 and pic.verdict.in_stop == 1 and pic.tracks == []
    assert pic.verdict.stop_reason is None
    out = core.decide(0, [], pic)
    assert out.state is GateState.STOP and out.reason.startswith("obstacle 1.5 m ahead")
    assert core.gate.cause == "obstacle"


def test_core_with_tracks_stops_for_a_post_and_names_it_and_its_cues():
    core = DecisionCore(tracks_cfg())
    outs = []
    for k in range(12):
        dets = {"stereo": Detections(points_xy=blob(4.05, 0.05)),
                "laser": Detections(points_xy=blob(3.95, 0.05, n=1))}
        pic = core.perceive(dets, VehicleState(k * DT, k), k * DT)
        outs.append(core.decide(k * DT, [], pic))
    assert outs[0].state is GateState.STOP and core.gate.cause == "obstacle"
    assert "(laser+geometry)" in outs[-1].reason and "stop zone" in outs[-1].reason
    assert len(pic.objects) == 1 and len(pic.cells_xy) == 9      # the track's cells (laser inside)
    assert pic.verdict.sectors and any(s.distance_m for s in pic.verdict.sectors)


def test_gate_cause_boot_fault_obstacle_clear():
    core = DecisionCore(tracks_cfg())
    assert core.gate.cause == "boot"
    pic = core.perceive({}, VehicleState(0, 0), 0)
    core.decide(0, [], pic)
    assert core.gate.state is GateState.STOP and core.gate.cause == "boot"
    core.decide(DT, ["laser: stale"], core.perceive({}, VehicleState(DT, 1), DT))
    assert core.gate.cause == "fault"
    for k in range(2, 8):
        out = core.decide(k * DT, [], core.perceive({}, VehicleState(k * DT, k), k * DT))
    assert out.state is GateState.CLEAR and core.gate.cause == "clear"


def make_loop(cfg):
    clock = ManualClock(S)
    laser, link = HandLaser("laser", clock), HandLink("link", clock)
    loop = ApplianceLoop(cfg, clock, {"laser": laser, "link": link},
                         [make_pipeline("laser", cfg)])
    return clock, loop, laser, link


def test_the_loop_decides_on_tracks_with_the_same_core():
    cfg = dataclasses.replace(tracks_cfg(),
                              grid=GridConfig(occupied_at=1.0))
    clock, loop, laser, link = make_loop(cfg)
    assert loop.core.tracker is not None and loop.gate is loop.core.gate
    for _ in range(6):
        loop.cycle()
        clock.advance(DT)
    assert loop.gate.state is GateState.CLEAR
    # one laser beam on a post at 4 m: a laser return cluster confirms when the grid holds
    # it (here occupied_at 1.0: the first cycle), so the loop stops at once, as the cell
    # decision does, and status names the track
    laser.put_obstacle(4.0, 0.0)
    states = []
    for _ in range(12):
        states.append(loop.cycle().output.state)
        clock.advance(DT)
    assert all(s is GateState.STOP for s in states)
    st = loop.status()
    assert st["obstacles"]["decision"] == "tracks"
    (t,) = st["tracks"]
    assert t["sources"] == ["laser"] and abs(t["x_m"] - 4.0) < 0.2 and t["confirmed"]
    assert link.sent[-1].state is GateState.STOP and "track" in link.sent[-1].reason


def test_snapshot_draws_the_tracks_and_status_text_lists_them():
    from appliance.cli import format_status
    from appliance.snapshot import TRACK_BGR, compose, grid_panel, track_label
    cfg = dataclasses.replace(tracks_cfg(), grid=GridConfig(occupied_at=1.0))
    clock, loop, laser, link = make_loop(cfg)
    laser.put_obstacle(6.0, 0.0)
    for _ in range(12):
        res = loop.cycle()
        clock.advance(DT)
    (t,) = [t for t in res.tracks if t.confirmed]
    assert track_label(t).startswith(f"#{t.id} 6.") and track_label(t).endswith("laser")
    img = grid_panel(res, loop.grid.evidence, cfg)
    assert np.any(np.all(img == np.array(TRACK_BGR, np.uint8), axis=2))
    assert compose(res, loop.grid.evidence, cfg, loop.status()).shape[0] > img.shape[0]
    text = format_status(loop.status())
    assert f"track {t.id}" in text and "laser" in text


def test_tracker_input_is_the_occupied_grid_by_default_or_every_hit():
    """input = "occupied": a cell must be hit in consecutive cycles (the grid's rule) before
    the tracker sees it; "hits": every cell hit this cycle is clustered."""
    pts = {"stereo": Detections(points_xy=blob(8.05, 3.05))}
    core = DecisionCore(tracks_cfg())
    assert core.cfg.tracking.input == "occupied"
    core.perceive(pts, VehicleState(0, 0), 0)
    assert core.tracker.tracks == []                  # one hit: not occupied yet
    core.perceive(pts, VehicleState(DT, 1), DT)
    assert len(core.tracker.tracks) == 1
    core = DecisionCore(tracks_cfg(input="hits"))
    core.perceive(pts, VehicleState(0, 0), 0)
    assert len(core.tracker.tracks) == 1


def test_a_held_track_keeps_its_last_cells_where_it_now_is():
    core = DecisionCore(tracks_cfg(coast_s=0.5))
    for k in range(8):
        pic = core.perceive({"stereo": Detections(points_xy=blob(8.05, 3.05))},
                            VehicleState(k * DT, k), k * DT)
    seen = {tuple(np.round(c, 2)) for c in pic.cells_xy}
    assert len(seen) == 9
    # unseen now, the vehicle drove 0.5 m: the same cells, 0.5 m nearer
    pic = core.perceive({}, VehicleState(8 * DT, 8, speed_mps=5.0), 8 * DT)
    held = {tuple(np.round(c + [0.5, 0.0], 2)) for c in pic.cells_xy}
    assert pic.objects and pic.objects[0].coasting and held == seen


def test_the_sectors_for_obstacle_distance_carry_only_confirmed_tracks():
    """With tracks, OBSTACLE_DISTANCE / FG_ObstacleSectors are built from the confirmed
    tracks' cells: a cluster not (yet) confirmed is not sent as an obstacle."""
    core = DecisionCore(tracks_cfg())
    seen = []
    for k in range(8):
        pic = core.perceive({"stereo": Detections(points_xy=blob(9.05, 0.05))},
                            VehicleState(k * DT, k), k * DT)
        seen.append((bool(pic.objects), any(s.distance_m for s in pic.verdict.sectors)))
    assert seen[0] == (False, False) and seen[-1] == (True, True)
    assert all(a == b for a, b in seen)


def test_a_large_candidate_is_in_the_stop_zone_only_where_its_cells_are():
    """A front end's candidate can be metres larger than what stands in it: with its cells
    known, a track is in a zone where a cell of it is, not wherever its footprint reaches."""
    cfg = tracks_cfg()
    big = TrackView(id=3, x_m=8.0, y_m=0.0, length_m=9.0, width_m=4.0, height_m=1.0,
                    vx_mps=0.0, vy_mps=0.0, confidence=0.9, sources=("geometry",),
                    confirmed=True, coasting=False, hits=9, age_s=1.0)
    assert assess_tracks([big], np.zeros((0, 2)), 0.0, cfg).in_stop == 1      # footprint only
    far = {3: np.array([[10.05, 0.05], [10.15, 0.05]])}
    v = assess_tracks([big], far[3], 0.0, cfg, far)
    assert v.in_stop == 0 and v.in_slow == 0
    near = {3: np.array([[4.05, 0.05]])}
    v = assess_tracks([big], near[3], 0.0, cfg, near)
    assert v.in_stop == 1 and v.nearest_m == pytest.approx(1.45)


# --- [grid] stop_at: the stubble-tuft false stops (docs/tracking.md, "False stops") ---------
def _drive(core, hits_at, n, speed=2.5, front=2.2):
    """Drive straight at ``speed``; ``hits_at(k)`` gives cycle k's points (vehicle frame)."""
    outs = []
    for k in range(n):
        v = VehicleState(k * DT, k, speed_mps=speed)
        pic = core.perceive({"stereo-novelty": Detections(points_xy=hits_at(k))}, v, k * DT)
        outs.append((core.decide(k * DT, [], pic), pic))
    return outs


def _cfg(stop_at):
    return Config(gate=GateConfig(hold_off_s=1.0),
                  grid=GridConfig(decay=0.5, occupied_at=1.4, stop_at=stop_at, stop_recur=0.0),
                  zones=ZonesConfig(front_x_m=2.2))


def test_a_two_cycle_blip_at_the_near_edge_slows_but_does_not_stop_with_stop_at():
    """The mechanism found on stubble-coverage 1: a stubble tuft's tip (0.5-0.6 m above the
    level ground) is matched only in the last two frames before it leaves the view at the
    near edge (x ~ 3.95 m, 1.75 m ahead of the front): two hits, an occupied cell, a STOP.
    With stop_at 1.7 (three cycles running) it is a SLOW; with the papers' rule a STOP."""
    def tuft(k):                          # world-fixed at x_w = 3.95 + 0.25 * 11, seen k=10, 11
        if k not in (10, 11):
            return np.zeros((0, 2))
        x = 3.95 + 0.25 * (11 - k)
        return np.array([[x, 0.9], [x + 0.1, 0.9], [x + 0.2, 0.9]])     # a tuft's 0.3 m
    for stop_at, want in ((0.0, GateState.STOP), (1.7, GateState.SLOW)):
        core = DecisionCore(_cfg(stop_at))
        outs = _drive(core, tuft, 14)
        states = [o.state for o, _ in outs[11:]]
        assert outs[11][1].verdict.nearest_m is not None
        assert want in states and (want is GateState.STOP or GateState.STOP not in states)
        if stop_at:
            assert "unconfirmed obstacle" in outs[11][0].reason


def test_stop_at_still_stops_for_a_post_approached_from_afar_without_delay():
    """A world-fixed post seen every cycle from 15 m: with stop_at 1.7 its cells are
    confirmed long before it reaches the stop zone, so the STOP comes on the same cycle as
    with the papers' rule."""
    x_w = 2.2 + 15.0

    def post(k):
        return blob(x_w - 0.25 * k, 0.05, n=2)
    first = {}
    for stop_at in (0.0, 1.7):
        core = DecisionCore(_cfg(stop_at))
        outs = _drive(core, post, 60)
        first[stop_at] = next(k for k, (o, _) in enumerate(outs)
                              if o.state is GateState.STOP and k > 10)
    assert first[0.0] == first[1.7]


def test_stop_at_at_or_below_occupied_at_is_the_papers_rule_and_is_checked():
    """stop_at <= occupied_at: an occupied cell in the stop zone is a STOP (the papers'
    rule, the reproduction tables); a negative value is a config error naming the key."""
    core = DecisionCore(_cfg(1.0))
    pic = core.perceive({"laser": Detections(points_xy=np.array([[4.05, 0.05]]))},
                        VehicleState(0, 0), 0)
    pic = core.perceive({"laser": Detections(points_xy=np.array([[4.05, 0.05]]))},
                        VehicleState(DT, 1), DT)
    assert pic.verdict.in_stop == 1 and core.decide(DT, [], pic).state is GateState.STOP
    from appliance.config import parse_config
    from hal.errors import ConfigError
    with pytest.raises(ConfigError, match="stop_at"):
        parse_config({"grid": {"stop_at": -1.0}}, "<t>")


def test_stop_at_a_person_walking_into_the_path_costs_at_most_one_cycle():
    """A person (0.45 x 0.3 m) walking across at 1.2 m/s into the path 6 m ahead while the
    vehicle drives at 2.5 m/s: their cells move, so with stop_at 1.7 the STOP comes one cycle
    (0.25 m) later than with the papers' rule, not never. (A faster crosser, an animal at
    3 m/s, is not stopped for at all with stop_at: docs/tracking.md, 'Is it the default?'.)"""
    def person(k):
        x, y = 2.2 + 6.0 - 0.25 * k, 3.5 - 0.12 * k
        xs, ys = np.arange(x - 0.15, x + 0.151, 0.05), np.arange(y - 0.225, y + 0.226, 0.05)
        return np.array([[a, b] for a in xs for b in ys])
    first = {}
    for stop_at in (0.0, 1.7):
        outs = _drive(DecisionCore(_cfg(stop_at)), person, 30)
        first[stop_at] = next(k for k, (o, _) in enumerate(outs)
                              if o.state is GateState.STOP and k > 10)
    assert first[0.0] <= first[1.7] <= first[0.0] + 1


# --- [grid] stop_chain: a STOP needs an object that stayed (or moved slowly) ----------------
def _chain_cfg(n, radius=0.3):
    return Config(gate=GateConfig(hold_off_s=1.0),
                  grid=GridConfig(stop_chain=n, stop_chain_radius_m=radius, stop_recur=0.0),
                  zones=ZonesConfig(front_x_m=2.2))


def _body(x, y, w=0.45, d=0.3):
    xs, ys = np.arange(x - d / 2, x + d / 2 + 1e-9, 0.05), np.arange(y - w / 2, y + w / 2 + 1e-9, 0.05)
    return np.array([[a, b] for a in xs for b in ys])


def test_stop_chain_turns_a_two_cycle_blip_in_the_stop_zone_into_a_slow():
    """The night phantoms of the training campaign: nothing for cycles, then a few cells hit
    in two cycles running inside the stop zone, then nothing. With stop_chain 3 that is a
    SLOW ("unconfirmed obstacle"); with the papers' rule a STOP. A third cycle makes it a STOP."""
    def blip(cycles):
        def hits(k):
            if k not in cycles:
                return np.zeros((0, 2))
            x = 2.2 + 2.5 + 0.25 * (max(cycles) - k)       # world-fixed, 2.5 m ahead at the end
            return np.array([[x, 0.0], [x, 0.1]])
        return hits
    for cfg, want in ((_cfg(0.0), GateState.STOP), (_chain_cfg(3), GateState.SLOW)):
        outs = _drive(DecisionCore(cfg), blip((10, 11)), 14)
        states = [o.state for o, _ in outs[11:]]
        assert want in states and (want is GateState.STOP or GateState.STOP not in states)
    outs = _drive(DecisionCore(_chain_cfg(3)), blip((10, 11)), 14)
    assert "unconfirmed obstacle" in outs[11][0].reason
    outs = _drive(DecisionCore(_chain_cfg(3)), blip((9, 10, 11)), 14)
    assert outs[11][0].state is GateState.STOP


def test_stop_chain_follows_a_fast_crosser_that_stop_at_loses():
    """An animal (0.45 x 0.3 m) crossing at 3 m/s 6 m ahead while the vehicle drives at
    2.5 m/s: its cells move 0.3 m a cycle, so no cell is hit three cycles running and stop_at
    1.7 never stops; a chain follows it within its 0.3 m radius, and the STOP comes on the
    papers' rule's cycle. With radius 0 (the same cell every cycle, stop_at's rule) it is lost
    again."""
    def animal(k):
        return _body(2.2 + 6.0 - 0.25 * k, 3.5 - 0.3 * k)

    def first_stop(cfg):
        outs = _drive(DecisionCore(cfg), animal, 30)
        return next((k for k, (o, _) in enumerate(outs)
                     if o.state is GateState.STOP and k > 10), None)
    paper = first_stop(_cfg(0.0))
    assert paper is not None
    assert first_stop(_cfg(1.7)) is None
    assert first_stop(_chain_cfg(3)) == paper
    assert first_stop(_chain_cfg(3, radius=0.0)) is None


def test_stop_chain_stops_for_a_post_approached_from_afar_on_the_same_cycle():
    """A world-fixed post seen every cycle from 15 m ahead: its chain is long before it
    reaches the stop zone, so stop_chain costs nothing there."""
    def post(k):
        return blob(2.2 + 15.0 - 0.25 * k, 0.05, n=2)
    firsts = []
    for cfg in (_cfg(0.0), _chain_cfg(3)):
        outs = _drive(DecisionCore(cfg), post, 60)
        firsts.append(next(k for k, (o, _) in enumerate(outs)
                           if o.state is GateState.STOP and k > 10))
    assert firsts[0] == firsts[1]


def test_stop_recur_stops_for_a_flickering_crate_that_stop_at_and_chains_lose():
    """Training campaign stubble-coverage 4 (seed 4): a stubble-coloured crate, held only in
    pairs of cycles with gaps (occupied at 44.7-44.9, 45.6, 45.9-46.0, 46.3 s), which
    stop_at 1.7 never confirmed and the vehicle hit it. A world-fixed crate 1.5-1.8 m ahead at
    1 m/s, hit in cycles 20-21 and 23-24: the papers' rule stops at 21, stop_at and
    stop_chain 3 never, stop_recur 1.3 at 24 (occupied again 3 cycles after: 1 + 0.8^3). A
    single occupied cycle (the night phantoms) is a SLOW under stop_recur."""
    def crate(cycles):
        def hits(k):
            if k not in cycles:
                return np.zeros((0, 2))
            x = 2.2 + 1.5 + 0.1 * (24 - k)
            return np.array([[x, 0.0], [x, 0.1], [x, -0.1]])
        return hits

    def first_stop(grid, cycles, speed=1.0):
        cfg = Config(gate=GateConfig(hold_off_s=1.0), grid=grid, zones=ZonesConfig(front_x_m=2.2))
        outs = _drive(DecisionCore(cfg), crate(cycles), 28, speed=speed)
        return next((k for k, (o, _) in enumerate(outs) if o.state is GateState.STOP
                     and k > 15), None)
    flicker = (20, 21, 23, 24)
    assert first_stop(GridConfig(stop_recur=0.0), flicker) == 21            # the papers' rule
    assert first_stop(GridConfig(stop_at=1.7, stop_recur=0.0), flicker) is None
    assert first_stop(GridConfig(stop_chain=3, stop_recur=0.0), flicker) is None
    assert first_stop(GridConfig(stop_recur=1.3, stop_recur_decay=0.8), flicker) == 24
    assert first_stop(GridConfig(stop_recur=1.3, stop_recur_decay=0.8), (20, 21)) is None
    # the default (1.3, decay 0.7: 1 + 0.7^3 = 1.343 three cycles after) likewise
    assert GridConfig().stop_recur == 1.3 and GridConfig().stop_recur_decay == 0.7
    assert first_stop(GridConfig(), flicker) == 24
    assert first_stop(GridConfig(), (20, 21)) is None
    with pytest.raises(Exception, match="stop_recur_decay"):
        from appliance.config import parse_config
        parse_config({"grid": {"stop_recur_decay": 1.5}}, "<t>")


def test_stop_chain_is_validated_and_reset_by_a_gap():
    """Out-of-range values are config errors naming the key; a gap in the stamps (> 2 s)
    forgets the chains like the evidence."""
    from appliance.config import parse_config
    from hal.errors import ConfigError
    with pytest.raises(ConfigError, match="stop_chain"):
        parse_config({"grid": {"stop_chain": -1}}, "<t>")
    with pytest.raises(ConfigError, match="stop_chain_radius_m"):
        parse_config({"grid": {"stop_chain_radius_m": 5.0}}, "<t>")
    core = DecisionCore(_chain_cfg(3))
    p = np.array([[5.0, 0.0]])
    for k in range(3):
        core.perceive({"s": Detections(points_xy=p)}, VehicleState(k * DT, k), k * DT)
    assert core.grid.chain_at(p)[0] == 3
    core.perceive({"s": Detections(points_xy=p)}, VehicleState(10**10, 9), 10**10)
    assert core.grid.chain_at(p)[0] == 1


def _stop_cycles(cfg: Config, frames: list[dict], speed: float = 0.0) -> list[bool]:
    core = DecisionCore(cfg)
    return [core.perceive(f, VehicleState(0, 0, speed_mps=speed), k * DT).verdict.in_stop > 0
            for k, f in enumerate(frames)]


def _stereo(x, y, conf=0.9):
    from appliance.perception import Candidate
    pts = blob(x, y, n=5)
    c = Candidate(x_m=x, y_m=y, length_m=0.5, width_m=0.5, height_m=0.6, points=60,
                  confidence=conf, sources=("geometry", "novelty"), pipeline="stereo-novelty")
    return {"stereo-novelty": Detections(points_xy=pts, candidates=(c,))}


def test_an_obstacle_first_seen_in_the_stop_zone_stops_on_the_same_cycle_as_the_cells():
    """#14 item 6, stubble-day 1 frame 164: a crate the perception had lost came back 3.4 m
    ahead, inside the stop zone; the cells stopped on the cycle its cell was occupied, the
    tracks one cycle later (a new track needs two frames). A candidate with a cell in the stop
    zone and strong geometry (or laser) evidence now confirms at once."""
    frames = [_stereo(3.5, 0.0) for _ in range(4)]       # stop zone 2.6 .. 4.6 m at standstill
    cells = _stop_cycles(Config(grid=GridConfig(stop_recur=0.0)), frames)   # the papers' rule
    tracks = _stop_cycles(tracks_cfg(), frames)
    assert cells == [False, True, True, True]             # the grid's two hits
    assert tracks == cells
    # the default cell decision (stop_recur) asks a first-seen stop-zone cell for one cycle
    # more: what it costs (docs/tracking.md, "stop_recur on the acceptance seeds")
    assert _stop_cycles(Config(), frames) == [False, False, True, True]
    # only in the stop zone, and only on strong evidence: a weak candidate there waits
    assert _stop_cycles(tracks_cfg(), [_stereo(3.5, 0.0, conf=0.3) for _ in range(4)])[1] is False
    assert _stop_cycles(tracks_cfg(stop_zone_strength=0.0), frames)[1] is False
    # and only in the stop zone: the same candidate 8 m ahead (slow zone) is confirmed after
    # the frames its range and size need (3 tracker frames here), not at once
    core = DecisionCore(tracks_cfg())
    slow = [core.perceive(f, VehicleState(0, 0), k * DT).verdict.in_slow > 0
            for k, f in enumerate([_stereo(8.0, 0.0) for _ in range(4)])]
    assert core.tracker.frames_needed(8.0, 0.5) == 3
    assert slow == [False, False, False, True]


def test_a_laser_return_cluster_confirms_on_the_grids_second_hit():
    """A pole two laser beams hit (the front end's laser candidate: confidence 0.18): with the
    laser's strength scaled by its return count it needed 12 frames to confirm; a laser return
    cluster is a measured surface, so it confirms when the grid holds it (two cycles), as the
    cell decision stops for it."""
    from appliance.perception import Candidate
    pts = np.array([[4.0, 0.02], [4.0, 0.07]])
    c = Candidate(x_m=4.0, y_m=0.045, length_m=0.2, width_m=0.2, height_m=0.7, points=2,
                  confidence=0.18, sources=("laser",), pipeline="laser")
    frames = [{"laser": Detections(points_xy=pts, candidates=(c,))} for _ in range(4)]
    now = Config(grid=GridConfig(stop_recur_now=("laser",)))     # a laser cell stops at once
    assert _stop_cycles(now, frames) == [False, True, True, True]
    assert _stop_cycles(tracks_cfg(), frames) == [False, True, True, True]
    # the default cell decision waits for the recurrence, the laser's cells too (a cycle later)
    assert _stop_cycles(Config(), frames) == [False, False, True, True]
    # off the stop zone too (the stop-zone rule does not apply): 8 m ahead, a SLOW at once
    far = [{"laser": Detections(points_xy=pts + [4.0, 0.0], candidates=(
        dataclasses.replace(c, x_m=8.0),))} for _ in range(3)]
    core = DecisionCore(tracks_cfg())
    slow = [core.perceive(f, VehicleState(0, 0), k * DT).verdict.in_slow > 0
            for k, f in enumerate(far)]
    assert slow == [False, True, True]
    core = DecisionCore(tracks_cfg(laser_fast=False))
    far = far + far * 4
    slow = [core.perceive(f, VehicleState(0, 0), k * DT).verdict.in_slow > 0
            for k, f in enumerate(far)]
    assert slow.index(True) == 12          # 0.18 a frame from the grid's second hit on


def test_a_track_whose_cells_reach_into_the_stop_zone_is_a_stop():
    """#14: the zone test was written three times and the track decision's differed from the
    cells': a thing whose cells' centres are 3 cm beyond the stop zone's end while the cells
    (where its hits are) reach 2 cm into it. The cell decision stopped for it; the track
    decision slowed for it, its tracks neither confirmed at once (stop_zone_strength) nor in
    the stop zone. One test now (appliance/zones.py footprints_meet): both STOP on the same
    cycle, through the decision core and the gate."""
    zones = ZonesConfig(min_stop_m=2.02)          # at standstill: stop zone 2.6 .. 4.62 m
    pts = np.array([[4.66, y] for y in (-0.25, -0.15, -0.05, 0.05, 0.15, 0.25)])  # 4.6-4.7

    def run(cfg):
        core = DecisionCore(cfg)
        outs = []
        for k in range(10):
            pic = core.perceive({"stereo": Detections(points_xy=pts)}, VehicleState(k * DT, k),
                                k * DT)
            outs.append((pic, core.decide(k * DT, [], pic), core.gate.cause))
        return outs

    cells = run(Config(gate=GateConfig(hold_off_s=0.3), zones=zones,
                       grid=GridConfig(stop_recur=0.0)))            # the papers' cell rule
    tracks = run(dataclasses.replace(tracks_cfg(), zones=zones))
    pic, out, cause = tracks[-1]
    assert len(pic.objects) == 1 and pic.objects[0].x_m > 4.62 + 0.02   # its centre: outside
    assert np.all(pic.cells_xy[:, 0] > 4.62)                            # its cells' centres too
    assert [p.verdict.in_stop > 0 for p, _, _ in cells] == [False] + [True] * 9
    assert [p.verdict.in_stop > 0 for p, _, _ in tracks] == [False] + [True] * 9
    assert out.state is GateState.STOP and cause == "obstacle"
    assert "track" in out.reason and "in the stop zone" in out.reason


def test_stop_recur_the_default_waits_one_cycle_for_a_camera_cell_and_a_laser_return():
    """The default cell decision (stop_recur 1.3, decay 0.7): a stop-zone cell occupied in one
    cycle only is a SLOW ("unconfirmed"), occupied again it is a STOP, the laser's cells
    included (``stop_recur_now = []`` since 2026-12-04: a tuft top the scan plane grazes comes
    and goes; docs/proving-ground.md "Tuft tops"). ``stop_recur_now = ["laser"]`` (the default
    before) stops on a laser cell's first occupied cycle. The papers' rule (stop_recur = 0)
    stops on the first occupied cycle for both."""
    def first_stop(cfg, source):       # the zone verdict's (the gate holds its boot STOP)
        core = DecisionCore(cfg)
        for k in range(4):
            pts = np.array([[4.05, 0.05]]) if source == "laser" else blob(4.0, 0.0)
            pic = core.perceive({source: Detections(points_xy=pts)}, VehicleState(k * DT, k),
                                k * DT)
            if pic.verdict.in_stop > 0:
                return k, pic.verdict
            last = pic.verdict
        return None, last
    default = Config(gate=GateConfig(hold_off_s=0.3))
    papers = Config(gate=GateConfig(hold_off_s=0.3), grid=GridConfig(stop_recur=0.0))
    assert first_stop(papers, "stereo-novelty")[0] == 1          # the grid's two hits
    assert first_stop(default, "stereo-novelty")[0] == 2
    core = DecisionCore(default)                   # the cycle between is a SLOW, and says why
    for k in range(2):
        pic = core.perceive({"laser": Detections(points_xy=np.array([[4.05, 0.05]]))},
                            VehicleState(k * DT, k), k * DT)
    assert pic.verdict.in_stop == 0 and pic.verdict.in_slow > 0
    assert "unconfirmed obstacle" in pic.verdict.slow_reason
    # a laser return: one cycle more than the papers' rule, like a camera cell
    assert first_stop(default, "laser")[0] == 2 and first_stop(papers, "laser")[0] == 1
    # a config that lists the laser stops for it at once
    laser_now = Config(gate=GateConfig(hold_off_s=0.3), grid=GridConfig(stop_recur_now=("laser",)))
    assert first_stop(laser_now, "laser")[0] == 1
    assert first_stop(laser_now, "stereo-novelty")[0] == 2
    from appliance.config import parse_config
    from hal.errors import ConfigError
    assert parse_config({"grid": {"stop_recur_now": ["laser", "rgbd"]}}, "<t>").grid \
        .stop_recur_now == ("laser", "rgbd")
    with pytest.raises(ConfigError, match="stop_recur_now"):
        parse_config({"grid": {"stop_recur_now": "laser"}}, "<t>")


# --- [tracking] movers: the cell decision, and a STOP for what walks into the vehicle -------
def _closed_loop(cfg, walker, seconds=8.0, source="laser"):
    """The vehicle (origin X, 2.5 m/s, straight along +x; its body 0.4 m behind the origin to
    2.6 m ahead, 1.5 m wide, as the simulator's) driven by the core's gate: on STOP it brakes
    at 2 m/s^2 after the 0.5 s reaction, on SLOW it goes 1 m/s. ``walker(t)``: its world
    centre (0.3 m x 0.45 m). Returns the first STOP time, the first contact time (None) and
    the gate's outputs."""
    core = DecisionCore(cfg)
    x_v, v, braking_at = 0.0, 2.5, None
    first_stop = contact = None
    outs = []
    for k in range(int(seconds * 10)):
        t = k / 10
        wx, wy = walker(t)
        pts = _body(wx - x_v, wy)
        pic = core.perceive({source: Detections(points_xy=pts)},
                            VehicleState(k * DT, k, speed_mps=v), k * DT)
        out = core.decide(k * DT, [], pic)
        outs.append(out)
        booting = k < 10                 # the gate's STOP while it boots (hold_off_s)
        if out.state is GateState.STOP and first_stop is None and not booting:
            first_stop = t
        if out.state is GateState.STOP and braking_at is None and not booting:
            braking_at = t + 0.5
        if contact is None and (abs(wx - (x_v + 1.1)) < 1.5 + 0.15 and abs(wy) < 0.75 + 0.225):
            contact = t
        if braking_at is not None and t >= braking_at:
            v = max(0.0, v - 0.2)
        elif braking_at is None and out.state is GateState.SLOW and not booting:
            v = max(1.0, v - 0.2)
        x_v += v * 0.1
    return first_stop, contact, outs


def _movers_cfg(on: bool) -> Config:
    return Config(gate=GateConfig(hold_off_s=1.0), zones=ZonesConfig(front_x_m=2.6),
                  tracking=TrackingConfig(movers=on))


def _setting_off(x0, y0, vx, vy, at_s):
    """Stands at (x0, y0) until ``at_s``, then walks at (vx, vy)."""
    return lambda t: (x0 + vx * max(0.0, t - at_s), y0 + vy * max(0.0, t - at_s))


def test_movers_stop_for_a_person_walking_into_the_side_that_the_cells_drive_into():
    """Training seed 15's crossing person (docs/tracking.md 'Movers'): standing 4.1 m to the
    right, 3.3 m ahead of the front when it sets off at 1.3 m/s (0.53, 1.18) towards the lane.
    It never stands in the stop zone: it meets the vehicle's side. The cells drive into it
    with the box CLEAR; with movers the box stops in time and nothing is met."""
    walker = _setting_off(2.6 + 2.0 * 2.5 + 3.3, -4.1, 0.53, 1.18, 2.0)
    stop_off, contact_off, outs_off = _closed_loop(_movers_cfg(False), walker)
    assert contact_off is not None
    assert stop_off is None or stop_off >= contact_off - 0.5     # no STOP in time
    stop_on, contact_on, outs_on = _closed_loop(_movers_cfg(True), walker)
    assert contact_on is None, (stop_on, contact_on)
    assert 2.0 < stop_on < 3.0
    reason = outs_on[int(round(stop_on * 10))].reason
    assert "moving obstacle track" in reason and "meets the vehicle in" in reason
    assert "aside" in reason


def test_movers_do_not_stop_for_a_walker_crossing_well_ahead_or_walking_alongside():
    """What a forward STOP would not help: a walker that crosses 15 m ahead and is gone long
    before the vehicle gets there, one walking alongside 2.5 m beside the path, a post 2 m
    beside the path seen with 5 cm of jitter. No STOP, with or without movers."""
    rng = np.random.default_rng(3)
    jitter = rng.normal(0.0, 0.05, (100, 2))
    cases = {
        "crossing ahead": _setting_off(2.6 + 17.0, -3.0, 0.0, 1.5, 1.0),
        "alongside": _setting_off(2.6 + 8.0, 2.5, 1.5, 0.0, 0.0),
        "post": lambda t: (30.0 + jitter[int(t * 10), 0], 2.1 + jitter[int(t * 10), 1]),
    }
    for name, walker in cases.items():
        for on in (False, True):
            stop, contact, _ = _closed_loop(_movers_cfg(on), walker, seconds=10.0)
            assert stop is None and contact is None, (name, on, stop, contact)


def test_movers_wait_for_a_velocity_seen_over_frames_and_keep_the_cells_stop():
    """A mover needs movers_min_run frames in a row before it is predicted; once in the stop
    zone the STOP is the cells' (their reason), movers on or not. Open loop at 2.5 m/s: a
    person first seen already walking in at 1.3 m/s from 3 m to the right, 6 m ahead."""
    cfg = _movers_cfg(True)
    core = DecisionCore(cfg)
    assert core.movers is not None and core.tracker is None
    assert DecisionCore(Config(tracking=TrackingConfig(movers=True, enabled=True))).movers is None
    verdicts = []
    for k in range(20):
        pts = _body(2.6 + 6.0 - 0.25 * k, -3.0 + 0.13 * k)
        pic = core.perceive({"laser": Detections(points_xy=pts)},
                            VehicleState(k * DT, k, speed_mps=2.5), k * DT)
        verdicts.append(pic.verdict)
    moving = [k for k, v in enumerate(verdicts)
              if v.in_stop and v.stop_reason and "moving obstacle" in v.stop_reason]
    assert moving and moving[0] >= cfg.tracking.movers_min_run - 1, moving
    cells = [k for k, v in enumerate(verdicts) if v.in_stop and v.stop_reason is None]
    assert cells and cells[0] > moving[0]        # the cells see it only once it is there
    assert all(k in moving or k in cells for k in range(moving[0], 20))   # held throughout


def test_the_loop_with_movers_keeps_a_standing_vehicle_from_a_person_walking_into_its_side():
    """The loop with the real laser pipeline and [tracking] movers: the vehicle stands (the
    zones' front 2.6 m), a person (the laser's 0.3 m at 0.7 m) walks at 1.3 m/s from 3 m to
    the right towards the vehicle's side just behind the front. The stop zone is ahead of the
    front, so the cells never stop; the movers do (before it arrives: the horizon at standstill
    is reaction_time_s + 0.5 s), name it, and status says so."""
    for movers in (False, True):
        cfg = Config(gate=GateConfig(hold_off_s=0.3), tracking=TrackingConfig(movers=movers))
        clock, loop, laser, link = make_loop(cfg)
        for _ in range(6):
            loop.cycle()
            clock.advance(DT)
        assert loop.gate.state is GateState.CLEAR
        first = None
        for k in range(14):
            y = -3.0 + 0.13 * k
            laser.put_obstacle(2.4, y)
            out = loop.cycle().output
            clock.advance(DT)
            if out.state is GateState.STOP and first is None:
                first = (k, y, out.reason)
        st = loop.status()
        if not movers:
            assert first is None and st["obstacles"]["decision"] == "cells"
            continue
        assert first is not None, "the movers did not stop"
        k, y, reason = first
        assert y < -1.25 - 0.15 and "moving obstacle track" in reason and "(laser)" in reason
        assert st["obstacles"]["decision"] == "cells+movers"
        assert st["tracks"] and st["tracks"][0]["sources"] == ["laser"]
        assert link.sent[-1].state is GateState.STOP


def _rgbd_frame(x, y, points, n=8):
    from appliance.perception import Candidate
    pts = blob(x, y, n=n)
    c = Candidate(x_m=x, y_m=y, length_m=0.4, width_m=0.4, height_m=0.5, points=points,
                  confidence=0.9, sources=("geometry", "colour"), pipeline="rgbd")
    return {"rgbd": Detections(points_xy=pts, candidates=(c,))}


@pytest.mark.parametrize("points, occupied_first", [(400, True), (299, False)])
def test_a_large_rgbd_candidate_is_occupied_on_its_first_frame(points, occupied_first):
    """[grid] confirm_points (#14: fewer frames when near and large): the cells of a candidate
    of at least confirm_points points are occupied at once; a smaller one waits for the
    second look, as every cell did before. A STOP still needs the recurrence."""
    cfg = Config(grid=GridConfig(confirm_points=300))
    core = DecisionCore(cfg)
    pic = core.perceive(_rgbd_frame(4.5, 0.0, points), VehicleState(0, 0), 0)
    assert (len(pic.cells_xy) > 0) is occupied_first
    assert pic.verdict.in_stop == 0                 # occupied once: SLOW at most, not STOP
    pic = core.perceive(_rgbd_frame(4.5, 0.0, points), VehicleState(DT, 0), DT)
    assert len(pic.cells_xy) > 0                    # two looks: occupied either way


def test_confirm_points_off_and_only_for_the_named_pipelines():
    g = GridConfig()                                    # on, beyond a metre of the front
    assert (g.confirm_points, g.confirm_min_ahead_m) == (300, 1.0)
    core = DecisionCore(Config(grid=GridConfig(confirm_points=0)))
    assert not len(core.perceive(_rgbd_frame(4.5, 0.0, 5000), VehicleState(0, 0), 0).cells_xy)
    cfg = Config(grid=GridConfig(confirm_points=300, confirm_pipelines=("laser",)))
    core = DecisionCore(cfg)
    assert not len(core.perceive(_rgbd_frame(4.5, 0.0, 5000), VehicleState(0, 0), 0).cells_xy)


def test_confirm_pipelines_names_are_checked(tmp_path):
    from appliance.config import ConfigError, load_config
    f = tmp_path / "c.toml"
    f.write_text('[grid]\nconfirm_pipelines = ["rgdb"]\n')
    with pytest.raises(ConfigError, match="unknown pipeline 'rgdb'"):
        load_config(f)
    f.write_text('[grid]\nstop_recur_now = ["lazer"]\n')
    with pytest.raises(ConfigError, match="grid.stop_recur_now"):
        load_config(f)


def test_confirm_points_finds_rgbd_candidates_inside_the_fused_pipeline():
    frame = _rgbd_frame(4.5, 0.0, 400)
    fused = {"fused": frame["rgbd"]}                # the candidate still names "rgbd"
    core = DecisionCore(Config(grid=GridConfig(confirm_points=300)))
    assert len(core.perceive(fused, VehicleState(0, 0), 0).cells_xy) > 0


def test_confirm_sources_keeps_a_texture_only_candidate_to_the_second_look():
    cfg = Config(grid=GridConfig(confirm_points=300, confirm_sources=("colour",)))
    frame = _rgbd_frame(4.5, 0.0, 400)                       # sources geometry + colour
    assert len(DecisionCore(cfg).perceive(frame, VehicleState(0, 0), 0).cells_xy) > 0
    d = frame["rgbd"]
    tex = dataclasses.replace(d.candidates[0], sources=("geometry", "texture"))
    frame = {"rgbd": dataclasses.replace(d, candidates=(tex,))}
    assert not len(DecisionCore(cfg).perceive(frame, VehicleState(0, 0), 0).cells_xy)


def test_confirm_min_ahead_keeps_a_candidate_near_the_front_to_the_second_look():
    """[grid] confirm_min_ahead_m: a bush row faced 0.6-0.8 m ahead at an end bay is not
    believed on one frame; the same candidate further out is."""
    zones = ZonesConfig(front_x_m=1.1)
    cfg = Config(zones=zones, grid=GridConfig(confirm_points=300, confirm_min_ahead_m=1.0))
    # near edge at 3.5 - 0.2 = 3.3 m: 2.2 m ahead of the front -> at once
    assert len(DecisionCore(cfg).perceive(_rgbd_frame(3.5, 0.0, 400), VehicleState(0, 0),
                                          0).cells_xy) > 0
    # near edge at 2.0 - 0.2 = 1.8 m: 0.7 m ahead of the front -> waits
    core = DecisionCore(cfg)
    assert not len(core.perceive(_rgbd_frame(2.0, 0.0, 400), VehicleState(0, 0), 0).cells_xy)
    assert len(core.perceive(_rgbd_frame(2.0, 0.0, 400), VehicleState(DT, 0), DT).cells_xy) > 0
    # 0: anywhere, as before
    cfg = Config(zones=zones, grid=GridConfig(confirm_points=300, confirm_min_ahead_m=0.0))
    assert len(DecisionCore(cfg).perceive(_rgbd_frame(2.0, 0.0, 400), VehicleState(0, 0),
                                          0).cells_xy) > 0
