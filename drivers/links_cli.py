"""Command-line overrides for the vehicle links, for the lead to wire into ``appliance/cli.py``:

    fieldguard run --config F --mavlink udpout:127.0.0.1:14550
    fieldguard run --config F --mavlink /dev/ttyACM0,921600
    fieldguard run --config F --can socketcan:can0
    fieldguard run --config F --can udp_multicast:239.74.163.2

Each function turns the override string into the device table a config file would hold; the
caller validates it like a file table (so an unknown key or bad value is reported the same way)
and puts it in place of the configured link of that type (or adds one named ``link``).
"""
from __future__ import annotations

from hal.errors import ConfigError


def mavlink_table(text: str) -> dict:
    """``CONNECTION`` as pymavlink spells it (udpin:/udpout:/tcp:/serial device), optionally
    ``DEVICE,BAUD`` for a serial port."""
    t = text.strip()
    if not t:
        raise ConfigError("--mavlink needs a connection, e.g. udpout:127.0.0.1:14550 or "
                          "/dev/ttyACM0,921600")
    table = {"type": "mavlink"}
    if "," in t and not t.startswith(("udp", "tcp")):
        dev, _, baud = t.rpartition(",")
        try:
            table["baud"] = int(baud)
        except ValueError:
            raise ConfigError(f"--mavlink {text!r}: baud rate {baud!r} is not a number")
        t = dev
    table["connection"] = t
    return table


def can_table(text: str) -> dict:
    """``INTERFACE:CHANNEL`` for python-can, e.g. ``socketcan:can0``."""
    iface, sep, channel = text.strip().partition(":")
    if not sep or not iface or not channel:
        raise ConfigError(f"--can {text!r}: expected INTERFACE:CHANNEL, e.g. socketcan:can0")
    return {"type": "can-j1939", "interface": iface, "channel": channel}


def apply_link_override(devices: dict, table: dict, default_name: str = "link",
                        replace_others: bool = True) -> dict:
    """Return a copy of the raw ``[devices]`` mapping (as read from TOML) with the link of the
    same type replaced by ``table`` — keeping its other options, e.g. sysid — or, if there is
    none, a new link named ``default_name`` added; with ``replace_others`` (the default) the
    links of other types are dropped then (``--mavlink`` on a sim config replaces the sim link).
    For ``--mavlink`` and ``--can`` together, call it for the second with
    ``replace_others=False`` and another ``default_name``."""
    out = dict(devices)
    for name, t in devices.items():
        if isinstance(t, dict) and t.get("kind", name) == "link" and t.get("type") == table["type"]:
            out[name] = {**t, **table}
            return out
    for name, t in list(out.items()):
        if replace_others and isinstance(t, dict) and t.get("kind", name) == "link":
            del out[name]
    out[default_name] = dict(table) if default_name == "link" else {"kind": "link", **table}
    return out
