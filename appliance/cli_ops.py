"""The technician's commands: watch, snapshot, selftest, record, replay. They talk to the
running daemon over its status socket and never open hardware the daemon owns (selftest opens
the configured devices itself only when no daemon is running)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from hal.errors import FieldguardError

DEFAULT_CONFIG = "/etc/fieldguard/fieldguard.toml"


def cmd_watch(a) -> int:
    from appliance.cli import format_status
    from appliance.status import read_status
    n = 0
    tty = sys.stdout.isatty()
    try:
        while a.count is None or n < a.count:
            try:
                text = format_status(read_status(a.socket))
            except ConnectionError as exc:
                text = f"fieldguard watch: {exc}"
            if tty:
                sys.stdout.write("\x1b[H\x1b[2J")
            print(time.strftime("%H:%M:%S ") + "fieldguard watch (Ctrl-C to quit)")
            print(text, flush=True)
            n += 1
            if a.count is None or n < a.count:
                time.sleep(a.interval)
    except KeyboardInterrupt:
        pass
    return 0


def cmd_snapshot(a) -> int:
    from appliance.status import request
    out = Path(a.output)
    if out.is_dir():                    # -o DIR: a new file in it, named by the time
        out = out / time.strftime("fieldguard-snapshot-%Y%m%d-%H%M%S.png")
    try:
        data = request(a.socket, "snapshot", timeout_s=15.0)
    except ConnectionError as exc:
        print(f"fieldguard: error: {exc}", file=sys.stderr)
        return 2
    if not data.startswith(b"\x89PNG"):
        try:
            msg = json.loads(data).get("error", data[:200])
        except ValueError:
            msg = data[:200]
        print(f"fieldguard: error: the daemon gave no picture: {msg}", file=sys.stderr)
        return 1
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
    except OSError as exc:
        raise FieldguardError(f"cannot write {out}: {exc.strerror or exc}; give -o a file or "
                              f"folder you can write to") from None
    print(f"wrote {out} ({len(data) // 1024} KiB)")
    return 0


def _print_selftest(rows: list[dict], source: str) -> int:
    print(f"selftest ({source})")
    bad = 0
    for r in rows:
        mark = "PASS" if r["ok"] else "FAIL"
        age = "" if r.get("age_s") is None else f", data {r['age_s']:.2f} s old"
        print(f"  {mark}  {r['name']:10s} {r['kind']}/{r['type']}: {r['message']}{age}")
        if not r["ok"]:
            bad += 1
            print(f"        fix: {r['fix']}")
    print("all devices answer" if not bad else f"{bad} device(s) failed")
    return 0 if not bad else 1


def cmd_selftest(a) -> int:
    from appliance.status import request_json
    if not a.config:
        try:
            doc = request_json(a.socket, "selftest")
            return _print_selftest(doc["devices"], "asked the running daemon")
        except ConnectionError as exc:
            if "did not answer" in str(exc):   # a daemon is there, busy: never open its devices
                raise FieldguardError(f"{exc}: it runs but is busy; try again (selftest never "
                                      f"opens the devices a running daemon owns)") from None
    from appliance.config import load_config
    from appliance.daemon import Daemon, selftest_devices, sim_config
    path = a.config or (DEFAULT_CONFIG if Path(DEFAULT_CONFIG).exists() else None)
    if path is None:
        raise FieldguardError(f"no daemon is running and there is no {DEFAULT_CONFIG}: give "
                              f"--config FILE")
    cfg = load_config(path)
    if a.sim:
        cfg = sim_config(cfg)
    d = Daemon(cfg, mode="sim" if a.sim else "hardware", serve_status=False,
               pace=1.0 if a.sim else None)
    d.start()
    try:
        d.run(max_cycles=max(1, int(a.seconds * cfg.loop.rate_hz)))
        rows = selftest_devices(d.devices, cfg)
    finally:
        d.shutdown()
    return _print_selftest(rows, f"opened the devices of {path} for {a.seconds:.1f} s")


def cmd_record(a) -> int:
    from appliance.status import request_json
    out = Path(a.out).resolve()
    if getattr(a, "mcap", None):            # refuse a bad MCAP name before recording
        from appliance.mcap_export import check_out
        check_out(Path(a.mcap))
    try:
        doc = request_json(a.socket, f"record {a.seconds} {out}")
    except ConnectionError as exc:
        print(f"fieldguard: error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"fieldguard: error: the daemon refused to record: {exc}", file=sys.stderr)
        return 1
    print(f"recording {doc['seconds']} s into {doc['recording']} (the daemon writes it; "
          f"`fieldguard replay {out}` plays it back)", flush=True)
    if not a.detach or getattr(a, "mcap", None):
        rc = _follow_recording(a, out)
        if rc:
            return rc
    if getattr(a, "mcap", None):
        from appliance.mcap_export import export_after_record
        return export_after_record(out, a.mcap, a.seconds, a.socket)
    return 0


def _follow_recording(a, out: Path) -> int:
    """Progress until the daemon says the recording is written, then "done"."""
    from appliance.status import request_json
    tty = sys.stdout.isatty()
    # the daemon's clock may run slower than the wall clock (a loaded simulator): a generous
    # deadline, and only while the daemon keeps answering
    limit_s = 3 * a.seconds + 30
    deadline = time.monotonic() + limit_s
    last = None
    while True:
        try:
            st = request_json(a.socket, f"record-status {out}")
        except ConnectionError as exc:
            raise FieldguardError(f"lost the daemon while it recorded {out}: {exc}") from None
        except RuntimeError as exc:
            raise FieldguardError(f"the daemon cannot say how the recording goes: {exc}") \
                from None
        line = f"recording: {st['written']} frames written"
        if st.get("dropped"):
            line += f", {st['dropped']} dropped (the writer could not keep up)"
        if st.get("done"):
            if tty and last is not None:
                print()
            if st.get("error"):
                raise FieldguardError(f"the recording {out} failed: {st['error']}")
            print(f"done: {st['written']} frames in {out}"
                  + (f" ({st['dropped']} dropped)" if st.get("dropped") else ""), flush=True)
            return 0
        if tty:
            print(f"\r{line}", end="", flush=True)
        elif line != last:
            print(line, flush=True)
        last = line
        if time.monotonic() > deadline:
            raise FieldguardError(f"the recording {out} is not finished after {limit_s:.0f} s; "
                                  f"see `fieldguard status`")
        time.sleep(0.5)


def cmd_replay(a) -> int:
    from appliance.cli import main
    args = ["run", "--replay", a.run, "--print-every", str(a.print_every)]
    if a.config:
        args += ["--config", a.config]
    if a.fast:
        args.append("--fast")
    if a.socket:
        args += ["--socket", a.socket]
    return main(args)


def register(sub) -> None:
    w = sub.add_parser("watch", help="the status screen, live",
                       description="Redraws `fieldguard status` every --interval seconds.")
    w.add_argument("--interval", type=float, default=1.0)
    w.add_argument("--count", type=int, help="stop after this many screens")
    w.add_argument("--socket")
    w.set_defaults(func=cmd_watch)

    s = sub.add_parser("snapshot", help="a picture of what the box sees now",
                       description="Camera image with masks and occupied cells, the depth or "
                                   "slope view, and the grid with the zones, in one PNG.")
    s.add_argument("-o", "--output", required=True,
                   help="PNG file to write (a folder: a new file in it, named by the time)")
    s.add_argument("--socket")
    s.set_defaults(func=cmd_snapshot)

    t = sub.add_parser("selftest", help="does every configured device and link answer?",
                       description="Asks the running daemon; with no daemon (or with --config) "
                                   "opens the configured devices for a few seconds itself. "
                                   "Exit 0 when every device passes.")
    t.add_argument("--config", help=f"config to test (default: ask the daemon, else "
                                    f"{DEFAULT_CONFIG})")
    t.add_argument("--sim", action="store_true", help="with --config: on the simulated field")
    t.add_argument("--seconds", type=float, default=1.5)
    t.add_argument("--socket")
    t.set_defaults(func=cmd_selftest)

    r = sub.add_parser("record", help="record what the box sees into a run folder",
                       description="The running daemon writes the next SECONDS of its inputs "
                                   "(and its decisions, as frames.csv columns) to a new run "
                                   "folder.")
    r.add_argument("--seconds", type=float, required=True)
    r.add_argument("--out", required=True, help="new run folder (never overwritten)")
    r.add_argument("--detach", action="store_true",
                   help="return at once (default: show progress until it is written, then "
                        "\"done\")")
    r.add_argument("--wait", action="store_true", help=argparse.SUPPRESS)   # the default now
    r.add_argument("--mcap", metavar="FILE.mcap",
                   help="when it is written, export it for Foxglove as well (fieldguard export)")
    r.add_argument("--socket")
    r.set_defaults(func=cmd_record)

    p = sub.add_parser("replay", help="play a run folder through the loop",
                       description="Same as `fieldguard run --replay RUN --print-every 1`.")
    p.add_argument("run")
    p.add_argument("--config")
    p.add_argument("--fast", action="store_true")
    p.add_argument("--print-every", type=float, default=1.0)
    p.add_argument("--socket")
    p.set_defaults(func=cmd_replay)
