"""The config field helper: a dataclass field with its validation rules (bounds, choices, doc).

Apart from appliance/config.py so that the option dataclasses of the perception pipelines can
use it without importing the appliance config (which imports the pipeline registry to validate
``[perception.NAME]`` tables: config -> perception, never back)."""
from __future__ import annotations

from dataclasses import field


def _f(default, *, lo=None, hi=None, choices=None, doc=""):
    """A config field with its validation rules."""
    meta = {"lo": lo, "hi": hi, "choices": choices, "doc": doc}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: default, metadata=meta)
    return field(default=default, metadata=meta)
