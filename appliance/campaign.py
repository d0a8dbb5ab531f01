"""``fieldguard campaign``: closed-loop coverage drives, many (scene kind, seed) at once, on Ray.

    fieldguard campaign --scene stubble-coverage,stubble-coverage-night,greenhouse-coverage \\
        --seeds 1000-1003 --minutes 20 --out /tmp/camp [--workers 2] [--address ADDR] \\
        [--config extra.toml] [--stereo-scale 0.5]

Each drive is one (kind, seed): the real daemon in lock-step with the simulated field for the
given simulated minutes (appliance/campaign_drive.py). ``--workers 1`` runs the drives one after
the other in this process, without Ray; ``--workers N`` (default: all cores) starts a local Ray
in-process with N CPUs and runs each drive as a Ray task (``@ray.remote``, one CPU each);
``--address`` joins an existing Ray cluster instead (its nodes need fieldguard installed). The
same drive gives the same figures either way (ManualClock, everything seeded, one OpenCV thread
per drive).

Resumable: each finished drive writes ``DIR/drives/KIND-SEED/`` (cycles.csv, events.json, then
result.json, each written to a temporary name and renamed); a rerun skips the drives whose
result.json is there with the same settings. ``DIR/summary.json`` and ``DIR/report.md`` (with
PNG plots) are rewritten from all the campaign's drives at the end.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from hal.errors import FieldguardError

COMPARE_EXCLUDE = ("engine", "workers", "timing", "provenance")   # differ by construction
SUMMARY_KEYS = ("drives", "simulated_hours", "distance_km", "collisions", "false_stops",
                "false_stops_per_hour", "false_stops_per_hour_ci95", "true_stops",
                "missed_stops", "fault_stops", "detours", "overrides", "false_stop_s",
                "slow_for_nothing_s", "detection_distance_m", "false_stops_by_place",
                "false_stops_by_cause", "model")


class CampaignError(FieldguardError):
    """A bad campaign argument or out dir (exit 2 with the message, never a traceback)."""


# ---------------------------------------------------------------------------------------------
# arguments
# ---------------------------------------------------------------------------------------------
def scene_kinds() -> dict[str, str]:
    from drivers.sim import scenes
    return getattr(scenes, "SCENE_KINDS", None) or scenes.SCENES


def parse_kinds(text: str) -> list[str]:
    kinds = [k.strip() for k in (text or "").split(",") if k.strip()]
    if not kinds:
        raise CampaignError("--scene: give one or more scene kinds, e.g. --scene "
                            "stubble-coverage,stubble-coverage-night")
    known = scene_kinds()
    bad = [k for k in kinds if k not in known]
    if bad:
        raise CampaignError(f"--scene: unknown scene kind {', '.join(map(repr, bad))}; known "
                            f"kinds: {', '.join(sorted(known))}")
    if len(set(kinds)) != len(kinds):
        raise CampaignError(f"--scene: a kind is named twice in {text!r}")
    return kinds


def parse_seeds(text: str) -> list[int]:
    """'A-B' (inclusive), 'A', or a comma list of those: '0-3,10'."""
    seeds: list[int] = []
    for part in (text or "").split(","):
        part = part.strip()
        if not part:
            continue
        a, sep, b = part.partition("-")
        try:
            lo = int(a)
            hi = int(b) if sep else lo
        except ValueError:
            raise CampaignError(f"--seeds: {part!r} is not a seed or a range A-B of seeds "
                                "(whole numbers >= 0, e.g. --seeds 1000-1005)") from None
        if lo < 0 or hi < lo:
            raise CampaignError(f"--seeds: bad range {part!r}: seeds are >= 0 and A <= B "
                                "(e.g. --seeds 1000-1005)")
        if hi - lo >= 100000:
            raise CampaignError(f"--seeds: range {part!r} is too long (at most 100000 seeds)")
        seeds.extend(range(lo, hi + 1))
    if not seeds:
        raise CampaignError("--seeds: give a seed range, e.g. --seeds 1000-1005 (seeds >= 1000 "
                            "are the acceptance set)")
    if len(set(seeds)) != len(seeds):
        raise CampaignError(f"--seeds: a seed is named twice in {text!r}")
    return seeds


def check_out_dir(out) -> Path:
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise CampaignError(f"--out {out}: exists and is not a directory; give a directory")
    try:
        (p / "drives").mkdir(parents=True, exist_ok=True)
        probe = p / f".write-test-{os.getpid()}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise CampaignError(f"--out {out}: cannot write there ({exc.strerror or exc}); give a "
                            "directory you can write to") from None
    return p


def load_extra_config(path, option: str = "--config") -> dict:
    """A --config (or --shadow) file's tables (merged over each drive's config); checked here
    once so a bad file is one clear error before any drive starts."""
    if not path:
        return {}
    import tomllib
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise CampaignError(f"{option} {path}: cannot read it ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise CampaignError(f"{option} {path}: not valid TOML: {exc}") from None
    from appliance.config import parse_config
    parse_config(data, str(path))          # ConfigError (a FieldguardError) names the key
    return data


# ---------------------------------------------------------------------------------------------
# one drive (runs here, or in a Ray worker)
# ---------------------------------------------------------------------------------------------
def drive_id(kind: str, seed: int) -> str:
    return f"{kind}-{seed}"


def make_spec(kind: str, seed: int, minutes: float, stereo_scale: float,
              extra: dict | None = None, shadow: dict | None = None) -> dict:
    """One drive's settings; with ``shadow`` (a --shadow file's tables) also the whole config
    of a second configuration judged on the drive's inputs (appliance/campaign_shadow.py)."""
    from appliance.campaign_drive import drive_config_data
    spec = {"kind": kind, "seed": int(seed), "minutes": float(minutes),
            "stereo_scale": float(stereo_scale),
            "config": drive_config_data(kind, seed, stereo_scale=stereo_scale, extra=extra)}
    if shadow is not None:
        spec["shadow"] = drive_config_data(kind, seed, stereo_scale=stereo_scale,
                                           extra=shadow)
    return spec


# The novelty model a drive saves (--save-models) or boots with (--models-from): the files in
# DIR/drives/KIND-SEED/models/, named as the box names its state (the latest model, and beside
# it the strobe-lit one: appliance/novelty_store.light_path)
MODEL_DIR = "models"
MODEL_FILE = "novelty.npz"
NOVELTY_PIPELINES = ("stereo-novelty", "fused")


def with_model_state(data: dict, model_file) -> dict:
    """Config data whose stereo-novelty model persists in ``model_file``: loaded at start,
    saved at the daemon's shutdown only (a drive's end), as the box keeps its state."""
    from appliance.campaign_drive import deep_merge
    return deep_merge(data, {"perception": {"stereo-novelty": {
        "model_state": str(model_file), "model_save_s": 0.0}}})


def run_drive(spec: dict, report=None, models: dict | None = None) -> dict:
    """Drive one spec; ``report(sim_s)`` is called every 30 simulated seconds. ``models``
    ({file name: bytes}, the files of a drive's MODEL_DIR): the box boots with them, as an
    installed box boots with the model it saved. With ``spec["save_models"]`` the drive's
    models at its end (saved at the daemon's shutdown, as the box saves them) are returned as
    ``out["models"]``, the same form. Bytes, not paths: a Ray worker may be another machine."""
    import shutil
    import tempfile

    from appliance.campaign_drive import Drive
    cb = None
    if report is not None:
        def cb(done, _total):
            report(done / 10.0)
    config, shadow, tmp = spec["config"], spec.get("shadow"), None
    if models or spec.get("save_models"):
        tmp = Path(tempfile.mkdtemp(prefix="fieldguard-drive-models-"))
        for name, data in (models or {}).items():
            (tmp / Path(name).name).write_bytes(data)
        config = with_model_state(config, tmp / MODEL_FILE)
        if shadow is not None:           # the shadow boots with the same model (it never saves)
            shadow = with_model_state(shadow, tmp / MODEL_FILE)
    try:
        d = Drive(spec["kind"], spec["seed"], spec["minutes"], config_data=config,
                  stereo_scale=spec["stereo_scale"], progress=cb, shadow_config=shadow)
        out = d.run()
        if spec.get("save_models"):
            out["models"] = {f.name: f.read_bytes() for f in sorted(tmp.glob("*.npz"))}
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    out["result"]["spec"] = spec
    return out


def _ray_drive(spec: dict, tracker=None, niceness: int | None = None,
               models: dict | None = None) -> dict:
    """The Ray task: a drive, its progress sent to the tracker actor. Ray starts its workers
    at a lower priority than the driver (nice + 15 here); the drive's thread, and the threads
    it starts, go back to the campaign's own niceness, so ``nice -n 10 fieldguard campaign``
    means the same for 1 worker as for N."""
    if niceness is not None:
        try:
            if os.getpriority(os.PRIO_PROCESS, 0) > niceness:
                os.setpriority(os.PRIO_PROCESS, 0, niceness)
        except (OSError, AttributeError):
            pass                         # not allowed to raise it back: run as Ray set it
    rep = None
    if tracker is not None:
        key = drive_id(spec["kind"], spec["seed"])

        def rep(sim_s):
            tracker.report.remote(key, sim_s)
    return run_drive(spec, rep, models)


class _Tracker:
    """Ray actor: the simulated seconds each running drive has done (for the progress bar)."""

    def __init__(self):
        self.done: dict[str, float] = {}

    def report(self, key: str, sim_s: float) -> None:
        self.done[key] = sim_s

    def get(self) -> dict:
        return dict(self.done)


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_drive(out: Path, drive: dict) -> None:
    from appliance.campaign_drive import ROW_FIELDS
    r = drive["result"]
    d = out / "drives" / drive_id(r["kind"], r["seed"])
    d.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    w = csv.DictWriter(buf, ROW_FIELDS, extrasaction="ignore")
    w.writeheader()
    for row in drive["rows"]:
        w.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in ROW_FIELDS})
    _atomic_write(d / "cycles.csv", buf.getvalue())
    _atomic_write(d / "events.json", json.dumps(drive["events"], indent=1))
    if drive.get("models") is not None:
        m = d / MODEL_DIR
        m.mkdir(exist_ok=True)
        for name, data in drive["models"].items():
            tmp = m / f".{name}.tmp-{os.getpid()}"
            tmp.write_bytes(data)
            os.replace(tmp, m / name)
    _atomic_write(d / "result.json", json.dumps(r, indent=1))      # last: marks it finished


def read_result(out: Path, kind: str, seed: int) -> dict | None:
    p = out / "drives" / drive_id(kind, seed) / "result.json"
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text("utf-8"))
    except (OSError, ValueError):
        return None                      # a torn file: drive it again


# ---------------------------------------------------------------------------------------------
# the summary
# ---------------------------------------------------------------------------------------------
def poisson_ci95(k: int, exposure: float) -> list[float | None]:
    """Exact (Garwood) 95 % interval of a Poisson rate: k events in ``exposure`` (hours).

    The textbook form is chi2.ppf(q, 2k) / 2, which is the inverse of the regularised lower
    incomplete gamma function, gammaincinv(k, q): the same numbers (tests/test_campaign.py
    checks them against scipy.stats for k up to 200), from scipy.special, which the tracker's
    scipy.optimize loads anyway, where scipy.stats cost every campaign process 2.6 CPU-s of
    imports for two numbers (2026-12-07)."""
    from scipy.special import gammaincinv
    if exposure <= 0:
        return [None, None]
    lo = 0.0 if k == 0 else float(gammaincinv(k, 0.025))
    hi = float(gammaincinv(k + 1, 0.975))
    return [round(lo / exposure, 3), round(hi / exposure, 3)]


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    if not n:
        return None
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def aggregate(results: list[dict]) -> dict:
    """The campaign figures over some drives' results (all of them, or one kind's)."""
    hours = sum(r["simulated_s"] for r in results) / 3600.0
    tot = lambda k: sum(int(r[k]) for r in results)  # noqa: E731
    fs = tot("false_stops")
    det: dict[str, list] = {}
    for r in results:
        for d in r["detections"]:
            det.setdefault(d["cls"], []).append(d["distance_m"])
    detection = {}
    for cls, ds in sorted(det.items()):
        held = [x for x in ds if x is not None]
        detection[cls] = {"min": None if not held else round(min(held), 2),
                          "median": None if not held else round(_median(held), 2),
                          "stops": len(ds), "stopped_without_hold": len(ds) - len(held)}
    by_place: dict[str, int] = {}
    by_cause: dict[str, int] = {}
    by_contact: dict[str, int] = {}
    for r in results:
        for k, v in r["false_stops_by_place"].items():
            by_place[k] = by_place.get(k, 0) + v
        for k, v in r["false_stops_by_cause"].items():
            by_cause[k] = by_cause.get(k, 0) + v
        for k, v in r.get("collisions_by_contact", {}).items():   # older results lack it
            by_contact[k] = by_contact.get(k, 0) + v
    samples = [r["model"]["samples_max"] for r in results if r["model"]["samples_max"]]
    # the false stops after each drive's first BOOT_S (a drive boots the box; a field box boots
    # once a day): per hour of the time after them. None when a result predates the count
    from appliance.campaign_drive import BOOT_S
    boot = None if any("false_stops_boot" not in r for r in results) else \
        tot("false_stops_boot")
    after_h = sum(max(0.0, r["simulated_s"] - BOOT_S) for r in results) / 3600.0
    after = None if boot is None else {
        "boot_s": BOOT_S, "false_stops": fs - boot, "hours": round(after_h, 6),
        "false_stops_per_hour": None if after_h <= 0 else round((fs - boot) / after_h, 3),
        "false_stops_per_hour_ci95": poisson_ci95(fs - boot, after_h)}
    shadow = None
    sh = [r["shadow"] for r in results if r.get("shadow")]
    if sh:
        keys = ("true_stops", "false_stops", "fault_stops", "missed_stops",
                "false_stops_primary_only", "false_stops_shadow_only",
                "true_stops_primary_only", "true_stops_shadow_only")
        shadow = {k: sum(x[k] for x in sh) for k in keys}
        shadow["false_stops_per_hour"] = None if hours <= 0 else \
            round(shadow["false_stops"] / hours, 3)
        shadow["false_stops_per_hour_ci95"] = poisson_ci95(shadow["false_stops"], hours)
        from appliance.campaign_shadow import differences
        shadow["differences"] = differences(results)
    # the people standing in the path when the box started (stubble-boot): how each fared
    ab = [b for r in results for b in r.get("at_boot", ())]
    at_boot = None if not ab else {
        "obstacles": len(ab),
        "held_from_first_s": sum(bool(b["held_from_first_s"]) for b in ab),
        "stopped": sum(bool(b["stopped"]) for b in ab),
        "collisions": sum(bool(b["collision"]) for b in ab),
        "missed": sum(bool(b["missed"]) for b in ab),
        "never_held": sum(b["first_held_s"] is None for b in ab),
        "first_held_s_max": max((b["first_held_s"] for b in ab
                                 if b["first_held_s"] is not None), default=None)}
    out = {
        "drives": len(results),
        "simulated_hours": round(hours, 6),
        "distance_km": round(sum(r["distance_m"] for r in results) / 1000.0, 3),
        "collisions": tot("collisions"),
        "collisions_by_contact": dict(sorted(by_contact.items())),
        "false_stops": fs,
        "false_stops_per_hour": None if hours <= 0 else round(fs / hours, 3),
        "false_stops_per_hour_ci95": poisson_ci95(fs, hours),
        "false_stops_boot": boot,
        "after_boot": after,
        "true_stops": tot("true_stops"),
        "missed_stops": tot("missed_stops"),
        "fault_stops": tot("fault_stops"),
        "detours": tot("detours"),
        "overrides": tot("overrides"),
        "false_stop_s": round(sum(r["false_stop_s"] for r in results), 1),
        # (a result.json written before the thirty-eighth session has none: 0)
        "slow_for_nothing_s": round(sum(r.get("slow_for_nothing_s", 0.0) for r in results), 1),
        "detection_distance_m": detection,
        "at_boot": at_boot,
        "false_stops_by_place": dict(sorted(by_place.items())),
        "false_stops_by_cause": dict(sorted(by_cause.items(), key=lambda kv: -kv[1])),
        "model": {"samples_max": max(samples, default=None),
                  "bytes_max": None if not samples else 40 * max(samples),
                  "bound": max((r["model"]["bound"] or 0 for r in results), default=0) or None},
    }
    if shadow is not None:
        out["shadow"] = shadow
    return out


def _commit() -> str | None:
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"],
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--",
                                "appliance", "drivers", "hal"], capture_output=True, text=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + ("+uncommitted" if dirty else "")) if head else None


def summarise(results: list[dict], *, engine: str, workers: int, kinds: list[str],
              seeds: list[int], timing: dict, provenance: dict) -> dict:
    results = sorted(results, key=lambda r: (kinds.index(r["kind"]), r["seed"]))
    s = {"engine": engine, "workers": workers, "kinds": kinds,
         "seeds": [min(seeds), max(seeds)] if seeds else None,
         "acceptance_seeds": all(x >= 1000 for x in seeds),
         "minutes_per_drive": results[0]["minutes"] if results else None,
         "stereo_scale": results[0]["stereo_scale"] if results else None,
         **aggregate(results)}
    s["per_scene"] = {k: {**aggregate([r for r in results if r["kind"] == k]),
                          "pipelines": next((r["pipelines"] for r in results
                                             if r["kind"] == k), None),
                          "image_px": next((r["image_px"] for r in results
                                            if r["kind"] == k), None),
                          "stopping_distance_at_cruise_m": next(
                              (r["stopping_distance_at_cruise_m"] for r in results
                               if r["kind"] == k), None)}
                      for k in kinds}
    s["per_drive"] = [{k: r[k] for k in ("kind", "seed", "simulated_s", "distance_m",
                                         "collisions", "true_stops", "false_stops",
                                         "missed_stops", "fault_stops", "detours",
                                         "overrides")} for r in results]
    # the host's figures: not part of the result (they differ run to run)
    cpu = sum(r["timing"]["process_cpu_s"] for r in results)
    sim_h = s["simulated_hours"]
    stage = {}
    for st in ("acquire", "perception", "fusion", "gate", "send"):
        vals = [r["timing"]["stage_wall_ms_p50"][st] for r in results
                if r["timing"]["stage_wall_ms_p50"].get(st) is not None]
        stage[st] = None if not vals else round(_median(vals), 2)
    s["timing"] = {**timing,
                   "drives_cpu_s": round(cpu, 1),
                   "simulated_hours_per_cpu_hour": None if cpu <= 0 else
                   round(sim_h / (cpu / 3600.0), 3),
                   "simulated_hours_per_wall_hour": None if not timing.get("wall_s") else
                   round(sim_h / (timing["wall_s"] / 3600.0), 3),
                   "stage_wall_ms_p50_median": stage,
                   "render_cpu_ms_p50_median": _median([r["timing"]["render_cpu_ms_p50"]
                                                       for r in results
                                                       if r["timing"]["render_cpu_ms_p50"]]),
                   "pipeline_cpu_ms_p50_median": _median(
                       [r["timing"]["pipeline_cpu_ms_p50"] for r in results
                        if r["timing"]["pipeline_cpu_ms_p50"]]),
                   "rss_mb_max": max((r["timing"]["rss_mb_max"] or 0 for r in results),
                                     default=None)}
    s["provenance"] = provenance
    return s


# ---------------------------------------------------------------------------------------------
# progress over the whole campaign
# ---------------------------------------------------------------------------------------------
class CampaignProgress:
    """drives done, simulated hours, ETA; a live bar on a terminal, a line a minute (and one
    per finished drive) in a log."""

    def __init__(self, total_drives: int, total_sim_h: float, stream=None, enabled=True):
        self.n, self.h = total_drives, max(total_sim_h, 1e-9)
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.enabled = enabled
        self.t0 = time.monotonic()
        self._last = -1e9
        self.skipped_h = 0.0

    def __call__(self, drives_done: int, sim_h_done: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not self.tty and not force and now - self._last < 60:
            return
        if self.tty and not force and now - self._last < 0.5:
            return
        self._last = now
        frac = min(1.0, sim_h_done / self.h)
        el = now - self.t0
        ran = sim_h_done - self.skipped_h
        left = self.h - sim_h_done
        eta = f"{el / ran * left / 60:.1f} min" if ran > 1e-6 else "?"
        bar = "#" * int(30 * frac)
        text = (f"campaign [{bar:<30}] {drives_done}/{self.n} drives, {sim_h_done:.2f}/"
                f"{self.h:.2f} sim h, {el / 60:.1f} min, eta {eta}")
        if self.tty:
            self.stream.write("\r" + text + ("\n" if drives_done >= self.n else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


# ---------------------------------------------------------------------------------------------
# the campaign
# ---------------------------------------------------------------------------------------------
class Campaign:
    def __init__(self, kinds, seeds, minutes: float, out, *, workers: int | None = None,
                 address: str | None = None, config_file: str | None = None,
                 stereo_scale: float = 0.5, progress: bool = True, report: bool = True,
                 command: str = "", shadow_file: str | None = None,
                 save_models: bool = False, models_from: str | None = None):
        self.kinds = parse_kinds(kinds) if isinstance(kinds, str) else list(kinds)
        self.seeds = parse_seeds(seeds) if isinstance(seeds, str) else list(seeds)
        if not (isinstance(minutes, (int, float)) and math.isfinite(minutes) and minutes > 0):
            raise CampaignError(f"--minutes {minutes}: give simulated minutes per drive > 0")
        if not 0.1 <= float(stereo_scale) <= 1.0:
            raise CampaignError(f"--stereo-scale {stereo_scale}: give a fraction of 1280x1024 "
                                "in [0.1, 1] (0.5: 640x512)")
        if workers is not None and workers < 1:
            raise CampaignError(f"--workers {workers}: give 1 or more (1 runs without Ray)")
        if workers is not None and workers > 1 and address:
            pass                         # on a cluster, --workers caps nothing: Ray schedules
        self.minutes, self.stereo_scale = float(minutes), float(stereo_scale)
        self.workers = workers if workers is not None else (os.cpu_count() or 1)
        self.address = address
        self.extra = load_extra_config(config_file)
        self.config_file = config_file
        self.shadow_file = shadow_file
        self.shadow = load_extra_config(shadow_file, "--shadow") if shadow_file else None
        self.progress, self.report, self.command = progress, report, command
        # seed by seed, each seed over the kinds: a campaign stopped early has every kind
        self.specs = [make_spec(k, s, self.minutes, self.stereo_scale, self.extra, self.shadow)
                      for s in self.seeds for k in self.kinds]
        self.save_models, self.models_from = bool(save_models), models_from
        self.boot_models: dict[str, dict] = {}     # drive id -> {file name: bytes}
        if save_models or models_from:
            self._plan_models()
        self.out = check_out_dir(out)        # last: a refused campaign leaves no folder
        self.interrupted = False
        self.failed: dict[str, str] = {}

    def _plan_models(self) -> None:
        """--save-models / --models-from: every drive must run a novelty pipeline, and with
        --models-from every drive must find its model in that campaign (checked before any
        drive starts). The spec says both, so a rerun with other models drives again."""
        import hashlib
        for sp in self.specs:
            if not set(sp["config"]["perception"]["pipelines"]) & set(NOVELTY_PIPELINES):
                raise CampaignError(
                    f"{'--models-from' if self.models_from else '--save-models'}: drive "
                    f"{drive_id(sp['kind'], sp['seed'])} runs no novelty model (pipelines "
                    f"{', '.join(sp['config']['perception']['pipelines'])}); give a --config "
                    "whose [perception] pipelines has stereo-novelty")
            if self.save_models:
                sp["save_models"] = True
        if not self.models_from:
            return
        src = Path(self.models_from).expanduser()
        if not (src / "drives").is_dir():
            raise CampaignError(f"--models-from {src}: not a campaign folder (no drives/ in it)")
        missing = []
        for sp in self.specs:
            key = drive_id(sp["kind"], sp["seed"])
            folder = src / "drives" / key / MODEL_DIR
            files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
            if not any(f.name == MODEL_FILE for f in files):
                missing.append(key)
                continue
            models = {f.name: f.read_bytes() for f in files}
            self.boot_models[key] = models
            sp["models_from"] = {"folder": str(folder.resolve()), "sha256": {
                n: hashlib.sha256(b).hexdigest()[:16] for n, b in models.items()}}
        if missing:
            raise CampaignError(
                f"--models-from {src}: no saved model for {len(missing)} of {len(self.specs)} "
                f"drives ({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}); "
                "drive those scenes and seeds there with --save-models first")

    def finished(self) -> dict[str, dict]:
        """The drives already done with these settings (skipped on a rerun)."""
        done = {}
        for sp in self.specs:
            r = read_result(self.out, sp["kind"], sp["seed"])
            if r is None:
                continue
            if r.get("spec") != json.loads(json.dumps(sp)):
                raise CampaignError(
                    f"--out {self.out}: drive {drive_id(sp['kind'], sp['seed'])} there was "
                    "driven with other settings (minutes, stereo scale or config); give another "
                    "--out, or delete that drive's folder to drive it again")
            done[drive_id(sp["kind"], sp["seed"])] = r
        return done

    def run(self) -> dict:
        t0 = time.time()
        w0, load0 = time.perf_counter(), os.getloadavg()
        done = self.finished()
        n_before = len(done)
        todo = [sp for sp in self.specs if drive_id(sp["kind"], sp["seed"]) not in done]
        use_ray = self.address is not None or self.workers > 1
        engine = "ray" if use_ray else "local"
        prog = CampaignProgress(len(self.specs), len(self.specs) * self.minutes / 60.0,
                                enabled=self.progress)
        prog.skipped_h = sum(r["simulated_s"] for r in done.values()) / 3600.0
        if done and self.progress:
            print(f"campaign: {len(done)} of {len(self.specs)} drives already in {self.out}, "
                  "skipped", file=sys.stderr)
        prog(len(done), prog.skipped_h, force=True)
        workers = self.workers
        if todo:
            try:
                if use_ray:
                    workers = self._run_ray(todo, done, prog)
                else:
                    self._run_local(todo, done, prog)
            except KeyboardInterrupt:      # ^C / SIGTERM: the finished drives' summary
                self.interrupted = True
        wall_s = time.perf_counter() - w0
        results = [done[drive_id(sp["kind"], sp["seed"])] for sp in self.specs
                   if drive_id(sp["kind"], sp["seed"]) in done]
        summary = summarise(
            results, engine=engine, workers=workers, kinds=self.kinds, seeds=self.seeds,
            timing={"wall_s": round(wall_s, 1), "drives_run": len(done) - n_before,
                    "drives_skipped": len(self.specs) - len(todo),
                    "loadavg_1min_start_end": [round(load0[0], 2),
                                               round(os.getloadavg()[0], 2)],
                    "cpu_count": os.cpu_count()},
            provenance={"command": self.command, "commit": _commit(),
                        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t0)),
                        "config_file": self.config_file, "shadow_file": self.shadow_file,
                        "address": self.address, "save_models": self.save_models,
                        "models_from": None if not self.models_from else
                        str(Path(self.models_from).expanduser().resolve())})
        if self.failed:
            summary["failed_drives"] = dict(self.failed)
        summary["complete"] = len(results) == len(self.specs)
        summary["drives_planned"] = len(self.specs)
        _atomic_write(self.out / "summary.json", json.dumps(summary, indent=2))
        if self.report and results:
            from appliance.campaign_report import write_report
            write_report(self.out, summary)
        if self.interrupted:
            raise CampaignError(
                f"interrupted: {len(results)} of {len(self.specs)} drives finished; their "
                f"summary is in {self.out}/summary.json; run the same command again to drive "
                "the rest")
        if self.failed:
            raise CampaignError(
                f"{len(self.failed)} drive(s) failed ({', '.join(sorted(self.failed))}); the "
                f"others are in {self.out}/summary.json; the first error: "
                f"{next(iter(self.failed.values()))}")
        return summary

    def _finish(self, drive: dict, done: dict) -> None:
        write_drive(self.out, drive)
        r = drive["result"]
        done[drive_id(r["kind"], r["seed"])] = r

    def _run_local(self, todo, done, prog) -> None:
        for sp in todo:
            key = drive_id(sp["kind"], sp["seed"])
            base = sum(r["simulated_s"] for r in done.values()) / 3600.0
            n_done = len(done)
            try:
                drive = run_drive(sp, lambda s: prog(n_done, base + s / 3600.0),
                                  self.boot_models.get(key))
            except FieldguardError:
                raise
            except Exception as exc:            # a drive's bug: report it, drive the others
                self.failed[key] = f"{key}: {type(exc).__name__}: {exc}"
                continue
            self._finish(drive, done)
            prog(len(done), sum(r["simulated_s"] for r in done.values()) / 3600.0, force=True)

    def _run_ray(self, todo, done, prog) -> int:
        try:
            import ray
        except ImportError:
            raise CampaignError(
                f"--workers {self.workers} needs Ray, which is not installed: pip install "
                "'fieldguard[campaign]' (or pip install ray), or run with --workers 1") from None
        started = not ray.is_initialized()
        if started:
            init_ray(self.workers, self.address)
            sigterm_interrupts()
        try:
            workers = int(ray.cluster_resources().get("CPU", self.workers))
            tracker = ray.remote(num_cpus=0)(_Tracker).remote()
            task = ray.remote(num_cpus=1, max_retries=0)(_ray_drive)
            nice = os.getpriority(os.PRIO_PROCESS, 0) if hasattr(os, "getpriority") else None
            pending = {task.remote(sp, tracker, nice,
                                   self.boot_models.get(drive_id(sp["kind"], sp["seed"]))): sp
                       for sp in todo}
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=2.0)
                for ref in ready:
                    sp = pending.pop(ref)
                    key = drive_id(sp["kind"], sp["seed"])
                    try:
                        drive = ray.get(ref)
                    except Exception as exc:        # RayTaskError: the drive's own error
                        cause = getattr(exc, "cause", None) or exc
                        self.failed[key] = f"{key}: {type(cause).__name__}: {cause}"
                        continue
                    self._finish(drive, done)
                base = sum(r["simulated_s"] for r in done.values())
                running = ray.get(tracker.get.remote())
                part = sum(v for k, v in running.items() if k not in done)
                prog(len(done), (base + part) / 3600.0, force=bool(ready))
        finally:
            if started:
                ray.shutdown()
        return workers


# ---------------------------------------------------------------------------------------------
# the command line
# ---------------------------------------------------------------------------------------------
def register(sub) -> None:
    c = sub.add_parser(
        "campaign", help="closed-loop coverage drives of the daemon on many simulated fields "
                         "(in parallel on Ray)",
        description="Drive the real daemon in lock-step with the simulated field for each "
                    "(scene kind, seed), score what the vehicle was told (collisions, false, "
                    "true and missed stops, detection distance), write DIR/summary.json, "
                    "per-drive CSVs and events, and DIR/report.md with plots. Seeds >= 1000 "
                    "are the acceptance set. Resumable: a rerun skips finished drives.")
    c.add_argument("--scene", required=True, metavar="KIND[,KIND...]",
                   help="scene kinds, e.g. stubble-coverage,stubble-coverage-night,"
                        "greenhouse-coverage")
    c.add_argument("--seeds", required=True, metavar="A-B", help="seed range, inclusive "
                   "(e.g. 1000-1003; a comma list of ranges works too)")
    c.add_argument("--minutes", required=True, type=float, help="simulated minutes per drive")
    c.add_argument("--out", required=True, metavar="DIR", help="campaign folder")
    c.add_argument("--workers", type=int, default=None,
                   help="parallel drives (default: all cores); 1 runs without Ray")
    c.add_argument("--address", help="join this Ray cluster (e.g. ray://head:10001 or auto) "
                                     "instead of starting a local one")
    c.add_argument("--config", metavar="FILE", help="TOML merged over each drive's config "
                   "(e.g. [perception] pipelines)")
    c.add_argument("--shadow", metavar="FILE",
                   help="TOML of a second configuration judged on each drive's own inputs "
                        "every cycle, never driving: its stops scored against the same truth, "
                        "and the false stops only one side made (docs/proving-ground.md "
                        "'Shadow'). It is merged over each drive's default config, not over "
                        "--config's: a shadow file names everything it differs in from the "
                        "defaults")
    c.add_argument("--save-models", action="store_true",
                   help="keep each drive's novelty model at its end (saved at the daemon's "
                        "shutdown, as the box saves it) in DIR/drives/KIND-SEED/models/, for "
                        "a later campaign's --models-from")
    c.add_argument("--models-from", metavar="CAMPAIGN",
                   help="each drive boots with the novelty model that campaign (run with "
                        "--save-models) saved at the end of its drive of the same scene and "
                        "seed, as an installed box boots with its saved model (otherwise a "
                        "drive boots with an empty one); compare the two with "
                        "`fieldguard campaign-compare`")
    c.add_argument("--stereo-scale", type=float, default=0.5,
                   help="stereo at this fraction of 1280x1024 (default 0.5: 640x512)")
    c.add_argument("--no-report", action="store_true", help="summary.json only, no report.md")
    c.add_argument("--json", action="store_true", help="print the summary as JSON")
    c.set_defaults(func=cmd_campaign)


def _end_ray_children() -> None:
    """A Ray start that timed out leaves its processes (GCS, raylet, monitors) running as our
    children and ray.shutdown() does not know them: end those, by pid (never another's)."""
    import signal
    me = os.getpid()
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == me and b"/ray/" in cmd:
            try:
                os.kill(int(d.name), signal.SIGKILL)
            except OSError:
                pass


def init_ray(workers: int, address: str | None = None, object_store_mb: int = 200,
             attempts: int = 3) -> None:
    """Start a local Ray in-process with ``workers`` CPUs (or join ``address``). Ray gives its
    raylet 30 s to register, which a heavily loaded host can miss: a local start that times
    out is shut down and tried again."""
    import logging

    import ray
    kw = dict(include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
    if address:
        try:
            ray.init(address=address, **kw)
        except ConnectionError as exc:
            raise CampaignError(f"--address {address}: cannot join that Ray cluster ({exc}; "
                                f"{exc.__cause__ or 'no more detail'})".splitlines()[0]
                                ) from None
        return
    # Ray's own processes (GCS, raylet) inherit this process's priority; under `nice -n 10`
    # on a loaded host they miss their start-up deadline. They start at normal priority when
    # we may (root), the drives still run at ours (_ray_drive).
    saved = os.getpriority(os.PRIO_PROCESS, 0)
    for k in range(attempts):
        try:
            try:
                if saved > 0:
                    os.setpriority(os.PRIO_PROCESS, 0, 0)
            except OSError:
                pass
            try:
                ray.init(num_cpus=workers, object_store_memory=object_store_mb * 2**20, **kw)
            finally:
                os.setpriority(os.PRIO_PROCESS, 0, saved)
            return
        except Exception as exc:                 # Ray raises a bare Exception for this
            if "timed out during startup" not in str(exc):
                raise
            ray.shutdown()
            _end_ray_children()
            if k == attempts - 1:
                raise CampaignError(f"could not start a local Ray in {attempts} tries ({exc}); "
                                    "the machine is too busy: try again, or run with "
                                    "--workers 1") from None


def sigterm_interrupts() -> None:
    """SIGTERM stops a campaign as ^C does (the finished drives' summary is written); called
    again after ray.init, which installs its own handler."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return

    def _term(*_):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, _term)


def cmd_campaign(a) -> int:
    import logging
    if not getattr(a, "verbose", False):       # each drive's daemon start / stop lines
        logging.getLogger("fieldguard").setLevel(logging.WARNING)
    sigterm_interrupts()
    camp = Campaign(a.scene, a.seeds, a.minutes, a.out, workers=a.workers, address=a.address,
                    config_file=a.config, stereo_scale=a.stereo_scale,
                    report=not a.no_report, shadow_file=a.shadow,
                    save_models=a.save_models, models_from=a.models_from,
                    command="fieldguard campaign " + " ".join(sys.argv[2:]))
    s = camp.run()
    if a.json:
        print(json.dumps(s, indent=2))
    else:
        print(format_summary(s))
    return 0


_DIFF_LINES = 30     # format_summary: the shadow's differences printed (all are in summary.json)


def format_summary(s: dict) -> str:
    ci = s["false_stops_per_hour_ci95"]
    lines = [f"campaign: {s['drives']} drives ({', '.join(s['kinds'])}; seeds "
             f"{s['seeds'][0]}-{s['seeds'][1]}), {s['simulated_hours']:.2f} simulated h, "
             f"{s['distance_km']:.2f} km, engine {s['engine']} x {s['workers']}",
             f"{'scene':26s} {'hours':>6s} {'km':>6s} {'coll':>4s} {'true':>5s} {'false':>5s} "
             f"{'FS/h':>6s} {'FS/h 95% CI':>15s} {'missed':>6s}"]

    def row(name, r):
        c = r["false_stops_per_hour_ci95"]
        fsh = "-" if r["false_stops_per_hour"] is None else f"{r['false_stops_per_hour']:.2f}"
        cis = "-" if c[0] is None else f"[{c[0]:.2f}, {c[1]:.2f}]"
        return (f"{name:26s} {r['simulated_hours']:6.2f} {r['distance_km']:6.2f} "
                f"{r['collisions']:4d} {r['true_stops']:5d} {r['false_stops']:5d} {fsh:>6s} "
                f"{cis:>15s} {r['missed_stops']:6d}")
    for k, r in s["per_scene"].items():
        lines.append(row(k, r))
    lines.append(row("all", s))
    if s.get("collisions_by_contact"):
        lines.append("collisions by where they touched the vehicle: " + ", ".join(
            f"{k} {v}" for k, v in s["collisions_by_contact"].items()) +
            " (side/rear: beside or behind the body, out of a forward box's view)")
    sh = s.get("shadow")
    if sh:
        lines.append(
            f"shadow ({s.get('provenance', {}).get('shadow_file') or '--shadow'}) on the same "
            f"inputs: {sh['false_stops']} false stops ({sh['false_stops_per_hour']}/h, 95 % CI "
            f"{sh['false_stops_per_hour_ci95']}), {sh['true_stops']} true, "
            f"{sh['missed_stops']} missed; false stops only the drive's own config made "
            f"{sh['false_stops_primary_only']}, only the shadow's {sh['false_stops_shadow_only']}"
            f"; true stops only the drive's {sh['true_stops_primary_only']}, only the "
            f"shadow's {sh['true_stops_shadow_only']}")
        diffs = sh.get("differences", [])
        if diffs:
            lines.append("where the drive and its shadow parted (drive, simulated s, what):")
            lines += [f"  {d['drive']:<28s} {d['t_s']:7.1f}  {d['what']}"
                      for d in diffs[:_DIFF_LINES]]
            if len(diffs) > _DIFF_LINES:
                lines.append(f"  ... and {len(diffs) - _DIFF_LINES} more (summary.json: "
                             "shadow.differences)")
    for cls, d in s["detection_distance_m"].items():
        lines.append(f"detection distance {cls}: min {d['min']} m, median {d['median']} m "
                     f"({d['stops']} stops)")
    b = s.get("at_boot")
    if b:
        lines.append(f"standing in the path at boot: {b['obstacles']} people; held from the "
                     f"first second and stopped for {b['held_from_first_s']}, stopped for "
                     f"{b['stopped']}, run into {b['collisions']}, missed {b['missed']}, never "
                     f"held {b['never_held']} (first held at most {b['first_held_s_max']} s "
                     "after the start)")
    ab = s.get("after_boot")
    if ab is not None:
        lines.append(f"after each drive's first {ab['boot_s']:.0f} s (the boot; a field box boots "
                     f"once, a drive each time): {ab['false_stops']} false stops, "
                     f"{ab['false_stops_per_hour']}/h (95 % CI {ab['false_stops_per_hour_ci95']}"
                     f"); {s['false_stops_boot']} in the first {ab['boot_s']:.0f} s")
    if s.get("simulated_hours"):
        slow = s.get("slow_for_nothing_s", 0.0)
        share = 100.0 * slow / (3600.0 * s["simulated_hours"])
        lines.append(f"stood or crawled for nothing: {s['false_stop_s']:.1f} s in false stops, "
                     f"{slow:.1f} s SLOW with nothing real in the zones ({share:.1f} % of the "
                     f"simulated time)")
    t = s["timing"]
    lines.append(f"false stops per hour {s['false_stops_per_hour']} (95 % CI {ci}); wall "
                 f"{t['wall_s'] / 60:.1f} min, {t['simulated_hours_per_cpu_hour']} simulated h "
                 "per CPU h")
    return "\n".join(lines)
