"""The unit verifies clean and rates OK; install/uninstall into a throwaway root."""
import os
import re
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.conftest import missing_tool

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "deploy" / "fieldguard.service"


def need(tool):
    if shutil.which(tool) is None:
        missing_tool(f"{tool} not installed")


def build_marks() -> dict[str, int]:
    """Every path (and its mtime) under the source tree's build/ and *.egg-info/: what a build
    in the tree writes."""
    marks = {}
    for top in ROOT.iterdir():
        if top.name == "build" or top.name.endswith(".egg-info"):
            for p in [top, *top.rglob("*")]:
                marks[str(p.relative_to(ROOT))] = p.lstat().st_mtime_ns
    return marks


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    need("systemctl")
    root = tmp_path_factory.mktemp("root")
    before = build_marks()
    r = subprocess.run(["bash", str(ROOT / "deploy" / "install.sh"), "--root", str(root),
                        "--pip-args", "--no-deps"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return SimpleNamespace(root=root, out=r.stdout, marks_before=before,
                           marks_after=build_marks())


def test_install_builds_outside_the_source_tree(installed):
    """A build in the tree (pip's default) shares build/ with every other install from it:
    two at once (tests/test_install.py beside this module) tore each other's build down
    (CI, 2026-12-08: "could not create 'build/bdist.linux-x86_64/wheel/...'")."""
    assert installed.marks_after == installed.marks_before


def test_install_lays_out_the_box(installed):
    root, out = installed.root, installed.out
    assert (root / "opt/fieldguard/venv/bin/fieldguard").exists()
    assert (root / "etc/fieldguard/fieldguard.toml").read_text() == \
        (ROOT / "deploy/fieldguard.toml").read_text()
    assert (root / "etc/udev/rules.d/99-fieldguard.rules").exists()
    assert (root / "etc/systemd/system/fieldguard.service").exists()
    wants = root / "etc/systemd/system/multi-user.target.wants/fieldguard.service"
    assert wants.is_symlink()
    # the shipped config is valid
    from appliance.config import load_config
    assert load_config(root / "etc/fieldguard/fieldguard.toml").devices


def test_unit_verifies_clean_in_the_installed_root(installed, tmp_path):
    need("systemd-analyze")
    root = installed.root
    # verify the installed unit with its paths pointing into the throwaway root, so that
    # systemd-analyze also checks that ExecStart/ExecStartPre exist as installed
    unit = tmp_path / "fieldguard.service"
    unit.write_text((root / "etc/systemd/system/fieldguard.service").read_text()
                    .replace("/opt/fieldguard/", f"{root}/opt/fieldguard/"))
    r = subprocess.run(["systemd-analyze", "verify", "--man=no", str(unit)],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    text = (r.stdout + r.stderr).strip()
    # systemd-analyze only warns (rc 0) about unknown keys: the output must be empty
    assert r.returncode == 0 and text == "", text


def test_unit_exposure_is_ok():
    need("systemd-analyze")
    r = subprocess.run(["systemd-analyze", "security", "--offline=true", str(UNIT)],
                       capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+) (\w+)", r.stdout + r.stderr)
    assert m, r.stdout[-500:] + r.stderr
    assert float(m.group(1)) <= 3.0 and m.group(2) == "OK", m.group(0)


def test_unit_is_what_the_daemon_expects():
    text = UNIT.read_text()
    for key in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "User=fieldguard",
                "NoNewPrivileges=yes", "ProtectSystem=strict", "RuntimeDirectory=fieldguard"):
        assert key in text, key


def test_upgrade_never_overwrites_the_config_and_uninstall_keeps_it(installed, tmp_path):
    root = installed.root
    cfg = root / "etc/fieldguard/fieldguard.toml"
    cfg.write_text(cfg.read_text().replace("hold_off_s = 1.0", "hold_off_s = 2.0"))
    r = subprocess.run(["bash", str(ROOT / "deploy" / "install.sh"), "--root", str(root),
                        "--pip-args", "--no-deps"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "hold_off_s = 2.0" in cfg.read_text()
    assert (root / "etc/fieldguard/fieldguard.toml.new").exists()
    assert "kept your" in r.stdout
    r = subprocess.run(["bash", str(ROOT / "deploy" / "uninstall.sh"), "--root", str(root)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert not (root / "opt/fieldguard").exists()
    assert not (root / "etc/systemd/system/fieldguard.service").exists()
    assert not (root / "etc/systemd/system/multi-user.target.wants/fieldguard.service").exists()
    assert cfg.exists()
    r = subprocess.run(["bash", str(ROOT / "deploy" / "uninstall.sh"), "--root", str(root),
                        "--purge"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and not (root / "etc/fieldguard").exists()


def test_install_refuses_unknown_option(tmp_path):
    r = subprocess.run(["bash", str(ROOT / "deploy" / "install.sh"), "--frobnicate"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "unknown option" in r.stderr


# ---- the shipped config and the device names (issue #16) ------------------------------------
SHIPPED = ROOT / "deploy" / "fieldguard.toml"


def _templates() -> dict[str, str]:
    """The commented device templates of the shipped config, uncommented, by heading (#n)."""
    out, cur, buf = {}, None, []

    def flush():
        if cur:
            out[f"{cur} #{len(out)}"] = "\n".join(buf)

    for line in SHIPPED.read_text().splitlines():
        if line.startswith("# [devices."):
            flush()
            cur, buf = line[2:].strip(), [line[2:]]
        elif cur and line.startswith("# ") and "=" in line:
            buf.append(line[2:])
        else:
            flush()
            cur, buf = None, []
    flush()
    return out


def test_shipped_config_is_a_hardware_template_that_parses():
    import tomllib
    from appliance.config import parse_config
    t = _templates()
    kinds = sorted({k.split()[0] for k in t})
    assert kinds == ["[devices.laser]", "[devices.link]", "[devices.rgbd]", "[devices.stereo]",
                     "[devices.trigger]"], kinds
    types = set()
    for head, body in t.items():
        table = tomllib.loads(body)["devices"]
        (name, dev), = table.items()
        types.add(dev["type"])
        # each template is a valid device table (beside a sim laser / a sim link)
        devs = {"laser": {"type": "sim"}, "link": {"type": "sim"}, name: dev}
        parse_config({"devices": devs}, f"template {head}")
    assert {"mavlink", "can-j1939", "sick-lms1xx", "aravis", "freenect", "serial"} <= types
    text = SHIPPED.read_text()
    assert "same as `fieldguard run --sim`" not in text


def test_shipped_config_records_incidents_within_a_disk_budget():
    from appliance.config import load_config
    cfg = load_config(SHIPPED)
    assert cfg.status.incident_dir == "/var/lib/fieldguard/incidents"     # StateDirectory
    assert cfg.status.incident_max >= 1 and 0 < cfg.status.incident_max_mb <= 5000
    assert "StateDirectory=fieldguard" in UNIT.read_text()


def test_device_names_agree_between_udev_the_drivers_and_the_templates():
    from drivers.strobe_serial import StrobeSerialTrigger as StrobeTrigger
    rules = (ROOT / "deploy" / "99-fieldguard.rules").read_text()
    names = {f"/dev/{n}" for n in re.findall(r'SYMLINK\+="([^"]+)"', rules)}
    assert names == {"/dev/fieldguard-strobe", "/dev/fieldguard-autopilot"}
    import inspect
    default_port = inspect.signature(StrobeTrigger.__init__).parameters["port"].default
    assert default_port in names
    t = "\n".join(_templates().values())
    for dev in re.findall(r'"(/dev/[^"]+)"', t):
        assert dev in names, dev
