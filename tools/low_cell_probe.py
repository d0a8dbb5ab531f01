"""Could a solid body under the band's floor be told from the stubble by its dense points?
Open loop, training seeds: for every head-on dog of a drive the vehicle drives its lane at
cruise from ``--from`` m (plus 4 m to start matching) to 1.5 m before it, with every cell
matched (``novelty_gate = "all"``: what the dense points could say wherever they were asked).
The low points (``--low`` to ``--floor`` m above the local ground, 1-10.5 m ahead, |y| <= 1.4 m)
are binned in 0.2 m ground cells; per cell: the points, the points x range^2 (``nx2``: a
surface's point count falls with the square of its range), their vertical support (the share
of their column down to the ground with the same disparity: a standing surface has it), and
the spread of their heights (p90 - p10). Prints those per class (the dog's cells: within 0.15
m of its footprint; the field's: every other cell), then rules "support >= S, spread >= D,
nx2 >= N" by the share of frames in which a dog cell passes (the dog caught) and in which
a field cell passes (a false obstacle in the path that frame).

    python tools/low_cell_probe.py stubble-thin 95 [--dogs 4] [--from 10] [--tsv cells.tsv]

Training seeds only (< 1000).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

COLUMNS = ("dog", "dog_h", "frame", "dist", "is_dog", "n", "nx2", "support", "hspan", "x", "y")
RULES = [(s, d, n) for s in (0.8, 0.9) for d in (0.0, 0.05) for n in (800, 1200, 2000)]


def cells_of(kind: str, seed: int, dogs: int | None = None, start_m: float = 10.0,
             low: float = 0.25, floor: float = 0.5, progress=None) -> list[tuple]:
    """Rows of ``COLUMNS``, one per low-point cell per frame."""
    import cv2
    cv2.setNumThreads(1)
    from appliance.evaluation import footprint_distance
    from appliance.perception import SensorInputs
    from appliance.perception.stereo import scaled_calibration, vertical_support
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    from drivers.sim import SimField
    from hal.types import GateState
    f = SimField(kind, seed=seed, sensors=("stereo",), stereo_scale=0.5)
    heads = [o for o in f.world.obstacles if o.cls == "dog-head-on"][:dogs]
    rows, frame = [], 0
    for ob in heads:
        s_ob = f.scene.route_s_of(ob.x, ob.y)
        p = StereoNoveltyPipeline(dataclasses.replace(
            StereoNoveltyConfig(), model_state="off", novelty_gate="all"), background=False)
        f.vehicle.s = max(0.0, s_ob - start_m - 4.0)
        f.vehicle.speed = f.scene.cruise_mps
        seq = 0
        try:
            while f.vehicle.s < s_ob - 1.5:
                s = f.render(seq * 100_000_000, seq)
                tr = next((t for t in s.truth if t["id"] == ob.id), None)
                p.process(SensorInputs(stamp_ns=s.stereo.stamp_ns, stereo=s.stereo,
                                       vehicle=s.vehicle))
                f.step(0.1, GateState.CLEAR)
                seq += 1
                if tr is None or not (1.5 < tr["x_m"] < start_m) or abs(tr["y_m"]) > 1.2:
                    continue
                frame += 1
                pts, px, h, _keep, k = p.last_points
                sel = ((h >= low) & (h < floor) & (pts[:, 0] > 1) & (pts[:, 0] < 10.5)
                       & (np.abs(pts[:, 1]) < 1.4))
                idx = np.flatnonzero(sel)
                if len(idx) == 0:
                    continue
                sup = vertical_support(p.last_disp, px[idx], pts[idx],
                                       scaled_calibration(s.stereo.calib, k), p._ground,
                                       known_min=0.5)
                P, H = pts[idx], h[idx]
                keys, inv = np.unique(np.floor(P[:, :2] / 0.2).astype(int), axis=0,
                                      return_inverse=True)
                inv = inv.reshape(-1)
                for j, (ix, iy) in enumerate(keys):
                    m = inv == j
                    cx, cy = (ix + 0.5) * 0.2, (iy + 0.5) * 0.2
                    is_dog = footprint_distance(np.array([[cx, cy]]), tr)[0] <= 0.15
                    hh = H[m]
                    rows.append((ob.id, ob.height_m, frame, tr["x_m"], int(is_dog),
                                 int(m.sum()), m.sum() * cx * cx, float(sup[m].mean()),
                                 float(np.percentile(hh, 90) - np.percentile(hh, 10)), cx, cy))
        finally:
            p.close()
        if progress:
            progress(f"dog {ob.id} ({ob.height_m:.2f} m high) done")
    return rows


def summary(rows: list[tuple], near_m: float = 6.0) -> str:
    """The per-class quantiles and the rules' shares of frames, as text."""
    if not rows:
        return "no low points near any head-on dog"
    A = np.array([r[1:] for r in rows], float)
    c = {n: A[:, i] for i, n in enumerate(COLUMNS[1:])}
    frames = np.unique(c["frame"])
    dist = dict(zip(c["frame"], c["dist"]))
    out = [f"{len(rows)} cells in {len(frames)} frames; quantiles p10 / p50 / p90 / p99:"]
    for n in ("n", "nx2", "support", "hspan"):
        for lab, name in ((1, "dog  "), (0, "field")):
            v = c[n][c["is_dog"] == lab]
            q = " / ".join(f"{x:.2f}" for x in np.percentile(v, (10, 50, 90, 99))) if len(v) \
                else "-"
            out.append(f"  {n:8s} {name} {q}")
    out.append(f"rule: frames with a dog cell passing (those under {near_m:g} m) | "
               "frames with a field cell passing")
    near = frames[[dist[f] < near_m for f in frames]]
    for s, d, n in RULES:
        ok = (c["support"] >= s) & (c["hspan"] >= d) & (c["nx2"] >= n)
        dog_f = set(c["frame"][ok & (c["is_dog"] == 1)])
        field_f = set(c["frame"][ok & (c["is_dog"] == 0)])
        near_share = np.mean([f in dog_f for f in near]) if len(near) else 0.0
        out.append(f"  support >= {s} spread >= {d} nx2 >= {n}: "
                   f"{len(dog_f) / len(frames):.2f} ({near_share:.2f})"
                   f" | {len(field_f) / len(frames):.3f}")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind")
    ap.add_argument("seed", type=int)
    ap.add_argument("--dogs", type=int, default=None, help="only the first N head-on dogs")
    ap.add_argument("--from", dest="start", type=float, default=10.0,
                    help="look from this far before each dog (m)")
    ap.add_argument("--tsv", type=Path, help="also write every cell's row here")
    a = ap.parse_args(argv)
    if a.seed >= 1000:
        sys.exit("training seeds only (< 1000): acceptance drives are scored, not looked into")
    rows = cells_of(a.kind, a.seed, a.dogs, a.start,
                    progress=lambda m: print(m, file=sys.stderr, flush=True))
    if a.tsv:
        with open(a.tsv, "w") as fh:
            fh.write("\t".join(COLUMNS) + "\n")
            for r in rows:
                fh.write("\t".join(str(round(v, 3)) if isinstance(v, float) else str(v)
                                   for v in r) + "\n")
    print(summary(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
