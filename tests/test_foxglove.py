"""Foxglove: MCAP files (`fieldguard export`, read back with the `mcap` package and decoded with
the schemas they carry) and the foxglove-sdk's live WebSocket server (a real websocket client,
the SDK's subprotocol)."""
import dataclasses
import json
import socket
import struct
import time

import pytest
from mcap.reader import make_reader

from appliance.cli import main
from appliance.config import ConsoleConfig, FoxgloveConfig, default_config
from appliance.daemon import Daemon, sim_config
from drivers.sim.record import write_sim_run

FRAMES = 8


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("fox") / "run"
    write_sim_run("stubble-day", FRAMES, path, sensors=("laser", "rgbd"))
    return path


def decoder(schema):
    """The protobuf message class of a foxglove schema, from the descriptor set in the file."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


def read_mcap(path):
    with open(path, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        msgs = {}
        for schema, channel, message in r.iter_messages():
            msgs.setdefault(channel.topic, []).append((schema, message))
    topics = {c.topic: (summary.schemas[c.schema_id].name, c.message_encoding,
                        summary.statistics.channel_message_counts[cid])
              for cid, c in summary.channels.items()}
    return topics, msgs


def test_export_writes_images_grid_scene_laser_and_state_in_foxglove_schemas(sim_run, tmp_path,
                                                                              capsys):
    out = tmp_path / "run.mcap"
    assert main(["export", str(sim_run), "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    topics, msgs = read_mcap(out)
    want = {"/camera/image": "foxglove.CompressedImage", "/camera/depth": "foxglove.RawImage",
            "/laser": "foxglove.LaserScan", "/grid": "foxglove.Grid",
            "/scene": "foxglove.SceneUpdate", "/log": "foxglove.Log",
            "/truth": "foxglove.SceneUpdate", "/state": "fieldguard.State",
            "/vehicle": "fieldguard.Vehicle"}
    for topic, schema in want.items():
        assert topics[topic][0] == schema, topic
    assert topics["/state"][1] == "json" and topics["/grid"][1] == "protobuf"
    # every recorded frame once; the box's picture and state every cycle
    for t in ("/camera/image", "/camera/depth", "/laser", "/truth", "/vehicle"):
        assert topics[t][2] == FRAMES, t
    cycles = topics["/state"][2]
    assert cycles >= FRAMES and topics["/grid"][2] == cycles and topics["/scene"][2] == cycles
    # decoded with the schema the file carries
    schema, m = msgs["/camera/image"][0]
    img = decoder(schema).FromString(m.data)
    assert img.format == "jpeg" and img.data[:2] == b"\xff\xd8"
    schema, m = msgs["/grid"][-1]
    g = decoder(schema).FromString(m.data)
    cfg = default_config().grid
    nx = round((cfg.x_max_m - cfg.x_min_m) / cfg.cell_m)
    ny = round((cfg.y_max_m - cfg.y_min_m) / cfg.cell_m)
    assert g.column_count == nx and g.cell_stride == 5 and len(g.data) == 5 * nx * ny
    assert [f.name for f in g.fields] == ["evidence", "occupied"]
    occupied = sum(1 for _, m in msgs["/grid"] if any(decoder(schema).FromString(m.data)
                                                      .data[4::5]))
    assert occupied > 0                       # the laser saw the course's obstacles
    schema, m = msgs["/laser"][0]
    scan = decoder(schema).FromString(m.data)
    assert len(scan.ranges) == 541 and scan.frame_id == "vehicle"
    schema, m = msgs["/truth"][0]
    truth = decoder(schema).FromString(m.data)
    assert all(e.cubes for e in truth.entities)
    schema, m = msgs["/scene"][0]
    ids = {e.id for e in decoder(schema).FromString(m.data).entities}
    assert {"stop_zone", "slow_zone", "vehicle"} <= ids
    states = [json.loads(m.data) for _, m in msgs["/state"]]
    assert states[0]["state"] == "STOP" and all(s["state"] in ("STOP", "SLOW", "CLEAR")
                                                for s in states)
    assert [m.log_time for _, m in msgs["/state"]] == sorted(m.log_time for _, m in msgs["/state"])


def test_export_refuses_what_it_cannot_do_with_a_clear_error(sim_run, tmp_path, capsys):
    out = tmp_path / "a.mcap"
    out.write_bytes(b"old")
    assert main(["export", str(sim_run), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err and out.read_bytes() == b"old"
    assert main(["export", str(tmp_path / "nothing"), "--out", str(tmp_path / "b.mcap")]) == 2
    assert "fieldguard: error:" in capsys.readouterr().err
    assert main(["export", str(sim_run), "--out", str(tmp_path / "no" / "c.mcap")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert main(["export", str(sim_run), "--out", str(tmp_path / "d.txt")]) == 2
    assert ".mcap" in capsys.readouterr().err


def test_export_carries_the_state_the_box_had_when_it_recorded(tmp_path):
    """A recording the daemon made has gate_state columns: they go out as /recording/state."""
    from appliance.recorder import Recorder
    cfg = sim_config(dataclasses.replace(default_config(),
                                         console=ConsoleConfig(listen="")))
    d = Daemon(cfg, mode="sim", pace=0.0, serve_status=False)
    d.start()
    rec = Recorder(10.0)
    d.loop.on_cycle.append(rec.on_cycle)
    try:
        job = rec.record(1.0, str(tmp_path / "rec"), d.clock.now_ns())
        d.run(max_cycles=15)
        rec.close()
        assert job.done.wait(10) and job.error is None and job.written >= 9
    finally:
        d.shutdown()
    assert main(["export", str(tmp_path / "rec"), "--out", str(tmp_path / "rec.mcap")]) == 0
    topics, msgs = read_mcap(tmp_path / "rec.mcap")
    assert topics["/recording/state"][0] == "fieldguard.RecordedState"
    assert topics["/recording/state"][2] == job.written
    rec_states = [json.loads(m.data)["state"] for _, m in msgs["/recording/state"]]
    assert set(rec_states) <= {"STOP", "SLOW", "CLEAR"} and rec_states


# -- the live server ------------------------------------------------------------------------------
def fox_daemon(tmp_path, listen):
    cfg = dataclasses.replace(default_config(), console=ConsoleConfig(listen="", rate_hz=10),
                              foxglove=FoxgloveConfig(listen=listen))
    d = Daemon(sim_config(cfg), mode="sim", pace=0.0, status_socket=str(tmp_path / "s.sock"))
    d.start()
    return d


def test_live_server_advertises_the_channels_and_streams_the_state(tmp_path):
    import websocket
    d = fox_daemon(tmp_path, "127.0.0.1:0")
    ws = None
    try:
        url = d.console.foxglove.url
        assert url.startswith("ws://127.0.0.1:")
        # the SDK 0.30 speaks foxglove.sdk.v1 (it refuses the older foxglove.websocket.v1)
        ws = websocket.create_connection(url, subprotocols=["foxglove.sdk.v1"], timeout=10)
        assert ws.subprotocol == "foxglove.sdk.v1"
        info = json.loads(ws.recv())
        assert info["op"] == "serverInfo" and info["name"] == "fieldguard"
        adv = json.loads(ws.recv())
        assert adv["op"] == "advertise"
        chans = {c["topic"]: c for c in adv["channels"]}
        assert chans["/grid"]["schemaName"] == "foxglove.Grid"
        assert chans["/scene"]["schemaName"] == "foxglove.SceneUpdate"
        assert chans["/laser"]["schemaName"] == "foxglove.LaserScan"
        assert chans["/camera/annotated"]["schemaName"] == "foxglove.CompressedImage"
        assert chans["/state"]["encoding"] == "json"
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 1, "channelId": chans["/state"]["id"]},
            {"id": 2, "channelId": chans["/grid"]["id"]}]}))
        got = {}
        t0 = time.monotonic()
        while len(got) < 2:
            assert time.monotonic() - t0 < 20, f"only {sorted(got)} arrived"
            d.run(max_cycles=3)
            ws.settimeout(0.5)
            try:
                frame = ws.recv()
            except websocket.WebSocketTimeoutException:
                continue
            if isinstance(frame, bytes) and frame[0] == 1:       # MessageData
                sub_id, _log_time = struct.unpack_from("<IQ", frame, 1)
                got[sub_id] = frame[13:]
        state = json.loads(got[1])
        assert state["state"] in ("STOP", "SLOW", "CLEAR") and "reason" in state
        assert len(got[2]) > 1000                               # a protobuf Grid
        assert d.console.foxglove.info()["views_sent"] >= 1
    finally:
        if ws is not None:
            ws.close()
        d.shutdown()


def test_live_server_on_a_taken_port_is_one_log_line_and_the_box_runs_on(tmp_path, caplog):
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen(1)
    port = blocker.getsockname()[1]
    try:
        with caplog.at_level("ERROR", logger="fieldguard.foxglove"):
            d = fox_daemon(tmp_path, f"127.0.0.1:{port}")
        try:
            d.run(max_cycles=10)
            st = d.status()
        finally:
            d.shutdown()
    finally:
        blocker.close()
    msgs = [r.getMessage() for r in caplog.records if r.name == "fieldguard.foxglove"]
    assert len(msgs) == 1 and f"127.0.0.1:{port}" in msgs[0] and "runs on" in msgs[0]
    assert st["cycles"] == 10 and st["console"]["foxglove"] is None
    assert "foxglove" in st["console"]["errors"][0]


def test_record_mcap_records_then_exports_for_foxglove(tmp_path, capsys):
    import threading
    cfg = dataclasses.replace(default_config(), console=ConsoleConfig(listen=""))
    sock = str(tmp_path / "s.sock")
    d = Daemon(sim_config(cfg), mode="sim", pace=1.0, status_socket=sock)
    d.start()
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    try:
        # a bad MCAP name is refused before anything is recorded
        assert main(["record", "--seconds", "1", "--out", str(tmp_path / "r0"), "--mcap",
                     str(tmp_path / "r0.txt"), "--socket", sock]) == 2
        assert ".mcap" in capsys.readouterr().err and not (tmp_path / "r0").exists()
        assert main(["record", "--seconds", "1", "--out", str(tmp_path / "rec"), "--mcap",
                     str(tmp_path / "rec.mcap"), "--socket", sock]) == 0
    finally:
        d.request_stop()
        th.join(10)
        d.shutdown()
    assert "wrote" in capsys.readouterr().out
    from drivers.runfolder import RunReader
    frames = len(RunReader(tmp_path / "rec"))
    topics, _ = read_mcap(tmp_path / "rec.mcap")
    assert frames >= 5
    assert topics["/recording/state"][2] == frames and topics["/laser"][2] == frames
    assert topics["/grid"][0] == "foxglove.Grid" and topics["/grid"][2] >= frames
