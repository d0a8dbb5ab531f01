"""The novelty model across restarts: a file in the state directory (issue #14).

A stereo-novelty pipeline's background model is what the box has learnt the field looks like;
keeping it means a restart does not start from an empty model. The file is an ``.npz`` of the
samples and weights with a JSON header (``magic``, ``version``, the detector's fingerprint:
descriptor definition and kernel). Reading it never takes the box down: a missing file is a
fresh start; a corrupt, truncated, foreign (other settings, another program's file) or
newer-version file is one clear log line and a fresh start. Writing goes to a temporary file
in the same directory and is renamed over the old one, and the directory is synced (a crash or
a power cut mid-write leaves the old model).

When: at shutdown, and every ``model_save_s`` seconds while running (:class:`ModelKeeper`, a
thread of the daemon's: a vehicle whose power is cut at key-off never shuts the box down, and a
box that saved only at shutdown booted with an empty model, or that of its last clean shutdown:
an empty one costs the first seconds' stubble stops, docs/front-end.md "The field's canopy, and
the boot").

Where: ``[perception.stereo-novelty] model_state``: "auto" (default) = the service's state
directory ($STATE_DIRECTORY, set by systemd's ``StateDirectory=``), file
``novelty-<pipeline>.npz``; "off" = never; anything else = that path.

One model per light: the latest file holds the newest model whatever its light; a model learnt
under the strobe is also written to ``<file>.night-strobe.npz`` beside it, which a day save
does not replace. A box that boots with a day model and finds the strobe lighting its frames
(it was parked by day and started after dark) swaps in that night model instead of learning
from empty (docs/front-end.md "A model of the other light").

The boot guard (``boot_guard``) is what makes a fresh start safe; the stored model is not
trusted more than that: after loading, every update still leaves out the cells near what the
frame detected.
"""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from appliance.perception.novelty import NIGHT_LIGHT
from appliance.periodic import Periodic

log = logging.getLogger("fieldguard.novelty")

MAGIC = "fieldguard-novelty"


def state_path(setting: str, pipeline: str, env: dict | None = None) -> Path | None:
    """The file for ``model_state = setting`` (None = do not persist)."""
    env = os.environ if env is None else env
    if setting in ("", "off"):
        return None
    if setting == "auto":
        d = env.get("STATE_DIRECTORY", "").split(":")[0]
        return Path(d) / f"novelty-{pipeline}.npz" if d else None
    return Path(setting)


def light_path(path: Path, light: str) -> Path:
    """The file that keeps the newest model learnt under ``light`` beside ``path`` (the latest
    model, whatever its light): ``novelty-stereo-novelty.night-strobe.npz``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.{light}{path.suffix}")


def save(path: Path, state: dict) -> None:
    """Write ``state`` (NoveltyDetector.export_state()) atomically."""
    meta = {"magic": MAGIC, "version": state["version"], "fingerprint": state["fingerprint"],
            "updates": int(state["updates"])}
    if state.get("light") is not None:          # the frames' light it was learnt under
        meta["light"] = state["light"]
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), x=state["x"], w=state["w"])
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)           # no half-written file left behind
        raise
    try:                      # the rename itself must survive a power cut
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass                  # a file system that cannot sync a directory: the rename stands
    finally:
        os.close(fd)


def read(path: Path, then: str = "starting with an empty model") -> dict | None:
    """The state in ``path``, or None (missing: silently; unreadable or not ours: logged,
    with ``then``: what the box does instead)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise ValueError("not a fieldguard novelty model")
            meta = json.loads(str(z["meta"]))
            if not isinstance(meta, dict) or meta.get("magic") != MAGIC:
                raise ValueError("not a fieldguard novelty model")
            return {"version": meta.get("version"), "fingerprint": meta.get("fingerprint"),
                    "updates": meta.get("updates", 1), "x": np.array(z["x"]),
                    "w": np.array(z["w"]), "light": meta.get("light")}
    except Exception as exc:                 # noqa: BLE001 - any bad file is a fresh start
        log.warning("novelty model %s unreadable (%s): %s", path, exc, then)
        return None


def _novelty_pipelines(pipelines):
    for p in pipelines:
        parts = getattr(p, "parts", None)
        if parts:
            yield from _novelty_pipelines(parts)
        elif hasattr(p, "novelty") and hasattr(p.novelty, "export_state"):
            yield p


def load_into(pipelines, env: dict | None = None) -> list[str]:
    """Load each stereo-novelty pipeline's saved model; returns what was loaded (for the
    log). Never raises for a bad file."""
    done = []
    for p in _novelty_pipelines(pipelines):
        path = state_path(getattr(p.options, "model_state", "off"), p.name, env)
        if path is None:
            continue
        state = read(path)
        if state is None:
            continue
        try:
            p.novelty.import_state(state)
        except ValueError as exc:
            log.warning("novelty model %s not used (%s): starting with an empty model", path,
                        exc)
            continue
        log.info("novelty model %s loaded: %d samples, learnt under %s light", path,
                 p.novelty.model.size, state.get("light") or "unrecorded")
        done.append(str(path))
        if state.get("light") == "day":
            _keep_night_model(p, light_path(path, NIGHT_LIGHT))
    return done


def _keep_night_model(p, path: Path) -> None:
    """A day model was loaded: the strobe-lit model beside it (if any, and fit) is kept for a
    boot that turns out to be at night (NoveltyDetector.set_aside_other_light)."""
    state = read(path, then="not kept for a strobe-lit boot")
    if state is None:
        return
    try:
        p.novelty.keep_night_model(state)
    except ValueError as exc:
        log.warning("novelty model %s not kept for a strobe-lit boot (%s)", path, exc)
        return
    log.info("novelty model %s kept for a strobe-lit boot", path)


def save_from(pipelines, env: dict | None = None) -> list[str]:
    """Save each stereo-novelty pipeline's model (an empty model is not written; a strobe-lit
    one also to its night file); returns the files written. A failure to write is logged,
    never raised (the box is shutting down or running)."""
    done = []
    for p in _novelty_pipelines(pipelines):
        path = state_path(getattr(p.options, "model_state", "off"), p.name, env)
        if path is None:
            continue
        state = p.novelty.export_state()
        if state is None:
            continue
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            save(path, state)
        except Exception as exc:             # noqa: BLE001 - shutting down: log, go on
            log.warning("novelty model %s not saved: %s", path, exc)
            continue
        done.append(str(path))
        if state.get("light") == NIGHT_LIGHT:    # also kept apart: a day save won't replace it
            night = light_path(path, NIGHT_LIGHT)
            try:
                save(night, state)
            except Exception as exc:         # noqa: BLE001 - as above
                log.warning("novelty model %s not saved: %s", night, exc)
                continue
            done.append(str(night))          # status lists it: the technician sees both
    return done


def save_period_s(pipelines, env: dict | None = None) -> float:
    """The shortest ``model_save_s`` of the pipelines that persist a model here (0: none saves
    while running: none has a ``model_state`` file, or every period is 0)."""
    periods = [float(getattr(p.options, "model_save_s", 0.0) or 0.0)
               for p in _novelty_pipelines(pipelines)
               if state_path(getattr(p.options, "model_state", "off"), p.name, env) is not None]
    periods = [t for t in periods if t > 0]
    return min(periods) if periods else 0.0


class ModelKeeper(Periodic):
    """Saves the novelty models every ``period_s`` seconds on its own thread (:func:`save_from`:
    never raises; a failure is a log line and the next period tries again). The model is read
    from its immutable snapshot (ParzenModel swaps snapshots whole), so the loop and the
    background update go on while it writes."""

    name = "novelty-save"
    logger = "fieldguard.novelty"

    def __init__(self, pipelines, period_s: float, env: dict | None = None):
        super().__init__(period_s)
        self.pipelines, self.env = pipelines, env
        self.saves = 0                  # rounds that wrote at least one model
        self.last_saved: list[str] = []
        self.last_saved_mono: float | None = None

    def tick(self) -> None:
        done = save_from(self.pipelines, self.env)
        if done:
            self.last_saved = done
            self.last_saved_mono = time.monotonic()
            self.saves += 1                 # last: a reader that sees it sees the rest

    def status(self) -> dict:
        """For the status document: the period, how many saves, the files, how long ago."""
        ago = (None if self.last_saved_mono is None
               else round(time.monotonic() - self.last_saved_mono, 1))
        return {"every_s": self.period_s, "saves": self.saves, "files": list(self.last_saved),
                "last_save_s_ago": ago}
