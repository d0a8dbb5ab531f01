"""tools/boot_with_model.py: each drive from an empty state, then again with the model it saved
(the installed box's boot after the periodic save)."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import boot_with_model as bwm  # noqa: E402


def _run(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "boot_with_model.py"), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_seed_lists():
    assert bwm.seeds_of("79-81,90") == [79, 80, 81, 90]
    assert bwm.seeds_of("5") == [5]


def test_refusals_are_messages(tmp_path):
    p = _run("--scene", "stubble-coverage", "--seeds", "x-3", "--out", str(tmp_path))
    assert p.returncode == 2 and "--seeds wants" in p.stderr and "Traceback" not in p.stderr
    cfg = tmp_path / "laser.toml"
    cfg.write_text('[perception]\npipelines = ["laser"]\n')
    p = _run("--scene", "stubble-coverage", "--seeds", "1", "--config", str(cfg),
             "--out", str(tmp_path))
    assert p.returncode == 2 and "must run stereo-novelty" in p.stderr
    p = _run("--scene", "stubble-coverage", "--seeds", "1", "--cross", "--out", str(tmp_path))
    assert p.returncode == 2 and "--cross wants two scenes" in p.stderr
    p = _run("--scene", "nosuch", "--seeds", "1", "--out", str(tmp_path))
    assert p.returncode == 2 and "unknown scene 'nosuch'" in p.stderr
    assert "Traceback" not in p.stderr


def test_cross_boots_each_scene_with_the_other_scenes_model(tmp_path, monkeypatch, capsys):
    """--cross: both scenes' runs from empty for a seed come first; then each scene's second
    run loads a copy of the model the other scene's first run saved (the drives themselves are
    the campaign's, tested there: here who loads what)."""
    calls = []

    def fake_one(kind, seed, minutes, extra, model):
        loaded = model.read_text() if model.exists() else None
        calls.append((kind, seed, model.name, loaded))
        model.write_text(f"model of {kind} {seed}")       # saved at the end, as the drive does
        return {k: 0 for k in bwm.KEYS}
    monkeypatch.setattr(bwm, "one", fake_one)
    rc = bwm.main(["--scene", "stubble-coverage,stubble-coverage-night", "--seeds", "3,4",
                   "--cross", "--config", str(_config(tmp_path)), "--out", str(tmp_path / "o")])
    assert rc == 0, capsys.readouterr().err
    day, night = "stubble-coverage", "stubble-coverage-night"
    assert calls == [
        (day, 3, f"{day}-3.npz", None), (night, 3, f"{night}-3.npz", None),
        (day, 3, f"{day}-3-with-{night}.npz", f"model of {night} 3"),
        (night, 3, f"{night}-3-with-{day}.npz", f"model of {day} 3"),
        (day, 4, f"{day}-4.npz", None), (night, 4, f"{night}-4.npz", None),
        (day, 4, f"{day}-4-with-{night}.npz", f"model of {night} 4"),
        (night, 4, f"{night}-4-with-{day}.npz", f"model of {day} 4")]
    out = capsys.readouterr().out
    assert f"{day} 3" in out and out.count(night) >= 2


def test_per_light_puts_the_scenes_own_night_model_beside_the_other_scenes(tmp_path,
                                                                         monkeypatch, capsys):
    """--cross --per-light: the night scene's second run loads the day scene's model and finds
    its own first run's night file beside it (the box's per-light file); the day scene's,
    which saved none, finds none. Without --cross it is refused."""
    seen = []

    def fake_one(kind, seed, minutes, extra, model):
        night = model.with_name(f"{model.stem}.night-strobe.npz")
        seen.append((kind, model.name, model.read_text() if model.exists() else None,
                     night.read_text() if night.exists() else None))
        model.write_text(f"model of {kind} {seed}")
        if kind.endswith("night"):
            night.write_text(f"night model of {kind} {seed}")
        return {k: 0 for k in bwm.KEYS}
    monkeypatch.setattr(bwm, "one", fake_one)
    day, night = "stubble-coverage", "stubble-coverage-night"
    out = tmp_path / "o"
    out.mkdir()
    (out / f"{night}-3-with-{day}.night-strobe.npz").write_text("stale, from a run before")
    rc = bwm.main(["--scene", f"{day},{night}", "--seeds", "3", "--cross", "--per-light",
                   "--config", str(_config(tmp_path)), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert seen == [
        (day, f"{day}-3.npz", None, None), (night, f"{night}-3.npz", None, None),
        (day, f"{day}-3-with-{night}.npz", f"model of {night} 3", None),
        (night, f"{night}-3-with-{day}.npz", f"model of {day} 3", f"night model of {night} 3")]
    p = _run("--scene", f"{day},{night}", "--seeds", "1", "--per-light", "--out", str(out))
    assert p.returncode == 2 and "--per-light goes with --cross" in p.stderr


def _config(tmp_path):
    cfg = tmp_path / "sl.toml"
    cfg.write_text('[perception]\npipelines = ["stereo-novelty", "laser"]\n')
    return cfg


def test_other_field_loads_the_model_of_the_other_seed_of_its_pair(tmp_path, monkeypatch,
                                                                   capsys):
    """--other-field: seeds in pairs; each drive's second run loads a copy of the model the
    same scene's drive of the other seed saved; an odd number of seeds is refused."""
    calls = []

    def fake_one(kind, seed, minutes, extra, model):
        calls.append((kind, seed, model.name, model.read_text() if model.exists() else None))
        model.write_text(f"model of {kind} {seed}")
        return {k: 0 for k in bwm.KEYS}
    monkeypatch.setattr(bwm, "one", fake_one)
    day = "stubble-coverage"
    rc = bwm.main(["--scene", day, "--seeds", "5-6", "--other-field",
                   "--config", str(_config(tmp_path)), "--out", str(tmp_path / "o")])
    assert rc == 0, capsys.readouterr().err
    assert calls == [
        (day, 5, f"{day}-5.npz", None), (day, 6, f"{day}-6.npz", None),
        (day, 5, f"{day}-5-with-{day}-6.npz", f"model of {day} 6"),
        (day, 6, f"{day}-6-with-{day}-5.npz", f"model of {day} 5")]
    assert f"{day} 6" in capsys.readouterr().out
    p = _run("--scene", day, "--seeds", "5-7", "--other-field", "--out", str(tmp_path))
    assert p.returncode == 2 and "--other-field wants an even number" in p.stderr
