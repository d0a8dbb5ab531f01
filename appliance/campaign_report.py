"""DIR/report.md of a campaign, with PNG plots drawn with OpenCV (no plotting dependency):

- ``route-KIND-SEED.png``: each drive's planned route, the track driven, the obstacles and every
  event (true / false / fault stop, missed stop, collision);
- ``detection.png``: detection distance per obstacle class against the stopping distance at
  cruise speed (the box's stop zone and the vehicle's braking distance);
- ``false_stops.png``: false stops by cause and by place;
- ``memory.png``: the novelty model's samples over simulated time per drive (and its bound);
- ``stages.png``: ms per loop stage (wall, p50 over the drives) and the renderer's CPU ms.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK, GREY, LIGHT = (0, 0, 0), (120, 120, 120), (225, 225, 225)
COLOURS = {"true": (0, 160, 0), "false": (0, 140, 255), "fault": (200, 0, 200),
           "missed": (0, 0, 160), "collision": (0, 0, 230)}
SERIES = [(180, 60, 0), (0, 140, 0), (0, 0, 200), (140, 0, 140), (0, 140, 200), (90, 90, 0),
          (60, 60, 60), (200, 120, 40)]


def text(img, s, org, scale=0.42, col=BLACK):
    cv2.putText(img, s, (int(org[0]), int(org[1])), FONT, scale, col, 1, cv2.LINE_AA)


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 5, 10) if m * mag >= raw), default=raw)
    start = math.ceil(lo / step) * step
    return [start + i * step for i in range(int((hi - start) / step + 1e-9) + 1)]


class Axes:
    """A plot area in an image with data -> pixel mapping, grid and tick labels."""

    def __init__(self, img, rect, xlim, ylim, title="", xlabel="", ylabel=""):
        x0, y0, w, h = rect
        self.img = img
        self.ax0, self.ay0, self.aw, self.ah = x0 + 60, y0 + 28, w - 75, h - 62
        self.xlo, self.xhi = xlim if xlim[1] > xlim[0] else (xlim[0], xlim[0] + 1)
        self.ylo, self.yhi = ylim if ylim[1] > ylim[0] else (ylim[0], ylim[0] + 1)
        cv2.rectangle(img, (self.ax0, self.ay0), (self.ax0 + self.aw, self.ay0 + self.ah),
                      BLACK, 1)
        text(img, title, (self.ax0, y0 + 18), 0.5)
        for t in nice_ticks(self.ylo, self.yhi, 5):
            p = self.px(self.xlo, t)
            cv2.line(img, (self.ax0, p[1]), (self.ax0 + self.aw, p[1]), LIGHT, 1)
            text(img, f"{t:g}", (x0 + 4, p[1] + 4), 0.38, GREY)
        text(img, xlabel, (self.ax0 + self.aw // 2 - 40, y0 + h - 8), 0.4, GREY)
        text(img, ylabel, (x0 + 4, self.ay0 - 6), 0.38, GREY)

    def px(self, x, y):
        return (int(round(self.ax0 + (x - self.xlo) / (self.xhi - self.xlo) * self.aw)),
                int(round(self.ay0 + self.ah - (y - self.ylo) / (self.yhi - self.ylo) * self.ah)))

    def xticks(self, n=8):
        for t in nice_ticks(self.xlo, self.xhi, n):
            p = self.px(t, self.ylo)
            cv2.line(self.img, (p[0], p[1]), (p[0], p[1] + 4), BLACK, 1)
            text(self.img, f"{t:g}", (p[0] - 8, p[1] + 17), 0.38, GREY)


def _blank(w, h):
    return np.full((h, w, 3), 255, np.uint8)


def bars(img, rect, labels, values, title, colour=(180, 60, 0), unit=""):
    """Horizontal bars, one per label."""
    x0, y0, w, h = rect
    text(img, title, (x0 + 8, y0 + 18), 0.5)
    if not labels:
        text(img, "(none)", (x0 + 20, y0 + 50), 0.45, GREY)
        return
    vmax = max(max(values), 1e-9)
    lab_w = min(int(w * 0.55), max(cv2.getTextSize(s[:70], FONT, 0.38, 1)[0][0]
                                   for s in labels) + 16)
    bh = max(10, min(26, (h - 40) // max(1, len(labels))))
    for i, (lab, v) in enumerate(zip(labels, values)):
        y = y0 + 30 + i * bh
        text(img, lab[:70], (x0 + 8, y + bh - 8), 0.38)
        L = int((w - lab_w - 70) * v / vmax)
        cv2.rectangle(img, (x0 + lab_w, y + 2), (x0 + lab_w + max(L, 1), y + bh - 4), colour, -1)
        text(img, f"{v:g}{unit}", (x0 + lab_w + L + 6, y + bh - 8), 0.38)


def _rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _f(v, default=float("nan")):
    try:
        return float(v)
    except (TypeError, ValueError):
        return default


def route_png(out: Path, kind: str, seed: int, rows: list[dict], events: list[dict],
              result: dict) -> Path:
    from drivers.sim.scenes import build_scene
    sc = build_scene(kind, seed)
    path = np.asarray(sc.path, float)
    obs = [(o.x, o.y, o.cls) for o in sc.world.obstacles]
    W, H = 1100, 760
    img = _blank(W, H)
    pts = path
    xlo, xhi = pts[:, 0].min() - 8, pts[:, 0].max() + 8
    ylo, yhi = pts[:, 1].min() - 8, pts[:, 1].max() + 8
    s = min((W - 40) / (xhi - xlo), (H - 110) / (yhi - ylo))

    def px(a, b):
        return (int(round(20 + (a - xlo) * s)), int(round(H - 60 - (b - ylo) * s)))
    cv2.polylines(img, [np.array([px(a, b) for a, b in path], np.int32)], False, LIGHT, 1,
                  cv2.LINE_AA)
    drv = [px(_f(r["x_m"]), _f(r["y_m"])) for r in rows[::5]
           if math.isfinite(_f(r["x_m"]))]
    if len(drv) > 1:
        cv2.polylines(img, [np.array(drv, np.int32)], False, (200, 120, 40), 2, cv2.LINE_AA)
    for x, y, _c in obs:
        cv2.circle(img, px(x, y), 3, (60, 60, 60), -1)
    for e in events:
        c = px(e["x_m"], e["y_m"])
        if e["event"] == "collision":
            cv2.drawMarker(img, c, COLOURS["collision"], cv2.MARKER_TILTED_CROSS, 14, 2)
        elif e["event"] == "missed":
            cv2.drawMarker(img, c, COLOURS["missed"], cv2.MARKER_TRIANGLE_UP, 12, 2)
        else:
            cv2.circle(img, c, 6, COLOURS.get(e["kind"], BLACK), 2, cv2.LINE_AA)
    text(img, f"{kind} seed {seed}: {result['simulated_s'] / 60:.1f} simulated min, "
              f"{result['distance_m']:.0f} m; true stops {result['true_stops']}, false "
              f"{result['false_stops']}, missed {result['missed_stops']}, collisions "
              f"{result['collisions']}, overrides {result['overrides']}, detours "
              f"{result['detours']}", (12, 22), 0.5)
    lx, ly = 20, H - 20
    for label, col, mk in (("true stop", COLOURS["true"], None),
                           ("false stop", COLOURS["false"], None),
                           ("fault stop", COLOURS["fault"], None),
                           ("missed stop", COLOURS["missed"], cv2.MARKER_TRIANGLE_UP),
                           ("collision", COLOURS["collision"], cv2.MARKER_TILTED_CROSS)):
        if mk is None:
            cv2.circle(img, (lx + 5, ly - 5), 6, col, 2, cv2.LINE_AA)
        else:
            cv2.drawMarker(img, (lx + 5, ly - 5), col, mk, 12, 2)
        text(img, label, (lx + 16, ly))
        lx += 130
    cv2.circle(img, (lx + 5, ly - 5), 3, (60, 60, 60), -1)
    text(img, "obstacle", (lx + 14, ly))
    cv2.line(img, (lx + 100, ly - 5), (lx + 125, ly - 5), (200, 120, 40), 2)
    text(img, "driven (grey: planned)", (lx + 130, ly))
    p = out / "plots" / f"route-{kind}-{seed}.png"
    cv2.imwrite(str(p), img)
    return p


def detection_png(out: Path, summary: dict, results: list[dict]) -> Path:
    W, H = 1000, 520
    img = _blank(W, H)
    pts = [(d["cls"], d["distance_m"]) for r in results for d in r["detections"]
           if d["distance_m"] is not None]
    classes = sorted({c for c, _ in pts} | set(summary["detection_distance_m"]))
    stops = [r["stopping_distance_at_cruise_m"] for r in results]
    zone = max((s["box_stop_zone"] for s in stops), default=0.0)
    brake = max((s["vehicle_braking"] for s in stops), default=0.0)
    ymax = max([d for _, d in pts] + [zone, 5.0]) * 1.1
    ax = Axes(img, (0, 0, W, H - 44), (-0.5, max(len(classes), 1) - 0.5), (0, ymax),
              "detection distance per class (first held continuously until the stop) vs "
              "stopping distance at cruise", ylabel="m ahead of the front")
    for i, c in enumerate(classes):
        ds = [d for cc, d in pts if cc == c]
        for j, d in enumerate(ds):
            jit = ((j * 37) % 11 - 5) / 30.0
            cv2.circle(img, ax.px(i + jit, d), 4, SERIES[0], -1, cv2.LINE_AA)
        med = summary["detection_distance_m"].get(c, {}).get("median")
        if med is not None:
            a, b = ax.px(i - 0.3, med), ax.px(i + 0.3, med)
            cv2.line(img, a, b, BLACK, 2)
        p = ax.px(i, 0)
        n = summary["detection_distance_m"].get(c, {}).get("stops", len(ds))
        # two rows of labels, alternating: long class names side by side overlap
        label = f"{c} ({n})"
        w = cv2.getTextSize(label, FONT, 0.38, 1)[0][0]
        text(img, label, (p[0] - w // 2, p[1] + 18 + 14 * (i % 2)), 0.38)
    for y, col, lab in ((zone, (0, 0, 200), f"box stop zone at cruise {zone:.2f} m"),
                        (brake, (0, 140, 0), f"vehicle braking distance {brake:.2f} m")):
        a, b = ax.px(-0.5, y), ax.px(max(len(classes), 1) - 0.5, y)
        cv2.line(img, a, b, col, 1, cv2.LINE_AA)
        text(img, lab, (b[0] - 260, a[1] - 5), 0.4, col)
    text(img, "dots: one true stop each; bar: median", (70, H - 8), 0.4, GREY)
    p = out / "plots" / "detection.png"
    cv2.imwrite(str(p), img)
    return p


def false_stops_png(out: Path, summary: dict) -> Path:
    W, H = 1200, 460
    img = _blank(W, H)
    cause = summary["false_stops_by_cause"]
    place = summary["false_stops_by_place"]
    places = ["headland", "lane", "near an obstacle"]
    bars(img, (0, 0, 760, H), list(cause), list(cause.values()),
         f"false stops by cause ({summary['false_stops']} in all)")
    bars(img, (770, 0, 430, H), places, [place.get(p, 0) for p in places],
         "false stops by place", colour=(0, 140, 255))
    p = out / "plots" / "false_stops.png"
    cv2.imwrite(str(p), img)
    return p


def memory_png(out: Path, results: list[dict], rows_by: dict) -> Path:
    W, H = 1000, 420
    img = _blank(W, H)
    series = []
    for r in results:
        rows = rows_by.get((r["kind"], r["seed"]), [])
        t = [_f(x["t_s"]) / 60 for x in rows[::10]]
        m = [_f(x["model_samples"]) for x in rows[::10]]
        if any(math.isfinite(v) for v in m):
            series.append((f"{r['kind']} {r['seed']}", t, m))
    bound = max((r["model"]["bound"] or 0 for r in results), default=0)
    tmax = max((max(t) for _, t, _m in series if t), default=1.0)
    vmax = max([max((v for v in m if math.isfinite(v)), default=0) for _, _t, m in series]
               + [bound or 0, 1]) * 1.05
    ax = Axes(img, (0, 0, W, H), (0, tmax), (0, vmax),
              "novelty model samples (Parzen window; 40 bytes each) vs simulated minutes",
              xlabel="simulated minutes")
    ax.xticks()
    for i, (lab, t, m) in enumerate(series):
        pts = [ax.px(a, b) for a, b in zip(t, m) if math.isfinite(b)]
        if len(pts) > 1:
            cv2.polylines(img, [np.array(pts, np.int32)], False, SERIES[i % len(SERIES)], 1,
                          cv2.LINE_AA)
        if i < 10:
            text(img, lab, (ax.ax0 + 10, ax.ay0 + 16 + 14 * i), 0.36, SERIES[i % len(SERIES)])
    if bound:
        a, b = ax.px(0, bound), ax.px(tmax, bound)
        cv2.line(img, a, b, (0, 0, 200), 1, cv2.LINE_AA)
        text(img, f"pruning bound {bound}", (b[0] - 170, a[1] - 5), 0.4, (0, 0, 200))
    if not series:
        text(img, "(no novelty model in these pipelines)", (ax.ax0 + 20, ax.ay0 + 40), 0.5,
             GREY)
    p = out / "plots" / "memory.png"
    cv2.imwrite(str(p), img)
    return p


def stages_png(out: Path, summary: dict, results: list[dict]) -> Path:
    W, H = 1000, 420
    img = _blank(W, H)
    labels, values = [], []
    for kind in summary["kinds"]:
        rs = [r for r in results if r["kind"] == kind]
        if not rs:
            continue
        for st in ("acquire", "perception", "fusion", "gate", "send"):
            v = [r["timing"]["stage_wall_ms_p50"][st] for r in rs
                 if r["timing"]["stage_wall_ms_p50"][st] is not None]
            labels.append(f"{kind}: {st} (wall p50)")
            values.append(round(float(np.median(v)), 2) if v else 0.0)
        for k, lab in (("render_cpu_ms_p50", "render, CPU p50"),
                       ("pipeline_cpu_ms_p50", "pipelines, CPU p50")):
            v = [r["timing"][k] for r in rs if r["timing"][k] is not None]
            labels.append(f"{kind}: {lab}")
            values.append(round(float(np.median(v)), 2) if v else 0.0)
    bars(img, (0, 0, W, H), labels, values, "ms per cycle stage (acquire includes the "
         "simulator's rendering; wall time on a shared machine)", unit=" ms")
    p = out / "plots" / "stages.png"
    cv2.imwrite(str(p), img)
    return p


def _fmt_ci(r):
    c = r["false_stops_per_hour_ci95"]
    return "-" if c[0] is None else f"[{c[0]:.2f}, {c[1]:.2f}]"


def write_report(out, summary: dict, images_rel: str = "plots") -> Path:
    out = Path(out)
    (out / "plots").mkdir(exist_ok=True)
    results, rows_by = [], {}
    for k in summary["kinds"]:
        for d in summary["per_drive"]:
            if d["kind"] != k:
                continue
            dd = out / "drives" / f"{k}-{d['seed']}"
            r = json.loads((dd / "result.json").read_text("utf-8"))
            results.append(r)
            rows_by[(k, d["seed"])] = _rows(dd / "cycles.csv")
    routes = []
    for r in results:
        dd = out / "drives" / f"{r['kind']}-{r['seed']}"
        ev = json.loads((dd / "events.json").read_text("utf-8"))
        routes.append(route_png(out, r["kind"], r["seed"], rows_by[(r["kind"], r["seed"])], ev,
                                r))
    det = detection_png(out, summary, results)
    fs = false_stops_png(out, summary)
    mem = memory_png(out, results, rows_by)
    stg = stages_png(out, summary, results)
    t, pv = summary["timing"], summary["provenance"]
    L = [f"# Campaign report: {', '.join(summary['kinds'])}, seeds {summary['seeds'][0]}-"
         f"{summary['seeds'][1]}", "",
         f"- command: `{pv.get('command') or '(API)'}`",
         f"- commit: `{pv.get('commit')}`, started {pv.get('started_utc')}",
         f"- engine: {summary['engine']} x {summary['workers']} workers; "
         f"{'ACCEPTANCE seeds (>= 1000)' if summary['acceptance_seeds'] else 'training seeds (< 1000) included'}",
         f"- {summary['drives']} drives of {summary['minutes_per_drive']} simulated minutes, "
         f"stereo scale {summary['stereo_scale']}",
         "- the box's boot: " + (
             f"each drive with the novelty model saved at the end of its drive in "
             f"`{pv['models_from']}` (as an installed box boots with its saved model)"
             if pv.get("models_from") else "each drive with an empty novelty model") + (
             "; each drive's model at its end kept in drives/KIND-SEED/models/"
             if pv.get("save_models") else ""),
         f"- wall {t['wall_s'] / 60:.1f} min for {t['drives_run']} drives run here "
         f"({t['drives_skipped']} already done), {t['simulated_hours_per_cpu_hour']} simulated "
         f"hours per CPU hour, load average (1 min) {t['loadavg_1min_start_end']} on "
         f"{t['cpu_count']} cores", "",
         "| scene | pipelines | image | hours | km | collisions | true stops | false stops | "
         "false stops/h | 95 % CI (Poisson) | missed stops | overrides | detours |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for k, r in summary["per_scene"].items():
        img = "x".join(map(str, r["image_px"])) if r.get("image_px") else "-"
        L.append(f"| {k} | {', '.join(r['pipelines'] or [])} | {img} | "
                 f"{r['simulated_hours']:.2f} | {r['distance_km']:.2f} | {r['collisions']} | "
                 f"{r['true_stops']} | {r['false_stops']} | {r['false_stops_per_hour']} | "
                 f"{_fmt_ci(r)} | {r['missed_stops']} | {r['overrides']} | {r['detours']} |")
    s = summary
    L.append(f"| **all** | | | {s['simulated_hours']:.2f} | {s['distance_km']:.2f} | "
             f"{s['collisions']} | {s['true_stops']} | {s['false_stops']} | "
             f"{s['false_stops_per_hour']} | {_fmt_ci(s)} | {s['missed_stops']} | "
             f"{s['overrides']} | {s['detours']} |")
    L += ["", "## Detection distance per class", "",
          "| class | true stops | min m | median m | stopped without holding it |",
          "|---|---|---|---|---|"]
    for c, d in s["detection_distance_m"].items():
        L.append(f"| {c} | {d['stops']} | {d['min']} | {d['median']} | "
                 f"{d['stopped_without_hold']} |")
    L += ["", f"![detection]({images_rel}/{det.name})", "",
          "## False stops by cause and place", "", f"![false stops]({images_rel}/{fs.name})",
          "", "## Model memory", "",
          f"Largest novelty model: {s['model']['samples_max']} samples "
          f"({s['model']['bytes_max']} bytes), bound {s['model']['bound']}; process RSS max "
          f"{t['rss_mb_max']} MB.", "", f"![memory]({images_rel}/{mem.name})", "",
          "## ms per stage", "", f"![stages]({images_rel}/{stg.name})", "",
          "## Drives", "",
          "| drive | sim min | m | collisions | true | false | missed | fault | overrides | "
          "detours |", "|---|---|---|---|---|---|---|---|---|---|"]
    for d in s["per_drive"]:
        L.append(f"| {d['kind']} {d['seed']} | {d['simulated_s'] / 60:.1f} | "
                 f"{d['distance_m']:.0f} | {d['collisions']} | {d['true_stops']} | "
                 f"{d['false_stops']} | {d['missed_stops']} | {d['fault_stops']} | "
                 f"{d['overrides']} | {d['detours']} |")
    L.append("")
    for p in routes:
        L.append(f"![{p.stem}]({images_rel}/{p.name})")
    L.append("")
    path = out / "report.md"
    path.write_text("\n".join(L), encoding="utf-8")
    return path
