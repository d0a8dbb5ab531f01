"""What does the field's canopy (``[perception.stereo-novelty] canopy_floor``) take away? One
closed-loop campaign drive; every cycle, the obstacle points the canopy dropped (raised by the
depth cue alone, under the canopy + margin) are clustered on the ground and each cluster is
labelled by the simulator's truth: an obstacle's (half its points or more within ``--near`` m of
an obstacle's footprint) or the field's.

    python tools/canopy_probe.py KIND SEED --minutes 2 --config slk.toml --out DIR

The drive must run stereo-novelty with ``canopy_floor = true``. ``DIR/KIND-SEED-canopy.jsonl``:
one line per cluster within ``--reach`` m of the front and ``--side`` m of the centre line
(time, label, class, points, length along, width across, heights, range). ``--summary`` over
one or more such files prints, per label, the quantiles of each shape figure and how many
clusters each candidate rule ("keep a cluster at least W wide and N points") would keep: the
question a shape rule must answer before it is built (a dog's back against a tall field's tuft
tops, docs/front-end.md "The field's canopy, and the boot"). Training seeds only: this is for
finding a rule, not for judging one.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

CELL_M = 0.1      # the ground grid the dropped points are clustered on (8-connected)


def clusters(xy: np.ndarray, cell_m: float = CELL_M) -> np.ndarray:
    """Label (N,) of each point's 8-connected cluster on a ``cell_m`` ground grid; -1 for none."""
    if not len(xy):
        return np.zeros(0, np.int64)
    ij = np.floor((xy - xy.min(0)) / cell_m).astype(np.int64)
    img = np.zeros((int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1), np.uint8)
    img[ij[:, 0], ij[:, 1]] = 1
    _, lab = cv2.connectedComponents(img, connectivity=8)
    return lab[ij[:, 0], ij[:, 1]].astype(np.int64)


def shape(xy: np.ndarray, h: np.ndarray) -> dict:
    """The figures of one cluster: points, extent along x and across y (plus one cell), heights."""
    return {"points": int(len(xy)),
            "length_m": round(float(np.ptp(xy[:, 0])) + CELL_M, 2),
            "width_m": round(float(np.ptp(xy[:, 1])) + CELL_M, 2),
            "h_max_m": round(float(h.max()), 2), "h_med_m": round(float(np.median(h)), 2),
            "h_span_m": round(float(np.ptp(h)), 2),
            "x_m": round(float(np.median(xy[:, 0])), 2), "y_m": round(float(np.median(xy[:, 1])), 2)}


def label(xy: np.ndarray, truth: list[dict], near_m: float) -> tuple[str, str]:
    """("obstacle", class) when half the points or more lie within ``near_m`` of one obstacle's
    footprint points (their convex hull), else ("field", "")."""
    for o in truth:
        hull = cv2.convexHull(np.asarray(o["pts_vehicle"], np.float32))
        d = np.array([-cv2.pointPolygonTest(hull, (float(x), float(y)), True) for x, y in xy])
        if np.mean(d <= near_m) >= 0.5:
            return "obstacle", o["cls"]
    return "field", ""


def summary(files: list[str]) -> int:
    rows = [json.loads(line) for f in files for line in open(f) if line.strip()]
    if not rows:
        print("canopy_probe: no clusters in these files")
        return 1
    print(f"{len(rows)} clusters from {len(files)} drive(s)")
    for lab in ("obstacle", "field"):
        r = [x for x in rows if x["label"] == lab]
        if not r:
            print(f"{lab}: none")
            continue
        cls = {}
        for x in r:
            cls[x["cls"]] = cls.get(x["cls"], 0) + 1
        print(f"{lab}: {len(r)} clusters" + (f" {cls}" if lab == "obstacle" else ""))
        for k in ("points", "width_m", "length_m", "h_max_m", "h_span_m", "x_m"):
            q = np.percentile([x[k] for x in r], [10, 50, 90])
            print(f"   {k:9s} p10 {q[0]:7.2f}  p50 {q[1]:7.2f}  p90 {q[2]:7.2f}")
    print("rule: keep a cluster (the canopy does not drop it) when width >= W and points >= N")
    print("   W     N   obstacle kept   field kept")
    for w in (0.0, 0.15, 0.2, 0.25, 0.3):
        for n in (1, 10, 30, 60):
            ko = sum(1 for x in rows if x["label"] == "obstacle" and x["width_m"] >= w
                     and x["points"] >= n)
            kf = sum(1 for x in rows if x["label"] == "field" and x["width_m"] >= w
                     and x["points"] >= n)
            no = sum(1 for x in rows if x["label"] == "obstacle")
            nf = sum(1 for x in rows if x["label"] == "field")
            print(f"  {w:4.2f} {n:4d}   {ko:5d}/{no:<5d}    {kf:6d}/{nf}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", nargs="?")
    ap.add_argument("seed", nargs="?", type=int)
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--stereo-scale", type=float, default=0.5)
    ap.add_argument("--config", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--reach", type=float, default=8.0, help="m ahead of the front")
    ap.add_argument("--side", type=float, default=2.5, help="m either side of the centre line")
    ap.add_argument("--near", type=float, default=0.3, help="m from an obstacle's footprint")
    ap.add_argument("--summary", nargs="+", metavar="JSONL")
    a = ap.parse_args(argv)
    if a.summary:
        return summary(a.summary)
    if a.kind is None or a.seed is None or a.out is None:
        ap.error("KIND SEED --out DIR (or --summary FILES)")
    from appliance.campaign import load_extra_config, make_spec
    from appliance.campaign_drive import Drive
    extra = load_extra_config(a.config) if a.config else None
    spec = make_spec(a.kind, a.seed, a.minutes, a.stereo_scale, extra)
    d = Drive(a.kind, a.seed, a.minutes, config_data=spec["config"], stereo_scale=a.stereo_scale)
    d.build()
    pipe = next((p for p in d.daemon.pipelines if hasattr(p, "novelty")), None)
    if pipe is None or not pipe.options.canopy_floor:
        print("canopy_probe: error: the drive must run stereo-novelty with "
              "[perception.stereo-novelty] canopy_floor = true (--config)", file=sys.stderr)
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = open(out / f"{a.kind}-{a.seed}-canopy.jsonl", "w")
    seen: dict = {}
    below = pipe._below_canopy

    def spy(pts, px, h, keep, *rest):
        canopy, dropped = below(pts, px, h, keep, *rest)
        seen["now"] = (canopy, None if dropped is None else (pts[dropped], h[dropped]))
        return canopy, dropped
    pipe._below_canopy = spy
    z = d.zones

    def after(res):
        canopy, got = seen.pop("now", (None, None))
        if got is None or not len(got[0]):
            return
        pts, h = got
        sel = ((pts[:, 0] >= z.front_x_m) & (pts[:, 0] <= z.front_x_m + a.reach)
               & (np.abs(pts[:, 1]) <= a.side))
        if not sel.any():
            return
        xy, hh = pts[sel, :2], h[sel]
        stop_len = res.verdict.stop_len_m if res.verdict is not None else z.min_stop_m
        truth = d.truth(stop_len)
        lab = clusters(xy)
        for c in np.unique(lab):
            m = lab == c
            lb, cls = label(xy[m], truth, a.near)
            log.write(json.dumps({"t_s": round(res.index / d.rate, 1), "label": lb, "cls": cls,
                                  "canopy_m": None if canopy is None else round(canopy, 2),
                                  **shape(xy[m], hh[m])}) + "\n")

    d.daemon.loop.on_cycle.append(after)
    r = d.run()["result"]
    log.close()
    print(json.dumps({k: r.get(k) for k in ("false_stops", "true_stops", "missed_stops",
                                            "collisions")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
