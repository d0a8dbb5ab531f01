import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def missing_tool(reason: str):
    """A test needs something the project's own scripts install. Locally it is skipped with the
    reason; in CI (CI=true) it FAILS, so a missing install step can never hide behind a skip."""
    import os

    import pytest
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"{reason} — CI must install it (tools/ci_system_deps.sh)")
    pytest.skip(reason)


import logging as _logging  # noqa: E402

import pytest as _pytest  # noqa: E402


@_pytest.fixture(autouse=True)
def _restore_root_logging():
    """A test that runs the CLI in-process (or setup_logging) points the root logger at the
    stderr pytest captured for that test; once that test ends the file is closed, and every
    later warning from a thread (a link's acquisition thread in a module fixture) printed
    "--- Logging error --- ValueError: I/O operation on closed file". Put the root logger back."""
    root = _logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
