"""[grid] slow_recur: a cell in the slow zone makes a SLOW only when it recurs.

Found by the campaign's new ``slow_for_nothing_s`` (thirty-eighth session): on training stubble
drives 145-150 the camera box was SLOW with nothing real in its zones a quarter of the time,
half of it in the gate's 1 s hold after a slow-zone cell occupied for a cycle or two."""
from __future__ import annotations

import numpy as np
import pytest

from appliance.config import ConfigError, ZonesConfig, parse_config
from appliance.decision import DecisionCore
from appliance.perception.base import Detections
from appliance.zones import assess, stop_length
from hal.types import VehicleState

NS = 100_000_000
Z = ZonesConfig()


def _slow_cell(speed=2.5):
    """A cell centre in the slow zone, beyond the stop zone, on the vehicle's axis."""
    return np.array([[Z.front_x_m + stop_length(speed, Z) + 2.0, 0.0]])


def test_assess_counts_a_slow_zone_cell_only_when_flagged():
    c = _slow_cell()
    assert assess(c, 2.5, Z).in_slow == 1
    assert assess(c, 2.5, Z, slow_ok=np.array([True])).in_slow == 1
    v = assess(c, 2.5, Z, slow_ok=np.array([False]))
    assert v.in_slow == 0 and v.in_stop == 0
    # a stop-zone cell not yet confirmed for a STOP is a SLOW whatever slow_ok says
    s = np.array([[Z.front_x_m + 1.0, 0.0]])
    v = assess(s, 2.5, Z, confirmed=np.array([False]), slow_ok=np.array([False]))
    assert v.in_stop == 0 and v.in_slow == 1


def _drive(cfg, hits):
    """The decision with the vehicle standing, camera points on one slow-zone cell in the
    cycles ``hits`` says; the state per cycle."""
    core = DecisionCore(cfg)
    p = _slow_cell(0.0)
    out = []
    for i, hit in enumerate(hits):
        d = {"stereo-novelty": Detections(points_xy=p if hit else np.zeros((0, 2)))}
        pic = core.perceive(d, VehicleState(i * NS, i * NS, 0.0, 0.0), i * NS)
        v = pic.verdict
        out.append("STOP" if v.in_stop else "SLOW" if v.in_slow else "CLEAR")
    return out


def test_a_slow_zone_cell_occupied_once_makes_no_slow_one_that_recurs_does():
    on = parse_config({"grid": {"slow_recur": 1.3}}, "<t>")
    off = parse_config({}, "<t>")
    blip = [True, True, False, False, False, False]       # occupied in one cycle (two hits)
    assert "SLOW" in _drive(off, blip)
    assert _drive(on, blip) == ["CLEAR"] * 6
    held = [True] * 6                                      # there cycle after cycle
    states = _drive(on, held)
    assert states[:2] == ["CLEAR", "CLEAR"] and states[2:] == ["SLOW"] * 4
    assert _drive(off, held)[1:] == ["SLOW"] * 5           # one cycle sooner without it


def test_slow_recur_needs_the_recurrence_memory():
    with pytest.raises(ConfigError) as e:
        parse_config({"grid": {"slow_recur": 1.3, "stop_recur": 0.0}}, "<t>")
    assert "grid.slow_recur" in str(e.value)
    assert parse_config({}, "<t>").grid.slow_recur == 0.0
