"""Does a box that boots with a learnt novelty model stop at boot? Each campaign drive twice on
the same field: first from an empty state (as every campaign drive boots), saving its model at
the end (``model_state`` = a file of this tool's); then again from the start, loading that
model (as an installed box boots after the periodic save, ``model_save_s``). Prints per drive
and in total the false stops of each run, those in the first 10 s (``BOOT_S``) apart.

    python tools/boot_with_model.py --scene stubble-coverage,stubble-coverage-night \
        --seeds 79-84 --minutes 1 [--config sl.toml] --out DIR [--json]

A proxy for the morning boot: the second run boots where the first began, with the model the
first had at its end (one minute on, the same light), not with yesterday's. Training seeds only
when a rule is to be judged on it later.

    python tools/boot_with_model.py --scene stubble-coverage,stubble-coverage-night \
        --seeds 79-84 --cross --out DIR

``--cross`` (two scenes): the second run of each scene loads the model the *other* scene's
first run saved, seed for seed: a box that saved its model at night and boots by day, and the
other way round (the saved model does not say what light it was learnt under).

``--other-field``: the seeds in pairs (79,80), (81,82), ...: the second run of each drive
loads the model the same scene's drive of the other seed saved: another field of the same
kind and light (a box moved to the next field with yesterday's model).

``--per-light`` (with ``--cross``): the second run also finds, beside the other scene's model,
the per-light files its own scene's first run saved (the box keeps its strobe-lit model in a
file of its own, ``<file>.night-strobe.npz``, which a day save does not replace): a box that
worked the field at night, then by day, and boots at night again.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from appliance.campaign import parse_seeds as seeds_of  # noqa: E402  (the campaign's own)
from appliance.novelty_store import light_path  # noqa: E402  (the box's own naming)

KEYS = ("false_stops", "false_stops_boot", "true_stops", "missed_stops", "collisions")


def one(kind: str, seed: int, minutes: float, extra: dict | None, model: Path) -> dict:
    from appliance.campaign import make_spec, run_drive, with_model_state
    r = run_drive(make_spec(kind, seed, minutes, 0.5, with_model_state(extra or {}, model))
                  )["result"]
    return {k: r.get(k, 0) for k in KEYS}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--seeds", required=True)
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--config", default=None)
    ap.add_argument("--out", required=True)
    ap.add_argument("--cross", action="store_true",
                    help="two scenes: each boots with the other's model (the same seed)")
    ap.add_argument("--other-field", action="store_true",
                    help="seeds in pairs (an even number): each drive's second run loads the "
                         "model of the same scene's drive of the other seed of its pair (a box "
                         "moved to another field)")
    ap.add_argument("--per-light", action="store_true",
                    help="with --cross: the second run also has its own scene's per-light "
                         "files (the night model kept apart) beside the other's model")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from appliance.campaign import (NOVELTY_PIPELINES, CampaignError, load_extra_config,
                                    make_spec)
    try:
        seeds = seeds_of(a.seeds)
    except CampaignError as exc:
        print(f"boot_with_model: error: --seeds wants N, N-M or lists of them ({exc})",
              file=sys.stderr)
        return 2
    extra = load_extra_config(a.config) if a.config else None
    kinds = [k for k in a.scene.split(",") if k]
    if a.other_field and (a.cross or len(seeds) % 2):
        print("boot_with_model: error: --other-field wants an even number of seeds (each loads "
              "the model of the other seed of its pair), and not --cross", file=sys.stderr)
        return 2
    if a.per_light and not a.cross:
        print("boot_with_model: error: --per-light goes with --cross (without it each run "
              "loads its own model, of its own light)", file=sys.stderr)
        return 2
    if a.cross and len(kinds) != 2:
        print("boot_with_model: error: --cross wants two scenes (--scene A,B): each boots with "
              "the other's model", file=sys.stderr)
        return 2
    try:
        pipes = [p for k in kinds for p in make_spec(k, seeds[0], a.minutes, 0.5, extra)
                 ["config"]["perception"]["pipelines"]]
    except ValueError as exc:                          # an unknown scene, named with the known
        print(f"boot_with_model: error: {exc}", file=sys.stderr)
        return 2
    if not any(p in NOVELTY_PIPELINES for p in pipes):
        print("boot_with_model: error: the drives must run stereo-novelty (the novelty model "
              "is what is carried over): set [perception] pipelines in --config",
              file=sys.stderr)
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    n, i = len(kinds) * len(seeds), 0
    # each group's runs from empty, then each of them again loading a model: its own, or with
    # --cross the other scene's of the same seed (both scenes of a seed are one group), or
    # with --other-field the same scene's of the other seed of a pair
    if a.cross:
        groups = [[(k, seed) for k in kinds] for seed in seeds]
    elif a.other_field:
        groups = [[(k, s1), (k, s2)] for k in kinds for s1, s2 in zip(seeds[::2], seeds[1::2])]
    else:
        groups = [[(k, seed)] for k in kinds for seed in seeds]
    for group in groups:
        firsts = []
        for k, seed in group:
            m = out / f"{k}-{seed}.npz"
            for old in (m, *out.glob(f"{k}-{seed}.*.npz")):    # and its per-light files
                old.unlink(missing_ok=True)
            print(f"[{i + 1}/{n}] {k} {seed}: from empty...", file=sys.stderr, flush=True)
            firsts.append(one(k, seed, a.minutes, extra, m))
            if not m.exists():
                print(f"boot_with_model: error: {k} {seed}: no model was saved (does the "
                      "config run stereo-novelty?)", file=sys.stderr)
                return 1
        for (k, seed), first in zip(group, firsts):
            i += 1
            sk, ss = next(x for x in group if x != (k, seed)) if len(group) > 1 else (k, seed)
            source = sk if a.cross else f"{sk} {ss}" if a.other_field else k
            loaded_file = out / f"{k}-{seed}.npz"
            if len(group) > 1:    # a copy: the run saves its own model at its end, over it
                loaded_file = out / f"{k}-{seed}-with-{source.replace(' ', '-')}.npz"
                loaded_file.write_bytes((out / f"{sk}-{ss}.npz").read_bytes())
                for f in out.glob(f"{loaded_file.stem}.*.npz"):
                    f.unlink()
                if a.per_light:   # its own scene's night model (and any other light's) beside
                    for f in out.glob(f"{k}-{seed}.*.npz"):
                        light = f.name[len(f"{k}-{seed}."):-len(".npz")]
                        light_path(loaded_file, light).write_bytes(f.read_bytes())
            print(f"[{i}/{n}] {k} {seed}: with the model of {source}...", file=sys.stderr,
                  flush=True)
            rows.append({"kind": k, "seed": seed, "empty": first, "model_of": source,
                         "loaded": one(k, seed, a.minutes, extra, loaded_file)})
            (out / "rows.json").write_text(json.dumps(rows, indent=1))
    tot = {w: {k: sum(r[w][k] for r in rows) for k in KEYS} for w in ("empty", "loaded")}
    if a.json:
        print(json.dumps({"rows": rows, "total": tot}))
        return 0
    print(f"{'drive':32s} {'empty: false (boot)':>20s} {'loaded: false (boot)':>21s}  model of")
    for r in rows:
        e, lo = r["empty"], r["loaded"]
        print(f"{r['kind'] + ' ' + str(r['seed']):32s} {e['false_stops']:>12d} ({e['false_stops_boot']})"
              f" {lo['false_stops']:>14d} ({lo['false_stops_boot']})  {r['model_of']}")
    for w in ("empty", "loaded"):
        t = tot[w]
        print(f"{w}: false stops {t['false_stops']} ({t['false_stops_boot']} in the first 10 s), "
              f"true {t['true_stops']}, missed {t['missed_stops']}, collisions {t['collisions']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
