"""``fieldguard campaign-compare A B``: two campaigns of the same drives (scene kinds, seeds,
minutes) under two configurations, compared drive by drive.

Why paired. A campaign's drives are deterministic (ManualClock, everything seeded), so the two
runs of one drive are the same cycles until the first cycle in which the two boxes decide
differently; from there on they are two different drives (the vehicle is elsewhere, at another
time). Totals of two short campaigns cannot separate small effects: the spread from seed to
seed is larger than the effect (docs/proving-ground.md, fourteenth session). Two things are
paired here and reported beside the totals:

* **the first difference** of each drive: where the two boxes first parted, what each said,
  and the simulator's truth there (the nearest real obstacle ahead in the path against the
  zones). The more cautious box (STOP > SLOW > CLEAR) was *right* when a real obstacle was
  within the zones, or a walker was about to meet the vehicle (cycles.csv ``real_meets``:
  going on as it was, within twice the time the vehicle needs to come to rest + 0.5 s), a
  *phantom* when nothing real was. Before that cycle the drives are equal,
  so this is the one clean, like-for-like difference a drive gives;
* **per-drive differences** of false stops and collisions, with an exact two-sided sign test
  over the drives that differ (ties dropped).

Reads only what ``fieldguard campaign`` writes (DIR/summary.json, DIR/drives/KIND-SEED/
cycles.csv); any problem with a folder is one clear error.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

RANK = {"CLEAR": 0, "SLOW": 1, "STOP": 2}


class CompareError(Exception):
    """A campaign folder that cannot be compared (said in one line)."""


# ---------------------------------------------------------------------------------------------
def load_campaign(path) -> dict:
    """summary.json of a campaign folder, checked for what the comparison reads."""
    p = Path(path)
    f = p / "summary.json"
    if not p.is_dir():
        raise CompareError(f"{p}: not a folder")
    if not f.is_file():
        raise CompareError(f"{p}: no summary.json (not a campaign folder, or the campaign has "
                           f"not finished a drive yet)")
    try:
        s = json.loads(f.read_text("utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CompareError(f"{f}: unreadable: {exc}") from None
    if not isinstance(s, dict) or not isinstance(s.get("per_drive"), list):
        raise CompareError(f"{f}: not a campaign summary (no per_drive list)")
    for d in s["per_drive"]:
        if not isinstance(d, dict) or not {"kind", "seed", "false_stops", "collisions",
                                           "simulated_s"} <= set(d):
            raise CompareError(f"{f}: a per_drive entry lacks kind/seed/false_stops/"
                               f"collisions/simulated_s")
    return s


def read_cycles(path: Path) -> list[dict]:
    if not path.is_file():
        raise CompareError(f"{path}: missing (the drive's per-cycle record)")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            return list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise CompareError(f"{path}: unreadable: {exc}") from None


def _num(v):
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


EARLY_M = 5.0      # a real obstacle this much beyond the zones: caution early, not a phantom


def first_difference(rows_a: list[dict], rows_b: list[dict], reach_extra_m: float,
                     early_m: float = EARLY_M) -> dict | None:
    """The first cycle where the two drives part (the box's state, or the vehicle's position or
    speed, differ), with what each box said and the truth there; None if they never part.
    ``reach_extra_m``: how far beyond the stop zone a real obstacle still makes caution right
    (the slow zone's extra length); up to ``early_m`` beyond that it is *early* (neither right
    nor a phantom: a SLOW for a person 7 m ahead when the zones reach 5 m)."""
    for ra, rb in zip(rows_a, rows_b):
        same_state = ra.get("state") == rb.get("state")
        same_place = all(ra.get(k) == rb.get(k) for k in ("x_m", "y_m", "speed_mps"))
        if same_state and same_place:
            continue
        out = {"t_s": _num(ra.get("t_s")),
               "a": {"state": ra.get("state"), "reason": ra.get("reason", "")},
               "b": {"state": rb.get("state"), "reason": rb.get("reason", "")}}
        if same_state:        # equal decisions, the vehicle elsewhere: not the box's doing
            out["judgement"] = "vehicle differs with equal decisions"
            out["cautious"] = None
            return out
        # the truth of the cycle the decisions parted in (positions still equal then)
        near = _num(ra.get("real_nearest_m"))
        zone = _num(ra.get("stop_zone_m")) or 0.0
        reach = zone + reach_extra_m
        judgement = ("right" if near is not None and near <= reach else
                     "early" if near is not None and near <= reach + early_m else "phantom")
        # a walker about to meet the vehicle (campaign_drive; the drives' truth is the same
        # here, so either record that has the column says it)
        meets = ra.get("real_meets") or rb.get("real_meets") or ""
        if meets:
            judgement = "right"
        cautious = "a" if RANK.get(ra.get("state"), 2) > RANK.get(rb.get("state"), 2) else "b"
        out.update(real_nearest_m=near, real_obstacle=ra.get("real_obstacle", ""),
                   real_meets=meets,
                   stop_zone_m=zone, cautious=cautious, judgement=judgement)
        return out
    if len(rows_a) != len(rows_b):
        n = min(len(rows_a), len(rows_b))
        return {"t_s": _num((rows_a or rows_b)[n - 1].get("t_s")) if n else 0.0,
                "a": {"state": None, "reason": f"{len(rows_a)} cycles"},
                "b": {"state": None, "reason": f"{len(rows_b)} cycles"},
                "judgement": "one record is shorter", "cautious": None}
    return None


def sign_test(plus: int, minus: int) -> float:
    """Exact two-sided sign test: the chance of a split at least this uneven if neither side
    were better (ties dropped beforehand)."""
    n = plus + minus
    if n == 0:
        return 1.0
    k = min(plus, minus)
    p = sum(math.comb(n, i) for i in range(k + 1)) / 2.0 ** n
    return min(1.0, 2.0 * p)


def compare(dir_a, dir_b, reach_extra_m: float | None = None) -> dict:
    """The drive-by-drive comparison of campaign folders A and B (a dict; see the module)."""
    if reach_extra_m is None:
        from appliance.config import Config
        reach_extra_m = float(Config().zones.slow_extra_m)
    sa, sb = load_campaign(dir_a), load_campaign(dir_b)
    if sa.get("minutes_per_drive") != sb.get("minutes_per_drive"):
        raise CompareError(f"the campaigns drove {sa.get('minutes_per_drive')} and "
                           f"{sb.get('minutes_per_drive')} minutes a drive: not the same drives")
    if sa.get("stereo_scale") != sb.get("stereo_scale"):
        raise CompareError(f"the campaigns' stereo scales differ ({sa.get('stereo_scale')} and "
                           f"{sb.get('stereo_scale')}): not the same drives")
    da = {(d["kind"], int(d["seed"])): d for d in sa["per_drive"]}
    db = {(d["kind"], int(d["seed"])): d for d in sb["per_drive"]}
    both = sorted(set(da) & set(db), key=lambda k: (k[1], k[0]))
    if not both:
        raise CompareError("the campaigns have no drive (scene kind and seed) in common")
    drives = []
    for key in both:
        a, b = da[key], db[key]
        name = f"{key[0]}-{key[1]}"
        rows_a = read_cycles(Path(dir_a) / "drives" / name / "cycles.csv")
        rows_b = read_cycles(Path(dir_b) / "drives" / name / "cycles.csv")
        drives.append({
            "kind": key[0], "seed": key[1],
            "a": {k: a.get(k) for k in ("false_stops", "collisions", "true_stops",
                                        "missed_stops", "simulated_s", "distance_m")},
            "b": {k: b.get(k) for k in ("false_stops", "collisions", "true_stops",
                                        "missed_stops", "simulated_s", "distance_m")},
            "first_difference": first_difference(rows_a, rows_b, reach_extra_m)})

    def tot(side, k):
        return sum(int(d[side][k] or 0) for d in drives)

    def side(s):
        from appliance.campaign import poisson_ci95
        h = sum(float(d[s]["simulated_s"] or 0.0) for d in drives) / 3600.0
        fs = tot(s, "false_stops")
        return {"simulated_hours": round(h, 4), "false_stops": fs,
                "false_stops_per_hour": None if h <= 0 else round(fs / h, 2),
                "false_stops_per_hour_ci95": poisson_ci95(fs, h) if h > 0 else [None, None],
                "collisions": tot(s, "collisions"), "true_stops": tot(s, "true_stops"),
                "missed_stops": tot(s, "missed_stops")}

    fewer = sum(1 for d in drives if d["b"]["false_stops"] < d["a"]["false_stops"])
    more = sum(1 for d in drives if d["b"]["false_stops"] > d["a"]["false_stops"])
    cfewer = sum(1 for d in drives if d["b"]["collisions"] < d["a"]["collisions"])
    cmore = sum(1 for d in drives if d["b"]["collisions"] > d["a"]["collisions"])
    # first differences, as B against A: B's caution right, or A's caution a phantom, is
    # B better there; B's caution a phantom, or A's caution right, is B worse
    better = worse = early = 0
    for d in drives:
        f = d["first_difference"]
        if not f or f.get("cautious") is None:
            continue
        if f["judgement"] == "early":
            early += 1
            continue
        good_for_b = (f["cautious"] == "b") == (f["judgement"] == "right")
        better += good_for_b
        worse += not good_for_b
    return {
        "a": str(dir_a), "b": str(dir_b),
        "a_commit": (sa.get("provenance") or {}).get("commit"),
        "b_commit": (sb.get("provenance") or {}).get("commit"),
        # how each campaign's box booted: None = from an empty novelty model, else the
        # campaign whose saved models it booted with (fieldguard campaign --models-from)
        "a_models_from": (sa.get("provenance") or {}).get("models_from"),
        "b_models_from": (sb.get("provenance") or {}).get("models_from"),
        "minutes_per_drive": sa.get("minutes_per_drive"),
        "acceptance_seeds": all(k[1] >= 1000 for k in both),
        "only_in_a": [f"{k}-{s}" for k, s in sorted(set(da) - set(db))],
        "only_in_b": [f"{k}-{s}" for k, s in sorted(set(db) - set(da))],
        "drives": drives,
        "totals": {"a": side("a"), "b": side("b")},
        "paired": {
            "false_stops": {"b_fewer": fewer, "b_more": more,
                            "same": len(drives) - fewer - more,
                            "sign_test_p": round(sign_test(fewer, more), 4)},
            "collisions": {"b_fewer": cfewer, "b_more": cmore,
                           "same": len(drives) - cfewer - cmore,
                           "sign_test_p": round(sign_test(cfewer, cmore), 4)},
            "first_difference": {"b_better": better, "b_worse": worse, "early": early,
                                 "never_parted": sum(1 for d in drives
                                                     if d["first_difference"] is None),
                                 "sign_test_p": round(sign_test(better, worse), 4)},
        },
    }


# ---------------------------------------------------------------------------------------------
def _first_text(f: dict | None) -> str:
    if f is None:
        return "never parted"
    head = (f"{f['t_s']:.1f} s: A {f['a']['state']}, B {f['b']['state']}"
            if f.get("t_s") is not None else f"A {f['a']['state']}, B {f['b']['state']}")
    if f.get("cautious") is None:
        return f"{head} ({f['judgement']})"
    near = f.get("real_nearest_m")
    truth = ("nothing real ahead" if near is None else
             f"real {f.get('real_obstacle') or 'obstacle'} {near:.1f} m, zone {f['stop_zone_m']:.1f} m")
    if f.get("real_meets"):
        truth += f"; walking in to meet the vehicle: {f['real_meets']}"
    who = f["cautious"].upper()
    verdict = {"right": "right", "early": "early", "phantom": "a phantom"}[f["judgement"]]
    return f"{head}; {truth}: {who}'s caution {verdict}"


def format_compare(c: dict) -> str:
    def boot(side):
        src = c.get(f"{side}_models_from")
        return "" if not src else f"; booted with the models of {src}"
    lines = [f"A = {c['a']} (commit {c['a_commit']}{boot('a')})",
             f"B = {c['b']} (commit {c['b_commit']}{boot('b')})",
             f"{len(c['drives'])} drives in common, {c['minutes_per_drive']} min each"
             + (" (acceptance seeds)" if c["acceptance_seeds"] else "")]
    for k in ("only_in_a", "only_in_b"):
        if c[k]:
            lines.append(f"{k.replace('_', ' ')} (not compared): {', '.join(c[k])}")
    lines.append(f"{'drive':32s} {'false A/B':>9s} {'coll A/B':>8s} {'missed A/B':>10s}  "
                 f"first difference")
    for d in c["drives"]:
        a, b = d["a"], d["b"]
        lines.append(f"{d['kind'] + '-' + str(d['seed']):32s} "
                     f"{a['false_stops']:>4d}/{b['false_stops']:<4d} "
                     f"{a['collisions']:>3d}/{b['collisions']:<4d} "
                     f"{a['missed_stops']:>5d}/{b['missed_stops']:<4d}  "
                     f"{_first_text(d['first_difference'])}")
    for s in ("a", "b"):
        t = c["totals"][s]
        ci = t["false_stops_per_hour_ci95"]
        cis = "-" if ci[0] is None else f"[{ci[0]:.1f}, {ci[1]:.1f}]"
        lines.append(f"{s.upper()}: {t['simulated_hours']:.2f} h, {t['collisions']} collisions, "
                     f"{t['false_stops']} false stops ({t['false_stops_per_hour']}/h {cis}), "
                     f"{t['true_stops']} true, {t['missed_stops']} missed")
    p = c["paired"]
    fs, co, fd = p["false_stops"], p["collisions"], p["first_difference"]
    lines.append(f"paired, false stops: B fewer in {fs['b_fewer']} drives, more in "
                 f"{fs['b_more']}, same in {fs['same']} (sign test p = {fs['sign_test_p']})")
    lines.append(f"paired, collisions: B fewer in {co['b_fewer']} drives, more in "
                 f"{co['b_more']}, same in {co['same']} (sign test p = {co['sign_test_p']})")
    lines.append(f"first differences: B better in {fd['b_better']}, worse in {fd['b_worse']}, "
                 f"early (not counted) {fd['early']}, never parted {fd['never_parted']} "
                 f"(sign test p = {fd['sign_test_p']})")
    return "\n".join(lines)


def compare_png(c: dict, out) -> Path:
    """One picture of the comparison: per drive, A's and B's false stops (bars), collisions
    (crosses) and when the drives first parted (a mark on the drive's time line: green where
    B was better there, red where worse, grey when not the box's doing)."""
    import cv2

    from appliance.campaign_report import BLACK, FONT, GREY, LIGHT, _blank, text
    A_COL, B_COL = (180, 110, 30), (0, 140, 255)
    drives = c["drives"]
    row_h, top, w = 24, 70, 1000
    img = _blank(w, top + row_h * max(1, len(drives)) + 60)
    text(img, f"A = {c['a']}   B = {c['b']}", (10, 20), 0.45)
    text(img, "false stops (A blue, B orange)", (260, 50), 0.42, GREY)
    text(img, "collisions", (560, 50), 0.42, GREY)
    text(img, "first difference in the drive (green: B better, red: B worse)", (660, 50),
         0.42, GREY)
    fmax = max([1] + [max(d["a"]["false_stops"], d["b"]["false_stops"]) for d in drives])
    for i, d in enumerate(drives):
        y = top + i * row_h
        if i % 2:
            cv2.rectangle(img, (0, y - 2), (w, y + row_h - 2), (245, 245, 245), -1)
        text(img, f"{d['kind']}-{d['seed']}", (10, y + 14), 0.4)
        for j, (side, col) in enumerate((("a", A_COL), ("b", B_COL))):
            n = int(d[side]["false_stops"] or 0)
            L = int(250 * n / fmax)
            yy = y + 2 + j * 9
            cv2.rectangle(img, (260, yy), (260 + max(L, 1), yy + 7), col, -1)
            text(img, str(n), (264 + L, yy + 8), 0.33)
        for j, (side, col) in enumerate((("a", A_COL), ("b", B_COL))):
            for k in range(int(d[side]["collisions"] or 0)):
                cx, cy = 565 + j * 40 + k * 9, y + 10
                cv2.line(img, (cx - 3, cy - 3), (cx + 3, cy + 3), col, 2)
                cv2.line(img, (cx - 3, cy + 3), (cx + 3, cy - 3), col, 2)
        x0, x1 = 660, w - 20
        cv2.line(img, (x0, y + 10), (x1, y + 10), LIGHT, 2)
        f = d["first_difference"]
        total = float(d["a"]["simulated_s"] or 0.0) or 1.0
        if f is not None and f.get("t_s") is not None:
            if f.get("cautious") is None or f["judgement"] == "early":
                col = GREY
            else:
                good = (f["cautious"] == "b") == (f["judgement"] == "right")
                col = (0, 160, 0) if good else (0, 0, 220)
            cx = int(x0 + (x1 - x0) * min(1.0, f["t_s"] / total))
            cv2.circle(img, (cx, y + 10), 5, col, -1)
            lab = f"{f['a']['state']}/{f['b']['state']}"
            tw = cv2.getTextSize(lab, FONT, 0.33, 1)[0][0]
            tx = cx + 8 if cx + 8 + tw <= x1 else cx - 8 - tw
            text(img, lab, (tx, y + 14), 0.33, BLACK)
    p = c["paired"]
    yb = top + row_h * max(1, len(drives)) + 20
    text(img, f"first differences: B better {p['first_difference']['b_better']}, worse "
              f"{p['first_difference']['b_worse']} (p = {p['first_difference']['sign_test_p']}); "
              f"false stops A {c['totals']['a']['false_stops']}, B "
              f"{c['totals']['b']['false_stops']}; collisions A {c['totals']['a']['collisions']}"
              f", B {c['totals']['b']['collisions']}", (10, yb), 0.45)
    out = Path(out)
    if not cv2.imwrite(str(out), img):
        raise CompareError(f"{out}: cannot write the picture")
    return out


def register(sub) -> None:
    c = sub.add_parser(
        "campaign-compare", help="compare two campaigns of the same drives, drive by drive",
        description="Compare campaign folders A and B (the same scene kinds, seeds and "
                    "minutes under two configurations) drive by drive: each drive's counts, "
                    "the first cycle where the two boxes decided differently and whether the "
                    "more cautious one was right (a real obstacle within the zones) or a "
                    "phantom, and exact sign tests over the drives.")
    c.add_argument("a", metavar="A", help="campaign folder (the baseline)")
    c.add_argument("b", metavar="B", help="campaign folder (the change)")
    c.add_argument("--json", action="store_true", help="print the comparison as JSON")
    c.add_argument("--png", metavar="FILE", help="also draw the comparison into FILE (.png)")
    c.set_defaults(func=cmd_compare)


def cmd_compare(a) -> int:
    import sys
    try:
        c = compare(a.a, a.b)
        if a.png:
            compare_png(c, a.png)
    except CompareError as exc:
        print(f"fieldguard campaign-compare: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(c, indent=1) if a.json else format_compare(c))
    return 0
