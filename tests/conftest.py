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
