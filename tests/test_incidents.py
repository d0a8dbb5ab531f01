"""The incident ring buffer: the seconds before and after a stop written as a run folder.

In its own module, away from tests/test_cli_ops.py's real-time daemon: that daemon runs in the
pytest process for the whole of its module, and a lock-step daemon beside it shares the GIL
with it (this test took 14-18 s there and 5 s alone)."""
import csv
import dataclasses

from appliance.config import StatusConfig, default_config
from appliance.daemon import Daemon, sim_config
from drivers.runfolder import RunReader


def test_incident_ring_buffer_keeps_the_seconds_before_a_stop(tmp_path):
    inc = tmp_path / "incidents"
    cfg = dataclasses.replace(default_config(), status=StatusConfig(
        incident_dir=str(inc), incident_seconds=1.0, incident_max=2))
    d = Daemon(sim_config(cfg), mode="sim", pace=0.0, serve_status=False)
    d.start()
    try:
        d.run(max_cycles=150)      # the vehicle stops for the first obstacle within ~8 s
    finally:
        d.shutdown()
    runs = sorted(p for p in inc.iterdir() if (p / "run.toml").exists())
    assert runs, "no incident written"
    assert len(runs) <= 2
    r = RunReader(runs[0])
    assert len(r) >= 10                       # 1 s before + 1 s after
    with open(runs[0] / "frames.csv") as f:
        states = [row["gate_state"] for row in csv.DictReader(f)]
    assert "STOP" in states and states[0] != "STOP"
    assert "stop" in runs[0].name.lower() or "obstacle" in runs[0].name.lower()
