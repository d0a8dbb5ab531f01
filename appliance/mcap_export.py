"""A run folder -> an MCAP file that Foxglove opens (``fieldguard export RUN --out FILE.mcap``;
``fieldguard record --mcap FILE`` records a run folder and exports it).

The run is played through the box's own loop (``run --replay``, as fast as it goes, no status
socket, no console), so the file holds what the box makes of those frames with the given config:
the camera images, depth and laser as recorded, and the box's grid, zones, tracks and state for
every cycle, in Foxglove's schemas (topics in appliance/foxglove_out.py). What the run folder
itself holds beyond the sensors goes in too: the ground truth (/truth) and, for a recording the
box made, the state it had live (/recording/state)."""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from hal.errors import FieldguardError

log = logging.getLogger("fieldguard.export")


def check_out(out: Path, overwrite: bool = False) -> None:
    """The MCAP file can be written: a .mcap name in an existing folder, not there yet."""
    if out.suffix != ".mcap":
        raise FieldguardError(f"{out}: the output must end in .mcap")
    if out.exists() and not overwrite:
        raise FieldguardError(f"{out} exists: give another name, or --overwrite (export)")
    if not out.parent.is_dir():
        raise FieldguardError(f"{out.parent} is not a folder: create it, or give another name")


def export_run(run: str | Path, out: str | Path, cfg=None, *, overwrite: bool = False,
               progress=None) -> dict:
    """Write ``out`` (MCAP) from run folder ``run``; returns {"frames", "cycles", "topics":
    {topic: messages}, "out"}. FieldguardError (clear, no traceback) for a bad run folder or an
    output that cannot be written."""
    import foxglove
    from foxglove.mcap import MCAPWriteOptions

    from appliance.config import ConsoleConfig, FoxgloveConfig, default_config
    from appliance.console.views import track_dicts
    from appliance.daemon import Daemon, replay_config
    from appliance.foxglove_out import FoxgloveChannels
    from drivers.runfolder import RunReader

    run, out = Path(run), Path(out)
    reader = RunReader(run)                       # RunFormatError (a FieldguardError) if bad
    if not len(reader):
        raise FieldguardError(f"{run}: the run has no frames: nothing to export")
    check_out(out, overwrite)
    cfg = cfg or default_config()
    cfg = dataclasses.replace(replay_config(cfg, str(run)), console=ConsoleConfig(listen=""),
                              foxglove=FoxgloveConfig(listen=""))
    positions = {f.index: i for i, f in enumerate(reader.frames)}
    has_truth = (run / "truth").is_dir()
    recorded = "gate_state" in (reader.frames[0].extra or {})

    ctx = foxglove.Context()
    try:
        writer = foxglove.open_mcap(str(out), allow_overwrite=overwrite, context=ctx,
                                    writer_options=MCAPWriteOptions(profile="",
                                                                    compression_threads=0))
    except Exception as exc:
        raise FieldguardError(f"cannot write {out}: {exc}") from None
    ch = FoxgloveChannels(ctx, cfg, recording=True)
    d = Daemon(cfg, mode="replay", replay_path=str(run), pace=0.0, serve_status=False)
    seen: set[int] = set()
    failure: list[str] = []
    state = {"cycles": 0}

    def sink(res) -> None:
        if failure:
            return
        try:
            ch.log_cycle(res, d.loop.grid.evidence, track_dicts(getattr(res, "tracks", None)),
                         res.stamp_ns)
            state["cycles"] += 1
            inp = res.inputs
            src = None if inp is None else (inp.stereo or inp.rgbd or inp.laser)
            if src is not None and src.seq not in seen and src.seq in positions:
                seen.add(src.seq)
                pos = positions[src.seq]
                if has_truth:
                    truth = reader.truth(pos)
                    if truth is not None:
                        ch.log_truth(truth, res.stamp_ns)
                if recorded:
                    ex = reader.frames[pos].extra
                    ch.log_recorded_state(ex.get("gate_state", ""), ex.get("gate_reason", ""),
                                          src.seq, res.stamp_ns)
                if progress is not None:
                    progress(len(seen))
        except Exception as exc:
            failure.append(f"{type(exc).__name__}: {exc}")
            d.request_stop()

    try:
        d.start()
        d.loop.on_cycle.append(sink)
        d.run(max_cycles=len(reader) * 4 + 50)      # the replay ends itself after its last frame
    finally:
        d.shutdown()
        writer.write_metadata("fieldguard", {"run": str(run), "run_name": reader.info.name,
                                             "frames": str(len(reader)), "config": cfg.source,
                                             "pipelines": ",".join(cfg.perception.pipelines)})
        writer.close()
    if failure:
        raise FieldguardError(f"export of {run} failed: {failure[0]}")
    return {"out": str(out), "frames": len(reader), "frames_seen": len(seen),
            "cycles": state["cycles"], "topics": dict(sorted(ch.counts.items()))}


# -- the command ---------------------------------------------------------------------------------
def cmd_export(a) -> int:
    from appliance.config import load_config
    from appliance.progress import Progress
    from drivers.runfolder import RunReader
    cfg = load_config(a.config) if a.config else None
    n = len(RunReader(a.run))
    res = export_run(a.run, a.out, cfg, overwrite=a.overwrite,
                     progress=Progress(f"export {Path(a.run).name}", n))
    topics = ", ".join(f"{t} {c}" for t, c in res["topics"].items())
    print(f"wrote {res['out']}: {res['frames_seen']}/{res['frames']} frames, {res['cycles']} "
          f"cycles ({topics}); open it in Foxglove (File > Open local file)")
    return 0


def export_after_record(out_run: Path, mcap: str, seconds: float, socket: str | None = None,
                        quiet_s: float = 1.5) -> int:
    """``record --mcap``: wait until the daemon has written the recording (its time is up and
    frames.csv has not grown for ``quiet_s``: the writer thread writes what is queued as fast as
    it can), then export it with the daemon's own config (its status names the file)."""
    import time
    from appliance.status import read_status
    csv = Path(out_run) / "frames.csv"
    t_end = time.monotonic() + seconds
    last, still_since = None, time.monotonic()
    while True:
        size = csv.stat().st_size if csv.exists() else -1
        if size != last:
            last, still_since = size, time.monotonic()
        if time.monotonic() >= t_end and size > 0 and time.monotonic() - still_since >= quiet_s:
            break
        if time.monotonic() > t_end + 60:
            raise FieldguardError(f"the recording {out_run} did not finish within a minute of "
                                  f"its end: see the daemon's log (journalctl -u fieldguard)")
        time.sleep(0.2)
    config = None
    try:
        src = read_status(socket).get("config")
        config = src if src and Path(src).is_file() else None
    except (ConnectionError, OSError, ValueError):
        pass
    print(f"recorded {out_run}; exporting it to {mcap} (config: {config or 'defaults'})",
          flush=True)
    from types import SimpleNamespace
    return cmd_export(SimpleNamespace(run=str(out_run), out=mcap, config=config,
                                      overwrite=False))


def register(sub) -> None:
    e = sub.add_parser("export", help="a run folder as an MCAP file for Foxglove",
                       description="Plays RUN through the box's loop (as `replay` does, as fast "
                                   "as it goes) and writes the camera, depth, laser, the grid, "
                                   "zones, tracks and state of every cycle, the ground truth and "
                                   "the recorded state, in Foxglove's schemas (docs/console.md).")
    e.add_argument("run", help="run folder (a recording, an incident, a simulated scene)")
    e.add_argument("--out", required=True, metavar="FILE.mcap", help="MCAP file to write")
    e.add_argument("--config", help="config whose pipelines, grid and zones to use "
                                    "(default: built-in defaults)")
    e.add_argument("--overwrite", action="store_true", help="replace an existing FILE.mcap")
    e.set_defaults(func=cmd_export)
