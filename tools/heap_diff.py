#!/usr/bin/env python3
"""What grew in the daemon's Python heap between two tracemalloc snapshots (the soak's --heap
dumps them, or ``fieldguard``'s status socket: ``heap PATH`` on a daemon started with
PYTHONTRACEMALLOC=N).

    .venv/bin/python tools/heap_diff.py FIRST.snap LAST.snap [--top 15] [--json]

Prints the total traced heap of each, and the source lines whose allocations grew (or shrank)
most, with the number of blocks: a leak is a line that keeps growing from snapshot to snapshot.
"""
from __future__ import annotations

import argparse
import json
import sys
import tracemalloc


def diff(first: str, last: str, top: int = 15, key: str = "lineno") -> dict:
    try:
        a = tracemalloc.Snapshot.load(first)
        b = tracemalloc.Snapshot.load(last)
    except (OSError, EOFError, ValueError) as exc:
        raise SystemExit(f"heap_diff: cannot read a snapshot: {exc}")
    ignore = [tracemalloc.Filter(False, tracemalloc.__file__)]
    a, b = a.filter_traces(ignore), b.filter_traces(ignore)
    stats = b.compare_to(a, key)
    return {
        "first_mb": round(sum(s.size for s in a.statistics("filename")) / 2**20, 3),
        "last_mb": round(sum(s.size for s in b.statistics("filename")) / 2**20, 3),
        "top": [{"where": str(s.traceback[0]) if s.traceback else "?",
                 "size_diff_kb": round(s.size_diff / 1024, 1), "size_kb": round(s.size / 1024, 1),
                 "count_diff": s.count_diff, "count": s.count}
                for s in stats[:top]],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("first")
    ap.add_argument("last")
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--by", choices=("lineno", "filename", "traceback"), default="lineno")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    d = diff(a.first, a.last, a.top, a.by)
    if a.json:
        print(json.dumps(d, indent=1))
        return 0
    print(f"traced heap: {d['first_mb']:.2f} MB -> {d['last_mb']:.2f} MB "
          f"({d['last_mb'] - d['first_mb']:+.2f} MB)")
    for t in d["top"]:
        print(f"{t['size_diff_kb']:+10.1f} kB {t['count_diff']:+7d} blocks  "
              f"(now {t['size_kb']:.1f} kB, {t['count']} blocks)  {t['where']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
