from appliance.config import GateConfig, ZonesConfig
from appliance.gate import SafetyGate
from appliance.zones import ZoneVerdict
from hal import GateState

S = 10**9


def verdict(in_stop=0, in_slow=0, nearest=None):
    return ZoneVerdict(3.0, 8.0, in_stop, in_slow, nearest, ())


def test_boots_in_stop_with_reason():
    g = SafetyGate(GateConfig(hold_off_s=1.0), ZonesConfig())
    assert g.state is GateState.STOP and "boot" in g.reason


def test_hold_off_before_clear():
    g = SafetyGate(GateConfig(hold_off_s=1.0), ZonesConfig())
    states = [g.decide(int(i * 0.1 * S), [], verdict()).state for i in range(15)]
    # clear from t=0: released at t >= 1.0 s (cycle 10), not before
    assert states[:10] == [GateState.STOP] * 10
    assert states[10] is GateState.CLEAR


def test_obstacle_stops_at_once_and_break_restarts_hold_off():
    g = SafetyGate(GateConfig(hold_off_s=0.5), ZonesConfig())
    t = 0
    for _ in range(10):
        out = g.decide(t, [], verdict())
        t += S // 10
    assert out.state is GateState.CLEAR
    out = g.decide(t, [], verdict(in_stop=3, nearest=2.0))
    assert out.state is GateState.STOP and "2.0 m" in out.reason
    t += S // 10
    # clear for 0.3 s, then a one-cycle flicker, then clear again: the hold-off starts over
    for _ in range(3):
        assert g.decide(t, [], verdict()).state is GateState.STOP
        t += S // 10
    assert g.decide(t, [], verdict(in_stop=1, nearest=2.5)).state is GateState.STOP
    t += S // 10
    seen = []
    for _ in range(8):
        seen.append(g.decide(t, [], verdict()).state)
        t += S // 10
    assert seen[:5] == [GateState.STOP] * 5 and seen[5] is GateState.CLEAR


def test_fault_is_stop_with_named_reason_even_when_clear():
    g = SafetyGate(GateConfig(hold_off_s=0.0), ZonesConfig())
    assert g.decide(0, [], verdict()).state is GateState.CLEAR
    out = g.decide(S // 10, ["laser: stale"], verdict())
    assert out.state is GateState.STOP and out.reason == "laser: stale"
    out = g.decide(2 * S // 10, ["laser: stale", "link: no data"], verdict())
    assert out.reason == "laser: stale (+1 more)"


def test_slow_zone_and_no_picture():
    g = SafetyGate(GateConfig(hold_off_s=0.0), ZonesConfig(slow_speed_mps=0.8))
    out = g.decide(0, [], verdict(in_slow=2, nearest=6.0))
    assert out.state is GateState.SLOW and out.speed_limit_mps == 0.8
    assert g.decide(1, [], None).state is GateState.STOP


def test_counter_rolls_and_checksum_changes():
    g = SafetyGate(GateConfig(hold_off_s=0.0), ZonesConfig())
    a = g.decide(0, [], verdict())
    b = g.decide(1, [], verdict())
    assert b.seq == (a.seq + 1) & 0xFFFF
    assert a.checksum() != b.checksum() or a.seq != b.seq
