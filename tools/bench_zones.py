"""CPU time of the zone decision per call: assess_tracks (10 or 30 confirmed tracks, still or
moving, with their cells or footprints only) and assess (2000 cells), docs/tracking.md
"One zone test".

    taskset -c 1 nice -n 15 python tools/bench_zones.py [SRC]

SRC: the source tree to time (default: this one), e.g. a `git archive` of another commit.
"""
import sys
import time
from pathlib import Path

sys.path.insert(0, sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from appliance.config import Config  # noqa: E402
from appliance.decision import assess_tracks  # noqa: E402
from appliance.tracking import TrackView  # noqa: E402
from appliance.zones import assess  # noqa: E402


def per_call_ms(fn, budget_s: float = 1.0) -> float:
    t0, k = time.process_time(), 0
    while time.process_time() - t0 < budget_s:
        fn()
        k += 1
    return 1e3 * (time.process_time() - t0) / k


def main() -> int:
    rng = np.random.default_rng(1)
    cfg = Config()

    def track(i, moving):
        return TrackView(id=i, x_m=rng.uniform(3, 20), y_m=rng.uniform(-5, 5), length_m=0.5,
                         width_m=0.5, height_m=1.0, vx_mps=1.0 if moving else 0.0, vy_mps=0.0,
                         confidence=0.9, sources=("geometry",), confirmed=True, coasting=False,
                         hits=5, age_s=1.0)

    for n, moving in ((10, False), (30, False), (30, True)):
        tracks = [track(i, moving) for i in range(n)]
        by_id = {t.id: (np.floor(np.array([[t.x_m, t.y_m]]) / 0.1) + 0.5) * 0.1
                 + rng.uniform(-0.2, 0.2, (6, 2)).round(1) for t in tracks}
        cells = np.concatenate(list(by_id.values()))
        for label, ids in (("cells", by_id), ("footprints", None)):
            ms = per_call_ms(lambda: assess_tracks(tracks, cells, 2.5, cfg, ids))
            print(f"assess_tracks {n} tracks {'moving' if moving else 'still'} {label}: "
                  f"{ms:.3f} ms")
    c = rng.uniform([2, -10], [30, 10], (2000, 2))
    print(f"assess 2000 cells: {per_call_ms(lambda: assess(c, 2.5, cfg.zones, cell_m=0.1)):.3f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
