"""The daemon's memory account (glibc's mallinfo2, Python's live blocks) and the heap trim that
gives freed arena pages back to the system (appliance/memory.py): a soak tells a leak from
fragmentation with them, and a box running for weeks holds what it uses."""
import dataclasses
import threading
import time

import pytest

from appliance import memory
from appliance.config import default_config, load_config
from appliance.daemon import Daemon, sim_config
from appliance.status import read_status
from hal.errors import ConfigError

glibc = pytest.mark.skipif(memory.malloc_stats() is None, reason="not glibc (no mallinfo2)")


@glibc
def test_in_use_follows_what_the_program_holds():
    before = memory.malloc_stats()["in_use_mb"]
    held = [bytes([i % 251]) * 1000 for i in range(20_000)]          # ~20 MB of small blocks
    during = memory.malloc_stats()["in_use_mb"]
    del held
    after = memory.malloc_stats()["in_use_mb"]
    assert during - before > 15
    assert during - after > 15


@glibc
def test_trim_gives_the_holes_in_the_heap_back():
    # 160 MB in 64 KB blocks (below glibc's mmap threshold: they come from the arena), every
    # page touched; then all freed but the last, which pins the top of the heap so that free()
    # cannot shrink it: the freed 160 MB stay resident inside the arena until a trim
    blocks = [bytes([i % 251]) * 65536 for i in range(2560)]
    pin = blocks[-1]
    del blocks
    held = memory.resident_mb()
    stats = memory.malloc_stats()
    assert stats["free_mb"] > 100, stats
    assert memory.trim() is True
    assert held - memory.resident_mb() > 100
    assert memory.malloc_stats()["free_mb"] > 100       # still free, no longer resident
    del pin


@glibc
def test_the_keeper_trims_on_its_own_thread_and_reports():
    k = memory.MemoryKeeper(trim_s=0.05)
    k.start()
    names = [t.name for t in threading.enumerate()]
    deadline = time.monotonic() + 10
    while k.trims < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    k.stop()
    assert "memory" in names
    doc = k.status()
    assert doc["trims"] >= 2 and doc["trim_s"] == 0.05
    assert doc["trim_ms_max"] >= doc["trim_ms_last"] >= 0
    assert doc["malloc"]["in_use_mb"] > 0 and doc["py_blocks"] > 1000
    assert "memory" not in [t.name for t in threading.enumerate()]


def test_zero_means_never():
    k = memory.MemoryKeeper(trim_s=0)
    k.start()
    time.sleep(0.1)
    k.stop()
    assert k.trims == 0 and k._thread is None
    assert k.status()["trims"] == 0


def test_the_interval_is_validated(tmp_path):
    p = tmp_path / "f.toml"
    p.write_text("[status]\nmalloc_trim_s = -1\n")
    with pytest.raises(ConfigError, match="malloc_trim_s"):
        load_config(p)
    p.write_text("[status]\nmalloc_trim_s = 0\n")
    assert load_config(p).status.malloc_trim_s == 0


@glibc
def test_the_running_daemon_reports_its_memory(tmp_path):
    cfg = default_config()
    cfg = dataclasses.replace(cfg, perception=dataclasses.replace(
        cfg.perception, pipelines=("laser",)), status=dataclasses.replace(
        cfg.status, malloc_trim_s=0.2))
    sock = str(tmp_path / "run" / "status.sock")
    d = Daemon(sim_config(cfg), mode="sim", pace=1.0, status_socket=sock)
    d.start()
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 60
        doc = read_status(sock)
        while doc["memory"]["trims"] < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
            doc = read_status(sock)
        mem = doc["memory"]
        assert mem["trims"] >= 1 and mem["trim_s"] == 0.2
        assert mem["malloc"]["in_use_mb"] > 1 and mem["malloc"]["arena_mb"] > 0
    finally:
        d.request_stop()
        th.join(10)
        d.shutdown()
    assert d.memory._thread is None                     # shut down with the daemon
