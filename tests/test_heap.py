"""The daemon's heap measure (the soak's --heap): ``heap`` / ``heap PATH`` on the status socket
and tools/heap_diff.py naming the line that grew."""
from __future__ import annotations

import tracemalloc

from appliance.daemon import heap_request, heap_status
from tools.heap_diff import diff

_kept: list[bytes] = []


def _grow(n):
    for _ in range(n):
        _kept.append(bytes(10_000))


def test_heap_request_when_not_traced_is_a_clear_error():
    was = tracemalloc.is_tracing()
    if was:
        tracemalloc.stop()
    try:
        assert heap_status() is None
        doc = heap_request([])
        assert "PYTHONTRACEMALLOC" in doc["error"]
    finally:
        if was:
            tracemalloc.start()


def test_heap_snapshots_and_diff_name_the_growing_line(tmp_path):
    tracemalloc.start(1)
    try:
        a = heap_request([str(tmp_path / "a.snap")])
        _grow(200)                               # ~2 MB kept alive
        b = heap_request([str(tmp_path / "b.snap")])
        assert b["traced_mb"] - a["traced_mb"] > 1.5
        assert heap_request(["x", "y"])["error"].startswith("usage")
        bad = heap_request([str(tmp_path / "no" / "such" / "dir.snap")])
        assert "cannot write" in bad["error"]
    finally:
        tracemalloc.stop()
        _kept.clear()
    d = diff(str(tmp_path / "a.snap"), str(tmp_path / "b.snap"), top=3)
    top = d["top"][0]
    assert "test_heap.py" in top["where"] and top["count_diff"] >= 200
    assert top["size_diff_kb"] > 1900
