"""The novelty model saved while the box runs (``[perception.stereo-novelty] model_save_s``):
a tractor whose power is cut at key-off never shuts the box down, and a box that saved its
model only at shutdown would boot every morning with an empty one."""
import dataclasses
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from appliance import novelty_store
from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline

ROOT = Path(__file__).resolve().parent.parent


def _pipe(**kw):
    return StereoNoveltyPipeline(dataclasses.replace(StereoNoveltyConfig(), **kw),
                                 background=False)


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_save_period_is_the_shortest_of_the_pipelines_that_persist(tmp_path):
    env = {"STATE_DIRECTORY": str(tmp_path)}
    a, b = _pipe(model_save_s=300.0), _pipe(model_save_s=60.0)
    off = _pipe(model_state="off", model_save_s=5.0)
    try:
        assert novelty_store.save_period_s([a, b, off], env) == 60.0
        assert novelty_store.save_period_s([a], {}) == 0.0     # no state directory: no file
        assert novelty_store.save_period_s([off], env) == 0.0
        assert novelty_store.save_period_s([_pipe(model_save_s=0.0)], env) == 0.0
    finally:
        for p in (a, b, off):
            p.close()


def test_keeper_saves_while_running_and_a_failure_is_a_log_line(tmp_path, caplog):
    env = {"STATE_DIRECTORY": str(tmp_path)}
    p = _pipe()
    f = tmp_path / "novelty-stereo-novelty.npz"
    k = novelty_store.ModelKeeper([p], 0.05, env)
    k.start()
    try:
        time.sleep(0.2)
        assert not f.exists()                            # an empty model is not written
        p.novelty.model.update(np.random.default_rng(0).uniform(0, 1, (50, 8)))
        assert _wait(lambda: f.exists())
        assert novelty_store.read(f)["updates"] == 1
        n = k.saves            # the file can be on disk before the round that wrote it counts
        p.novelty.model.update(np.random.default_rng(1).uniform(0, 1, (50, 8)))
        assert _wait(lambda: (novelty_store.read(f) or {}).get("updates") == 2)
        assert _wait(lambda: k.saves >= n + 1) and k.last_saved == [str(f)]
        st = k.status()
        assert st["every_s"] == 0.05 and st["files"] == [str(f)] and 0 <= st["last_save_s_ago"] < 5
        assert not (tmp_path / "novelty-stereo-novelty.npz.tmp").exists()
    finally:
        k.stop()
    assert k._thread is None
    # a place it cannot write: logged every period, the thread goes on, the old file stays
    ro = _pipe(model_state=str(tmp_path / "d" / "x.npz"))
    (tmp_path / "d").write_text("a file where a directory should be")
    ro.novelty.model.update(np.random.default_rng(2).uniform(0, 1, (10, 8)))
    k = novelty_store.ModelKeeper([ro], 0.05, env)
    with caplog.at_level(logging.WARNING, "fieldguard.novelty"):
        k.start()
        try:
            assert _wait(lambda: caplog.text.count("not saved") >= 2)
            assert k._thread.is_alive() and k.saves == 0
        finally:
            k.stop()
    for x in (p, ro):
        x.close()


def test_model_survives_a_power_cut_of_the_running_daemon(tmp_path):
    """The real daemon on the simulated field, killed with SIGKILL (no shutdown, as a power
    cut): the model it saved while running is loaded by the next start."""
    cfg = tmp_path / "c.toml"
    cfg.write_text('[perception]\npipelines = ["stereo-novelty"]\n\n'
                   '[perception.stereo-novelty]\nmodel_save_s = 0.5\n')
    state = tmp_path / "state"
    state.mkdir()
    env = {**os.environ, "STATE_DIRECTORY": str(state), "PYTHONPATH": str(ROOT)}
    f = state / "novelty-stereo-novelty.npz"
    p = subprocess.Popen([sys.executable, "-m", "appliance.cli", "run", "--sim", "--fast",
                          "--config", str(cfg), "--duration", "600",
                          "--socket", str(tmp_path / "s.sock")], env=env, cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait(lambda: f.exists() or p.poll() is not None, 120), "no model saved in 120 s"
        assert p.poll() is None, p.stderr.read()[-2000:]
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=15)
    finally:
        if p.poll() is None:
            p.kill()
        p.stderr.close()
    saved = novelty_store.read(f)
    assert saved is not None and saved["updates"] >= 1 and len(saved["w"]) > 0
    r = subprocess.run([sys.executable, "-m", "appliance.cli", "run", "--sim", "--fast",
                        "--config", str(cfg), "--duration", "0.3",
                        "--socket", str(tmp_path / "s2.sock")], env=env, cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"novelty model {f} loaded: {len(saved['w'])} samples" in r.stderr
