import pytest

from appliance.config import default_config, load_config, parse_config
from hal.errors import ConfigError


def write(tmp_path, text):
    p = tmp_path / "fg.toml"
    p.write_text(text)
    return p


def test_defaults_are_valid():
    cfg = default_config()
    assert cfg.loop.rate_hz == 10.0
    assert cfg.perception.pipelines == ("laser",)
    assert cfg.grid.cell_m == 0.1


def test_shipped_default_config_loads():
    from pathlib import Path
    cfg = load_config(Path(__file__).resolve().parents[1] / "deploy" / "fieldguard.toml")
    assert {d.kind for d in cfg.devices} >= {"laser", "link"}
    # the shipped box stops for a walker about to meet it (the default since the 17th session)
    assert cfg.tracking.movers and not cfg.tracking.enabled
    assert default_config().tracking.movers


def test_full_file(tmp_path):
    p = write(tmp_path, """
[loop]
rate_hz = 10
[gate]
hold_off_s = 2.0
[zones]
decel_mps2 = 1.5
[[zones.exclusion]]
x_min_m = -1.0
x_max_m = 0.0
y_min_m = -3.0
y_max_m = 3.0
[perception]
pipelines = ["laser"]
[perception.laser]
max_range_m = 20.0
[devices.laser]
type = "sim"
timeout_s = 0.3
[devices.link]
type = "log"
assume_speed_mps = 2.0
""")
    cfg = load_config(p)
    assert cfg.gate.hold_off_s == 2.0
    assert cfg.zones.exclusion[0].y_max_m == 3.0
    assert cfg.device("laser").timeout_s == 0.3
    assert cfg.device("link").options["assume_speed_mps"] == 2.0
    with pytest.raises(Exception):
        cfg.loop.rate_hz = 5   # frozen


@pytest.mark.parametrize("text, key, words", [
    ("[loop]\nrate_hz = 'fast'\n", "loop.rate_hz", "must be a number"),
    ("[loop]\nrate_hz = 0.0\n", "loop.rate_hz", ">= 1.0"),
    ("[loop]\nrat_hz = 10\n", "loop.rat_hz", "unknown key"),
    ("[lop]\nrate_hz = 10\n", "lop", "unknown section"),
    ("[gate]\nhold_off_s = -1\n", "gate.hold_off_s", ">= 0.0"),
    ("[devices.laser]\ntype = 'sick-lms9000'\n", "devices.laser.type", "unknown type"),
    ("[devices.laser]\ntimeout_s = 0.2\n", "devices.laser", "needs a type"),
    ("[devices.laser]\ntype = 'sim'\nbaud = 9600\n", "devices.laser.baud", "unknown key"),
    ("[devices.toaster]\ntype = 'sim'\n", "devices.toaster", "unknown device kind"),
    ("[perception]\npipelines = ['sonar']\n", "perception.pipelines", "unknown pipeline"),
    ("[grid]\nx_min_m = 5.0\nx_max_m = 1.0\n", "grid", "x_max_m > x_min_m"),
    ("[[zones.exclusion]]\nx_min_m = 1.0\nx_max_m = 0.0\ny_min_m = 0\ny_max_m = 1\n",
     "zones.exclusion[0]", "x_max_m > x_min_m"),
    ("[devices.laser]\ntype = 'sim'\n[devices.link]\ntype = 'sim'\n[gate]\nrequired = ['radar']\n",
     "gate.required", "not configured"),
    ("[devices.laser]\ntype = 'sim'\nrequired = 'yes'\n", "devices.laser.required", "true or false"),
])
def test_bad_values_name_file_and_key(tmp_path, text, key, words):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    msg = str(ei.value)
    assert str(p) in msg
    assert f"[{key}]" in msg
    assert words in msg


def test_not_toml(tmp_path):
    p = write(tmp_path, "[loop\nrate_hz=")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")


def test_cli_config_check(tmp_path, capsys):
    from appliance.cli import main
    good = write(tmp_path, "[devices.laser]\ntype = 'sim'\n")
    assert main(["config", "check", str(good)]) == 0
    assert "OK" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text("[loop]\nrate_hz = -3\n")
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "loop.rate_hz" in err and "bad.toml" in err
