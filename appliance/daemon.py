"""The supervised daemon: builds devices from the config through the driver registry, runs the
loop, serves status, and on the way out tells every link STOP."""
from __future__ import annotations

import dataclasses
import logging
import signal
import time
import threading
import types
from pathlib import Path

from appliance.config import Config, DeviceConfig
from appliance.loop import ApplianceLoop
from appliance.memory import MemoryKeeper
from appliance.perception import make_pipeline
from appliance import novelty_store
from appliance.recorder import Recorder
from appliance.service import Notifier
from appliance.status import StatusServer
from drivers.registry import create_device
from hal.clock import Clock, ManualClock, MonotonicClock
from hal.devices import Device
from hal.errors import ConfigError, DeviceError

log = logging.getLogger("fieldguard.daemon")

_PIPELINE_SENSORS = {"laser": ("laser",), "stereo": ("stereo",), "stereo-novelty": ("stereo",),
                     "rgbd": ("rgbd",)}


def _dev(name, kind, type_, timeout_s=0.25, **opts) -> DeviceConfig:
    return DeviceConfig(name=name, kind=kind, type=type_, timeout_s=timeout_s, required=True,
                        options=types.MappingProxyType(opts))


def sim_config(cfg: Config, scene: str | None = None) -> Config:
    """The config for ``--sim``: the file's settings, with simulated devices for every sensor the
    configured pipelines need and a simulated vehicle (unless the file already names sim
    devices). Other links the config names (a MAVLink bench autopilot, a CAN bus) are kept: they
    are told the same as the simulated vehicle."""
    sim = cfg.sim if scene is None else dataclasses.replace(cfg.sim, scene=scene)
    if any(d.type == "sim" for d in cfg.devices):
        return dataclasses.replace(cfg, sim=sim)
    sensors = []
    for p in cfg.perception.pipelines:
        for s in _PIPELINE_SENSORS.get(p, ()):
            if s not in sensors:
                sensors.append(s)
    links = tuple(d for d in cfg.devices if d.kind == "link" and d.name != "link")
    links += tuple(dataclasses.replace(d, name=f"{d.name}-{d.type}") for d in cfg.devices
                   if d.kind == "link" and d.name == "link")
    devs = tuple(_dev(s, s, "sim") for s in sensors) + (_dev("link", "link", "sim"),) + links
    return dataclasses.replace(cfg, sim=sim, devices=devs)


def replay_config(cfg: Config, run_path: str) -> Config:
    from drivers.runfolder import RunReader
    info = RunReader(run_path).info
    devs = [_dev(s, s, "replay") for s in ("stereo", "rgbd", "laser")
            if getattr(info, s) is not None]
    devs.append(_dev("link", "link", "replay"))
    devs += [dataclasses.replace(d, name=f"{d.name}-{d.type}") if d.name == "link" else d
             for d in cfg.devices if d.kind == "link" and d.type not in ("sim", "replay")]
    return dataclasses.replace(cfg, devices=tuple(devs))


class RenderAheadClock(ManualClock):
    """The lock-step clock of ``--sim``: advancing it to the next cycle steps the simulated
    vehicle and renders the world for that time, so the loop's acquire reads a finished frame
    (the simulator's rendering is not the box's time; it is measured apart, ``render_ms``)."""

    def __init__(self, start_ns: int, hub):
        super().__init__(start_ns)
        self._hub = hub                      # () -> SimHub | None (made with the devices)
        from appliance.loop import _Timing
        self.render_ms = _Timing()

    def sleep_until(self, t_ns: int) -> None:
        super().sleep_until(t_ns)
        hub = self._hub()
        if hub is not None:
            t0 = time.perf_counter()
            hub.at(self.now_ns())
            self.render_ms.add((time.perf_counter() - t0) * 1e3)


class Daemon:
    def __init__(self, cfg: Config, *, mode: str = "hardware", replay_path: str | None = None,
                 pace: float | None = None, status_socket: str | None = None,
                 clock: Clock | None = None, serve_status: bool = True,
                 notifier: Notifier | None = None):
        if mode not in ("hardware", "sim", "replay"):
            raise ValueError(mode)
        if not cfg.devices:
            raise ConfigError("no [devices] configured: give a config with devices, or run "
                              "with --sim or --replay RUN", file=cfg.source)
        from appliance.perception.stereo import check_daemon_matchers
        check_daemon_matchers(cfg)
        self.cfg = cfg
        self.mode = mode
        self.render_clock: RenderAheadClock | None = None
        if clock is None and mode == "sim":
            clock = self.render_clock = RenderAheadClock(10**9, lambda: self.shared.get("sim_hub"))
        self.clock = clock or (MonotonicClock() if mode == "hardware" else ManualClock(10**9))
        self.pace = pace if pace is not None else (cfg.sim.pace if mode == "sim" else
                                                   (1.0 if mode == "replay" else None))
        if mode == "hardware":
            self.pace = None
        self.shared = {"sim_config": cfg.sim, "replay_path": replay_path,
                       "rate_hz": cfg.loop.rate_hz,
                       "sim_sensors": tuple(d.kind for d in cfg.devices
                                            if d.type == "sim" and d.kind != "link")}
        self.devices: dict[str, Device] = {}
        self.stop_event = threading.Event()
        self.status_socket = status_socket if status_socket is not None else cfg.status.socket
        self.serve_status = serve_status
        self.status_server: StatusServer | None = None
        self.loop: ApplianceLoop | None = None
        self.pipelines = []
        self.recorder: Recorder | None = None
        self._record_jobs: dict = {}       # path -> recorder job, for record-status
        self.notifier = notifier if notifier is not None else Notifier()
        self._ready = False
        self.day_night = None
        self._status_state = None
        self._status_t = 0.0
        self.console = None
        self.memory = None
        self.model_keeper = None

    # -------------------------------------------------------------------------------------
    def start(self) -> None:
        for dc in self.cfg.devices:
            dev = create_device(dc, self.clock, self.shared)
            self.devices[dc.name] = dev
        for name, dev in self.devices.items():
            try:
                dev.open()
            except DeviceError as exc:
                # a device that does not open is a fault (STOP), not a crash: the loop runs
                dev._fault(f"could not open: {exc}")
                log.error("%s: could not open: %s", name, exc)
            if type(dev)._acquire_once is not Device._acquire_once:
                dev.start_acquisition()
        self.pipelines = [make_pipeline(n, self.cfg) for n in self.cfg.perception.pipelines]
        novelty_store.load_into(self.pipelines)     # a bad file: a log line, a fresh start
        self.model_keeper = novelty_store.ModelKeeper(
            self.pipelines, novelty_store.save_period_s(self.pipelines))
        self.model_keeper.start()                   # saves while running (power cuts)
        self.loop = ApplianceLoop(self.cfg, self.clock, self.devices, self.pipelines,
                                  kinds={d.name: d.kind for d in self.cfg.devices})
        self.loop.on_cycle.append(self._notify_cycle)
        if self.render_clock is not None:    # the first frame too is rendered before a cycle
            self.render_clock.sleep_until(self.clock.now_ns())
        for dev in self.devices.values():    # a strobe controller switching by scene brightness
            make = getattr(dev, "day_night_switch", None)
            self.day_night = self.day_night or (make(self.devices) if make else None)
        if self.day_night is not None:
            self.loop.on_cycle.append(self.day_night)
        if self.mode == "replay":
            self.loop.on_cycle.append(self._end_of_replay)
        sc = self.cfg.status
        self.recorder = Recorder(self.cfg.loop.rate_hz, sc.incident_dir, sc.incident_seconds,
                                 sc.incident_max, incident_max_mb=sc.incident_max_mb)
        self.loop.on_cycle.append(self.recorder.on_cycle)
        self.memory = MemoryKeeper(sc.malloc_trim_s)
        self.memory.start()
        if self.serve_status:
            self.status_server = StatusServer(self.status_socket, self.status, self.handle)
            self.status_server.start()
            from appliance.console import ConsoleService    # web console, Foxglove: never fatal
            self.console = ConsoleService(self)
            self.console.start()
        log.info("fieldguard up: mode=%s devices=%s pipelines=%s status=%s", self.mode,
                 ",".join(self.devices), ",".join(p.name for p in self.pipelines),
                 self.status_server.path if self.status_server else "-")

    def _end_of_replay(self, res) -> None:
        """A replay ends a few cycles after its last frame (long enough to show the STOP that
        stale data causes), unless the run loops."""
        p = self.shared.get("replay_player")
        if p is not None and not p.loop and p.finished(res.stamp_ns - 5 * self.loop.period_ns):
            self.request_stop()

    def _notify_cycle(self, res) -> None:
        """sd_notify: READY after the first gate cycle; STATUS on change (reason changes at most
        once a second); WATCHDOG only after a healthy cycle (on time, sent on every link)."""
        n = self.notifier
        text = f"{res.output.state.value}: {res.output.reason}"
        if not self._ready:
            n.ready(text)
            self._ready = True
            self._status_state, self._status_t = res.output.state, time.monotonic()
        elif res.output.state is not self._status_state or time.monotonic() - self._status_t >= 1:
            n.status(text)
            self._status_state, self._status_t = res.output.state, time.monotonic()
        if res.on_time and res.sent:
            n.healthy_cycle()

    def status(self) -> dict:
        doc = self.loop.status() if self.loop else {"state": "STOP", "reason": "starting"}
        doc["mode"] = self.mode
        doc["config"] = self.cfg.source
        n = self.notifier
        from appliance.service import logging_backend
        doc["systemd"] = {"notify": n.enabled, "watchdog_s": n.watchdog_s,
                          "last_messages": list(n.sent[-5:]), "errors": n.errors,
                          "backend": getattr(n, "backend", None), "logging": logging_backend()}
        hub = self.shared.get("sim_hub")
        if hub is not None:
            doc["sim"] = {"scene": self.cfg.sim.scene, **hub.field.stats()}
        if self.render_clock is not None:     # the simulator's time, apart from the loop's
            doc["sim_render_ms"] = self.render_clock.render_ms.summary()
        if self.recorder is not None:
            doc["incidents"] = list(self.recorder.incidents)[-5:]
        if self.day_night is not None:
            doc["day_night"] = self.day_night.status()
        if self.console is not None:
            doc["console"] = self.console.info()
        if self.memory is not None:
            doc["memory"] = self.memory.status()
        if self.model_keeper is not None and self.model_keeper.period_s > 0:
            doc["novelty_model_saves"] = self.model_keeper.status()
        heap = heap_status()
        if heap is not None:
            doc["heap"] = heap
        return doc

    # -- requests on the status socket ---------------------------------------------------------
    def handle(self, words: list[str]):
        cmd = words[0]
        if cmd == "snapshot":
            from appliance.snapshot import compose, encode_png
            res = self.loop.last if self.loop else None
            if res is None:
                return {"error": "no cycle has run yet"}
            return encode_png(compose(res, self.loop.grid.evidence.copy(), self.cfg,
                                      self.status()))
        if cmd == "selftest":
            return {"devices": selftest_devices(self.devices, self.cfg)}
        if cmd == "record":
            if len(words) != 3:
                return {"error": "usage: record SECONDS PATH"}
            seconds = float(words[1])
            if not 0 < seconds <= 3600:
                return {"error": "seconds must be in (0, 3600]"}
            job = self.recorder.record(seconds, words[2], self.clock.now_ns())
            self._record_jobs[str(job.path)] = job
            while len(self._record_jobs) > 20:          # the newest few are enough
                self._record_jobs.pop(next(iter(self._record_jobs)))
            return {"recording": str(job.path), "seconds": seconds}
        if cmd == "record-status" and len(words) == 2:  # progress of `fieldguard record`
            job = self._record_jobs.get(words[1])
            if job is None:
                return {"error": f"no recording {words[1]} asked of this daemon"}
            return {"recording": str(job.path), "written": job.written,
                    "dropped": job.dropped, "done": job.done.is_set(), "error": job.error}
        if cmd == "record-status":
            return {"incidents": list(self.recorder.incidents)}
        if cmd == "heap":                               # `heap` or `heap PATH` (a snapshot)
            return heap_request(words[1:])
        return {"error": f"unknown request {cmd!r}"}

    def run(self, max_cycles: int | None = None) -> None:
        self.loop.run(self.stop_event, max_cycles=max_cycles, pace=self.pace)

    def request_stop(self, *_args) -> None:
        self.stop_event.set()

    def install_signal_handlers(self) -> None:
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)

    def shutdown(self) -> None:
        if self.loop is not None:
            self.loop.send_stop_everywhere("fieldguard shutting down")
        self.notifier.stopping("STOP: fieldguard shutting down")
        if self.model_keeper is not None:
            self.model_keeper.stop()                # no periodic save racing the last one
        for p in self.pipelines:
            try:
                p.close()
            except Exception:
                log.exception("closing pipeline %s", p.name)
        novelty_store.save_from(self.pipelines)     # never raises
        if self.recorder is not None:
            self.recorder.close()
        for dev in self.devices.values():
            dev.close()
        if self.console is not None:
            self.console.stop()
        if self.status_server is not None:
            self.status_server.stop()
        if self.memory is not None:
            self.memory.stop()
        self.notifier.close()
        log.info("fieldguard stopped")


def heap_status() -> dict | None:
    """Python's own heap as tracemalloc counts it (numpy's buffers included), when the daemon
    was started with PYTHONTRACEMALLOC=N: a leak measure that the process's RSS (frame buffers
    coming and going, the allocator keeping freed pages) cannot give. None when not traced."""
    import tracemalloc
    if not tracemalloc.is_tracing():
        return None
    cur, peak = tracemalloc.get_traced_memory()
    return {"traced_mb": round(cur / 2**20, 3), "peak_mb": round(peak / 2**20, 3)}


def heap_request(args: list[str]) -> dict:
    """``heap``: the traced heap's size; ``heap PATH``: also a tracemalloc snapshot dumped to
    PATH (compare two with tools/heap_diff.py). Taking one holds the interpreter for a moment
    (about a second with a few hundred thousand blocks): a measuring run's tool, not a field
    one."""
    import tracemalloc
    doc = heap_status()
    if doc is None:
        return {"error": "the daemon's heap is not traced: start it with PYTHONTRACEMALLOC=1 "
                         "(or more frames) in its environment"}
    if len(args) > 1:
        return {"error": "usage: heap [PATH]"}
    if args:
        try:
            tracemalloc.take_snapshot().dump(args[0])
        except OSError as exc:
            return {"error": f"cannot write the heap snapshot {args[0]}: {exc.strerror}"}
        doc["snapshot"] = args[0]
    return doc


HINTS = {
    "stereo": "check the camera cables and power, the GigE network (jumbo frames, addresses) and "
              "the trigger controller",
    "rgbd": "check the USB cable and power of the depth camera",
    "laser": "check the laser's power and Ethernet cable, and its IP address in the config",
    "trigger": "check the trigger controller's serial cable and its port in the config",
    "link": "check the vehicle link: cable or connection string, baud rate, that the autopilot "
            "or tractor controller is on and talking",
}


def selftest_devices(devices: dict, cfg: Config) -> list[dict]:
    out = []
    types_ = {d.name: (d.kind, d.type) for d in cfg.devices}
    for name, dev in devices.items():
        kind, type_ = types_.get(name, (dev.kind, "?"))
        try:
            ok, msg = dev.selftest()
        except Exception as exc:
            ok, msg = False, f"selftest raised {type(exc).__name__}: {exc}"
        h = dev.health()
        out.append({"name": name, "kind": kind, "type": type_, "ok": bool(ok), "message": msg,
                    "age_s": None if h.age_s is None else round(h.age_s, 3),
                    "fix": "" if ok else HINTS.get(kind, "check the device")})
    return out
