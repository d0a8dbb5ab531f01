"""The ``fieldguard`` command."""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time

from hal.errors import FieldguardError

log = logging.getLogger("fieldguard")


def _setup_logging(verbose: bool) -> None:
    from appliance.service import setup_logging
    setup_logging(verbose)


def _load(path):
    from appliance.config import default_config, load_config
    return load_config(path) if path else default_config()


# ---------------------------------------------------------------------------------------------
def _load_run_config(a):
    """The config file (or defaults) with the command line's link overrides applied; the
    overridden tables go through the same validation as the file's."""
    if not (a.mavlink or a.can):
        return _load(a.config)
    import tomllib
    from pathlib import Path

    from appliance.config import parse_config
    from drivers.links_cli import apply_link_override, can_table, mavlink_table
    data = {}
    if a.config:
        try:
            data = tomllib.loads(Path(a.config).read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as exc:
            from hal.errors import ConfigError
            raise ConfigError(f"cannot read: {exc}", file=a.config)
    devs = data.get("devices", {})
    if a.mavlink:
        devs = apply_link_override(devs, mavlink_table(a.mavlink))
    if a.can:
        devs = apply_link_override(devs, can_table(a.can),
                                   default_name="can" if a.mavlink else "link",
                                   replace_others=not a.mavlink)
    data["devices"] = devs
    return parse_config(data, a.config or "<command line>")


# scenes whose vehicle and sensors the defaults do not fit: `run --sim SCENE` without a
# --config runs the pipeline and the zones the scene is built for (the greenhouse sprayer:
# an RGB-D camera, 1.2 m long, 0.8 m wide between bush rows 1.2 m apart; with the default
# 2.5 m wide zones the bushes are in the stop zone and it never starts: docs/rgbd.md)
from appliance.config import SCENE_PIPELINES, SCENE_ZONES  # noqa: E402


def all_sensors_simulated(cfg) -> bool:
    """True when every sensor device of the config is simulated (links may be real): such a
    config can only run the simulated field, so it runs as ``--sim`` does (lock-step clock,
    rendering outside the loop's time), not against the wall clock."""
    sensors = [d for d in cfg.devices if d.kind != "link"]
    return bool(sensors) and all(d.type == "sim" for d in sensors)


def cmd_run(a) -> int:
    import dataclasses

    from appliance.config import check_scene
    from appliance.daemon import Daemon, replay_config, sim_config
    cfg = _load_run_config(a)
    if a.sim is not None and a.replay:
        raise FieldguardError("give --sim or --replay, not both")
    if a.sim:
        check_scene(a.sim)
        if not a.config and a.sim in SCENE_PIPELINES:
            cfg = dataclasses.replace(
                cfg, perception=dataclasses.replace(cfg.perception,
                                                    pipelines=SCENE_PIPELINES[a.sim], optional=()),
                zones=dataclasses.replace(cfg.zones, **SCENE_ZONES.get(a.sim, {})))
    if a.sim is not None:
        cfg, mode = sim_config(cfg, a.sim or None), "sim"
    elif a.replay:
        cfg, mode = replay_config(cfg, a.replay), "replay"
    elif all_sensors_simulated(cfg):
        mode = "sim"
        log.info("every sensor in %s is simulated: running the simulated field (scene %s) "
                 "as `run --sim` does", cfg.source, cfg.sim.scene)
    else:
        mode = "hardware"
    pace = 0.0 if a.fast else None
    d = Daemon(cfg, mode=mode, replay_path=a.replay, pace=pace, status_socket=a.socket)
    d.install_signal_handlers()
    printer = None
    try:
        d.start()
        if a.print_every and a.print_every > 0:
            printer = _StatusPrinter(d, a.print_every)
            d.loop.on_cycle.append(printer)
        max_cycles = None
        if a.duration:
            max_cycles = int(round(a.duration * cfg.loop.rate_hz))
        d.run(max_cycles=max_cycles)
    finally:
        d.shutdown()
        if printer:
            printer.final()
    return 0


class _StatusPrinter:
    """One line on stdout per change of state and every N seconds of (sim) time."""

    def __init__(self, daemon, every_s: float):
        self.d, self.every_ns = daemon, int(every_s * 1e9)
        self.last_ns = None
        self.last_state = None
        self._prev = None
        self.true_stops = self.false_stops = self.obstacle_stops = 0
        self.fault_stops: dict[str, int] = {}

    def _tally_stop(self, res) -> None:
        """Each entry into STOP after boot: for an obstacle (true or false, when the simulator
        can say what is really ahead) or for a fault."""
        state = res.output.state.value
        entered = state == "STOP" and self._prev not in (None, "STOP")
        self._prev = state
        if not entered:
            return
        reason = res.output.reason
        if "zone" in reason or getattr(self.d.loop.gate, "cause", "") == "obstacle":
            hub = self.d.shared.get("sim_hub")
            if hub is None:
                self.obstacle_stops += 1
                return
            v = res.verdict
            reach = (v.stop_len_m if v is not None else 0.0) + self.d.cfg.zones.slow_extra_m
            # true: something really is in the vehicle's corridor within the zones (+1 m)
            if hub.field.vehicle.clearance_ahead() <= reach + 1.0:
                self.true_stops += 1
            else:
                self.false_stops += 1
        elif "end of recording" not in reason:             # a replay's end is no fault
            import re
            key = re.sub(r"\s*\(.*$", "", ":".join(reason.split(":")[:2])).strip()
            self.fault_stops[key] = self.fault_stops.get(key, 0) + 1

    def __call__(self, res) -> None:
        self._tally_stop(res)
        self.last_cycle = (res.output.state.value, res.output.reason)
        changed = res.output.state.value != self.last_state
        due = self.last_ns is None or res.stamp_ns - self.last_ns >= self.every_ns
        if not (changed or due):
            return
        self.last_ns, self.last_state = res.stamp_ns, res.output.state.value
        v = res.verdict
        near = "-" if v is None or v.nearest_m is None else f"{v.nearest_m:4.1f} m"
        sim = ""
        hub = self.d.shared.get("sim_hub")
        if hub is not None:
            st = hub.field.stats()
            sim = (f" | sim {st.get('time_s', 0):6.1f} s, {st.get('distance_m', 0):6.1f} m "
                   f"driven, {st.get('collisions', 0)} collisions")
        print(f"[{res.index:6d}] {res.output.state.value:5s} nearest {near:>7s} "
              f"cells {len(res.cells_xy):4d} | {res.output.reason}{sim}", flush=True)

    def final(self):
        print("\n".join(self.summary(self.d.status())), flush=True)

    def summary(self, st: dict) -> list[str]:
        """The closing summary, in words."""
        def n(k, one, many=None):
            return f"{k} {one if k == 1 else (many or one + 's')}"
        state, reason = getattr(self, "last_cycle", (st.get("state"), st.get("reason")))
        out = [f"summary: {st.get('cycles')} cycles ({st.get('mode')}); the last cycle said "
               f"{state} ({reason})"]
        sim = st.get("sim")
        if sim:
            out.append(f"  drove {sim.get('distance_m', 0):.1f} m in {sim.get('time_s', 0):.1f} s "
                       f"of simulated time ({sim.get('stopped_s', 0):.1f} s standing)")
        obstacle = self.true_stops + self.false_stops + self.obstacle_stops
        if not obstacle:
            out.append("  stops for obstacles: none")
        elif sim is not None:
            out.append(f"  stops for obstacles: {obstacle}: {self.true_stops} true (something "
                       f"really ahead), {self.false_stops} false (nothing really there)")
        else:
            out.append(f"  stops for obstacles: {obstacle}")
        if self.fault_stops:
            out.append("  stops for faults: " + ", ".join(
                f"{k} x {r}" for r, k in sorted(self.fault_stops.items(), key=lambda kv: -kv[1])))
        if sim is not None:
            ov = sim.get("overrides", 0)
            out.append("  overrides: none (the safety driver never drove on while the box said "
                       "STOP)" if not ov else
                       f"  overrides: {ov}: the simulated safety driver drove on {n(ov, 'time')} "
                       f"while the box held STOP with nothing really ahead (false stops)")
            c = sim.get("collisions", 0)
            hit = ", ".join(map(str, sim.get("obstacles_hit") or []))
            out.append("  collisions: none" if not c else
                       f"  collisions: {c}: the vehicle hit {hit or n(c, 'obstacle')}")
        t = st.get("timing_ms", {}).get("cycle", {})
        line = (f"  loop: cycle p50 {t.get('p50')} ms, p99 {t.get('p99')} ms, "
                f"{n(st.get('overruns', 0), 'overrun')}")
        r = (st.get("sim_render_ms") or {})
        if r.get("p50") is not None:
            line += f"; the simulator's rendering (not the box's time) p50 {r['p50']} ms"
        out.append(line)
        return out


def cmd_status(a) -> int:
    from appliance.status import read_status
    try:
        doc = read_status(a.socket)
    except ConnectionError as exc:
        print(f"fieldguard: error: {exc}", file=sys.stderr)
        return 2
    healthy = doc.get("state") != "STOP" or not doc.get("faults")
    if a.json:
        print(json.dumps(doc, indent=2))
    else:
        print(format_status(doc))
    return 0 if healthy else 1


def format_status(doc: dict) -> str:
    lines = [f"state   {doc.get('state')}   ({doc.get('reason')})",
             f"mode    {doc.get('mode')}   config {doc.get('config')}   cycles {doc.get('cycles')}"]
    t = doc.get("timing_ms", {}).get("cycle", {})
    lines.append(f"loop    last {t.get('last')} ms  p50 {t.get('p50')} ms  p99 {t.get('p99')} ms"
                 f"  overruns {doc.get('overruns')}  skipped {doc.get('skipped')}")
    r = doc.get("sim_render_ms") or {}
    if r.get("p50") is not None:
        lines.append(f"sim     rendering p50 {r['p50']} ms  p99 {r['p99']} ms  (the simulator's "
                     f"time between cycles, not the box's)")
    views = doc.get("console") or {}
    urls = [f"{k} {v['url']}" for k, v in views.items() if isinstance(v, dict) and v.get("url")]
    if urls or views.get("errors"):
        lines.append("views   " + "   ".join(urls + [f"({e})" for e in views.get("errors", [])]))
    lines.append("devices")
    for n, h in doc.get("devices", {}).items():
        age = "-" if h.get("age_s") is None else f"{h['age_s']:.2f} s"
        req = "required" if h.get("required") else "optional"
        lines.append(f"  {n:10s} {h.get('kind', ''):8s} {h.get('state'):9s} age {age:>8s} "
                     f"{req}  {h.get('reason', '')}")
    for n, notes in doc.get("pipeline_notes", {}).items():
        flat = notes if "cue" in notes else {f"{k}.{kk}": vv for k, v in notes.items()
                                              for kk, vv in v.items()}
        lines.append(f"pipeline {n}: " + ", ".join(f"{k}={v}" for k, v in flat.items()))
    o = doc.get("obstacles")
    if o:
        lines.append(f"picture {o['occupied_cells']} occupied cells, stop zone {o['stop_zone_m']} m,"
                     f" in stop {o['in_stop_zone']}, in slow {o['in_slow_zone']}, "
                     f"nearest {o['nearest_m']} m")
        if o.get("zones_along"):                      # [zones] follow_path is on
            lines.append(f"zones   along {o['zones_along']}")
    for t in doc.get("tracks", []):
        lines.append(f"  track {t['id']:<5} {t['distance_m']:5.1f} m  x {t['x_m']:6.2f} y "
                     f"{t['y_m']:6.2f}  {t['length_m']:.1f}x{t['width_m']:.1f} m  v "
                     f"{t['vx_mps']:+.1f},{t['vy_mps']:+.1f} m/s  p {t['confidence']:.2f}  "
                     f"{'+'.join(t['sources'])}{'  (held unseen)' if t.get('coasting') else ''}")
    for n, peers in doc.get("links", {}).items():
        for p in peers:
            lines.append(f"link    {n}: " + ", ".join(f"{k}={v}" for k, v in p.items()))
    stops = doc.get("last_stops", [])
    if stops:
        lines.append("last stops")
        for s in stops[-5:]:
            lines.append(f"  t={s['stamp_s']:.1f} s  {s['reason']}")
    return "\n".join(lines)


def cmd_sim(a) -> int:
    from appliance.config import check_scene
    from appliance.progress import Progress
    from drivers.sim.field import SENSORS
    from drivers.sim.record import write_sim_run
    check_scene(a.scene)
    if a.frames < 1:
        raise FieldguardError(f"--frames must be at least 1, got {a.frames}")
    if not 0.1 <= a.stereo_scale <= 1.0:
        raise FieldguardError(f"--stereo-scale must be in [0.1, 1.0], got {a.stereo_scale}")
    sensors = tuple(x.strip() for x in a.sensors.split(",")) if a.sensors else None
    bad = [x for x in sensors or () if x not in SENSORS]
    if bad or sensors == ():
        raise FieldguardError(f"--sensors: unknown sensor(s) {', '.join(map(repr, bad))}; give "
                              f"a comma list of {', '.join(SENSORS)}")
    kw = {} if sensors is None else {"sensors": sensors}
    try:
        out = write_sim_run(a.scene, a.frames, a.out, seed=a.seed,
                            stereo_scale=a.stereo_scale,
                            progress=Progress(f"sim {a.scene}", a.frames),
                            overwrite=a.overwrite, **kw)
    except OSError as exc:
        raise FieldguardError(f"cannot write the run folder {a.out}: "
                              f"{exc.strerror or exc}; give --out a folder you can write "
                              f"to") from None
    print(f"wrote {a.frames} frames to {out} (preview: {out}/preview.png)")
    return 0


def cmd_eval(a) -> int:
    # one run with --out writes its decisions here whatever --workers says (one run is one
    # task: there is nothing to spread); many runs, or --address, go to Ray
    if len(a.run) > 1 or a.address or (a.workers is not None and not getattr(a, "out", None)):
        from appliance.campaign_eval import cmd_eval_many    # many runs, on Ray
        return cmd_eval_many(a)
    a.run = a.run[0]
    from appliance.evaluation import evaluate_run, format_table
    from appliance.progress import Progress
    cfg = _load(a.config) if a.config else None
    label = a.pipeline or "default perception"
    out = getattr(a, "out", None)
    if out:
        parent = os.path.dirname(os.path.abspath(out))
        if not os.path.isdir(parent):
            raise FieldguardError(f"--out {out}: folder {parent} does not exist; create it "
                                  f"or name a file in an existing folder")
    if a.json:
        # stdout carries the JSON only: anything printed while evaluating (a native library's
        # printf, e.g. LIBELAS's warnings) goes to stderr
        with _fd1_on_stderr():
            res = evaluate_run(a.run, a.pipeline, cfg,
                               progress=Progress(f"eval {label}", 1), out=out)
        print(json.dumps(res, indent=2, default=float))
        return 0
    res = evaluate_run(a.run, a.pipeline, cfg, progress=Progress(f"eval {label}", 1), out=out)
    print(format_table(res))
    return 0


class _fd1_on_stderr:
    """File descriptor 1 points at stderr inside the block (what native code prints to
    stdout lands there), and back after it."""

    def __enter__(self):
        sys.stdout.flush()
        self._saved = os.dup(1)
        os.dup2(2, 1)

    def __exit__(self, *exc):
        sys.stdout.flush()
        os.dup2(self._saved, 1)
        os.close(self._saved)
        return False


def _check_cue_models(cfg) -> list[str]:
    """Load every learned-cue model the config asks for (what the daemon will read at start):
    a required one that fails raises its CueModelError; an optional one gives a warning."""
    from appliance.config import pipeline_options
    from appliance.cue_model import CueModelError, load_cue_model
    from appliance.perception import pipeline_class
    notes = []
    for name in cfg.perception.pipelines:
        domain = None if name == "fused" else getattr(pipeline_class(name), "cue_domain", None)
        o = pipeline_options(cfg, name) if domain else None
        mode = getattr(o, "cue", "off")
        if mode == "off":
            continue
        try:
            m = load_cue_model(o.cue_model or None, domain)
        except CueModelError as exc:
            if mode == "required":
                raise CueModelError(f"[perception.{name}] cue = \"required\": {exc} (the box "
                                    "would hold STOP)") from None
            notes.append(f"warning: [perception.{name}] optional learned cue unavailable, the "
                         f"box will run without it: {exc}")
        else:
            notes.append(f"[perception.{name}] learned cue ({mode}): {m.path}, "
                         f"{m.info.feature_set}, threshold {m.info.threshold:.3f}")
    return notes


def cmd_config_check(a) -> int:
    """Every check `run --config FILE` makes before it starts (and with --sim, every check of
    `run --sim --config FILE`): the file, its scenes, connection strings and DBC, devices
    present, pipelines and their models."""
    from appliance.config import load_config
    from hal.errors import ConfigError
    cfg = load_config(a.file)
    # the config's own keys first (the most specific message), then what it lacks
    from appliance.perception.stereo import check_daemon_matchers
    check_daemon_matchers(cfg)            # a config for the box: never LIBELAS
    notes = _check_cue_models(cfg)
    if a.sim:
        from appliance.daemon import sim_config
        cfg = sim_config(cfg)             # what `run --sim --config FILE` runs: checked too
        check_daemon_matchers(cfg)
        notes = _check_cue_models(cfg)
    elif not cfg.devices:
        # what the daemon says too: an empty file is the built-in defaults, which have no
        # devices, so only --sim or --replay can run it
        raise ConfigError("no [devices] configured, so `fieldguard run --config` (and the "
                          "service) would refuse it. A file without [devices] (an empty file "
                          "is the built-in defaults) runs only with --sim or --replay RUN: check "
                          "it with `fieldguard config check --sim FILE`, or add [devices] tables "
                          "(deploy/fieldguard.toml has one for each kind)", file=a.file)
    if not a.sim and all_sensors_simulated(cfg):
        notes.append(f"note: every sensor is simulated: `run --config` runs the simulated field "
                     f"(scene {cfg.sim.scene}) as `run --sim` does")
    print(f"{a.file}: OK ({len(cfg.devices)} devices: "
          f"{', '.join(f'{d.name}={d.type}' for d in cfg.devices) or 'none'}; pipelines: "
          f"{', '.join(cfg.perception.pipelines)})")
    for n in notes:
        print(n)
    return 0


# ---------------------------------------------------------------------------------------------
# Commands that live in their own modules: each module has ``register(subparsers)`` that adds
# its sub-parser(s) with ``set_defaults(func=...)``. Add a line here to plug a command in.
COMMAND_MODULES: list[str] = ["appliance.cli_ops", "appliance.cli_rgbd", "appliance.cli_novelty",
                              "appliance.cli_cue", "appliance.campaign",
                              "appliance.campaign_compare", "appliance.mcap_export"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fieldguard", description=(
        "fieldguard: obstacle-detection safety box for tractors and sprayers. "
        "It tells the vehicle STOP whenever it cannot vouch for what is ahead."))
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    r = sub.add_parser("run", help="run the daemon (hardware, --sim or --replay)",
                       description="Run the 10 Hz safety loop. With no --sim/--replay the "
                                   "devices of the config file are used.")
    r.add_argument("--config", help="TOML config file (default: built-in defaults)")
    r.add_argument("--sim", nargs="?", const="", metavar="SCENE",
                   help="run on the built-in simulated field (default scene: stubble-day)")
    r.add_argument("--replay", metavar="RUN", help="replay a run folder through the loop")
    r.add_argument("--mavlink", metavar="CONNECTION",
                   help="MAVLink link instead of the configured one, e.g. udpout:127.0.0.1:14550 "
                        "or /dev/ttyACM0,921600 (bench tests)")
    r.add_argument("--can", metavar="INTERFACE:CHANNEL",
                   help="CAN (J1939) link instead of the configured one, e.g. socketcan:can0")
    r.add_argument("--fast", action="store_true", help="sim/replay as fast as possible")
    r.add_argument("--duration", type=float, help="stop after this many seconds of loop time")
    r.add_argument("--socket", help="status socket path (default: config or runtime dir)")
    r.add_argument("--print-every", type=float, default=0.0, metavar="S",
                   help="print a status line on every change of state and every S seconds")
    r.set_defaults(func=cmd_run)

    s = sub.add_parser("status", help="show the running daemon's state",
                       description="Read the daemon's status socket. Exit 0 healthy, 1 STOP "
                                   "with faults, 2 no daemon.")
    s.add_argument("--json", action="store_true", help="machine-readable output")
    s.add_argument("--socket", help="status socket path")
    s.set_defaults(func=cmd_status)

    m = sub.add_parser("sim", help="render a simulated scene into a run folder")
    m.add_argument("scene", help="scene name (stubble-day, stubble-night, greenhouse, "
                                 "stubble-empty)")
    m.add_argument("--frames", type=int, default=100)
    m.add_argument("--out", required=True, help="run folder to write")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--stereo-scale", type=float, default=1.0,
                   help="render stereo at this fraction of 1280x1024")
    m.add_argument("--sensors", help="comma list of stereo,laser,rgbd (default: the scene's)")
    m.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    m.set_defaults(func=cmd_sim)

    e = sub.add_parser("eval", help="score a pipeline on a run folder",
                       description="Score as docs/run-format.md defines; prints a table, or "
                                   "JSON with --json.")
    e.add_argument("run", nargs="+", help="run folder(s); several are scored in parallel on "
                   "Ray (--workers) and printed as one table")
    e.add_argument("--workers", type=int, help="runs scored at once (default: all cores; 1: "
                   "one after the other, without Ray)")
    e.add_argument("--address", help="score on this Ray cluster instead of a local Ray")
    e.add_argument("--pipeline", default=None,
                   help="laser, stereo, stereo-novelty, rgbd, fused (default: the box's default "
                        "perception for the sensors the run has, or the --config's pipelines)")
    e.add_argument("--out", metavar="FILE",
                   help="write the box's decision for every frame as JSON Lines "
                        "(docs/run-format.md \"The box's decisions\")")
    e.add_argument("--config")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_eval)

    c = sub.add_parser("config", help="configuration tools")
    csub = c.add_subparsers(dest="config_cmd", required=True, metavar="SUBCOMMAND")
    cc = csub.add_parser("check", help="validate a config file without starting anything")
    cc.add_argument("file")
    cc.add_argument("--sim", action="store_true",
                    help="check it as `run --sim --config FILE` uses it (devices optional)")
    cc.set_defaults(func=cmd_config_check)

    import importlib
    for mod in COMMAND_MODULES:
        importlib.import_module(mod).register(sub)
    return p


def _error_log_path():
    from pathlib import Path
    base = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    if not base:
        import tempfile
        base = str(Path(tempfile.gettempdir()) / f"fieldguard-{os.getuid()}")
    return Path(base) / "internal-errors.log"


def _report_internal_error(args, exc: BaseException) -> None:
    """An exception nobody meant: one line for the user, the traceback in a log file (and in
    the journal/stderr log only with -v)."""
    import traceback
    text = "".join(traceback.format_exception(exc))
    where = "the log"
    try:
        path = _error_log_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a", encoding="utf-8") as f:
            f.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} fieldguard "
                    f"{' '.join(sys.argv[1:]) or getattr(args, 'cmd', '')}\n{text}")
        where = str(path)
    except OSError:
        pass
    if getattr(args, "verbose", False):
        log.error("internal error:\n%s", text)
    else:
        log.debug("internal error:\n%s", text)
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    print(f"fieldguard: error: internal error: {type(exc).__name__}"
          f"{': ' + msg if msg else ''} (please report; details in {where})", file=sys.stderr)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    try:
        return args.func(args)
    except FieldguardError as exc:
        print(f"fieldguard: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:          # `fieldguard status | head`: not an error of ours
        return 0
    except Exception as exc:         # never a traceback for the user
        _report_internal_error(args, exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
