"""Coverage-guided run of one target under atheris (libFuzzer): ``python -m tests.fuzz.run
TARGET [libFuzzer options] [CORPUS_DIR ...]``. tools/fuzz.sh is the usual way in."""
from __future__ import annotations

import importlib
import os
import sys

from tests.fuzz.common import ROOT, TARGETS, quiet_logs


def main() -> None:
    import atheris
    if len(sys.argv) < 2 or sys.argv[1] not in TARGETS:
        sys.exit(f"usage: python -m tests.fuzz.run TARGET [libFuzzer args]; targets: "
                 f"{' '.join(TARGETS)}")
    name = sys.argv[1]
    mod_name = "tests.fuzz." + TARGETS[name]
    # instrument the project's own code (and the target's extra third-party parsers) for
    # coverage feedback; everything else runs uninstrumented
    extra = importlib.import_module("tests.fuzz.instrument").EXTRA.get(name, [])
    # (every target imports the code it feeds at module level; setup(), which builds what a
    # target needs and may import more of it, runs inside the block too)
    # the simulator (drivers.sim) reads no outside bytes, and numba cannot compile its
    # renderer once atheris has rewritten the bytecode
    sim = ["drivers.sim"] + ["drivers.sim." + p.stem for p in
                             (ROOT / "drivers" / "sim").glob("*.py") if p.stem != "__init__"]
    with atheris.instrument_imports(include=["hal", "drivers", "appliance", *extra],
                                    exclude=sim):        # exact module names
        mod = importlib.import_module(mod_name)
        if hasattr(mod, "setup"):
            mod.setup()
    # libFuzzer's -merge runs argv[0] again: tools/fuzz.sh points it at an executable wrapper
    argv0 = os.environ.get("FUZZ_ARGV0") or sys.argv[0]
    atheris.Setup([argv0] + sys.argv[2:], mod.one_input)
    with quiet_logs():
        atheris.Fuzz()


if __name__ == "__main__":
    main()
