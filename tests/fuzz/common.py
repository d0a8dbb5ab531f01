"""What every fuzz target shares.

A target is a module ``tests/fuzz/fuzz_<name>.py`` with ``one_input(data: bytes) -> None``: the
bytes go into the project's code the way outside bytes reach it on the box. ``one_input``
returns normally when the code either accepted the input or refused it with an error of the
project's family (:class:`hal.errors.FieldguardError`, or the documented error of a parser
that the driver turns into a fault, e.g. ValueError from ``strobe_serial.parse_line``). Anything
else escaping is a defect, and so is a hang (libFuzzer's ``-timeout``; :func:`replay` here) or
memory without bound (libFuzzer's ``-rss_limit_mb``).

Long runs: ``tools/fuzz.sh TARGET MINUTES`` (atheris, coverage-guided, see tests/fuzz/run.py).
Short runs in the suite: tests/test_fuzz_short.py (the committed corpus plus seeded random
mutations of it, :func:`mutations`).
"""
from __future__ import annotations

import os
import random
import signal
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CORPUS = Path(__file__).resolve().parent / "corpus"

#: target name (as tools/fuzz.sh takes it) -> module name in tests.fuzz
TARGETS = {
    "cola": "fuzz_cola",
    "strobe": "fuzz_strobe",
    "mavlink": "fuzz_mavlink",
    "j1939": "fuzz_j1939",
    "runfolder": "fuzz_runfolder",
    "config": "fuzz_config",
    "annotations": "fuzz_annotations",
    "cue-model": "fuzz_cue_model",
    "status": "fuzz_status",
    "console": "fuzz_console",
}


class Hang(Exception):
    """One input ran longer than its time limit."""


@contextmanager
def time_limit(seconds: float):
    """Raise :class:`Hang` in the main thread if the block runs longer than ``seconds``."""
    def on_alarm(*_):
        raise Hang(f"one input ran longer than {seconds} s")
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def scratch_dir(name: str) -> Path:
    """A per-process scratch folder for targets that must write a file (RAM-backed if it can)."""
    base = Path("/dev/shm") if os.access("/dev/shm", os.W_OK) else Path(tempfile.gettempdir())
    d = base / f"fieldguard-fuzz-{name}-{os.getpid()}"
    d.mkdir(parents=True, exist_ok=True)
    return d


def corpus_files(target: str) -> list[Path]:
    d = CORPUS / target
    return sorted(p for p in d.iterdir() if p.is_file()) if d.is_dir() else []


def mutations(seeds: list[bytes], n: int, seed: int = 0, max_len: int = 1 << 16):
    """``n`` inputs made from ``seeds`` by a fixed-seed random mutator (byte flips, inserts of
    interesting bytes, deletions, duplications, splices of two seeds): deterministic, for the
    short runs in the suite. The coverage-guided search is libFuzzer's, in the long runs."""
    rng = random.Random(seed)
    seeds = [s for s in seeds] or [b""]
    interesting = [b"\x00", b"\xff", b"\x02", b"\x03", b"\n", b"\r", b"*", b" ", b"=",
                   b"-1", b"0", b"1e309", b"nan", b"NaN", b"inf", b"9" * 24, b"\"", b"[", b"{",
                   b"\x80", b"\xfd", b"\xfe"]
    for _ in range(n):
        data = bytearray(rng.choice(seeds))
        for _ in range(rng.randint(1, 8)):
            op = rng.randrange(6)
            pos = rng.randint(0, len(data))
            if op == 0 and data:
                data[min(pos, len(data) - 1)] ^= 1 << rng.randrange(8)
            elif op == 1:
                data[pos:pos] = rng.choice(interesting)
            elif op == 2 and data:
                del data[pos:pos + rng.randint(1, 16)]
            elif op == 3 and data:
                a = rng.randint(0, len(data) - 1)
                data[pos:pos] = data[a:a + rng.randint(1, 64)]
            elif op == 4:
                other = rng.choice(seeds)
                cut = rng.randint(0, len(other))
                data = data[:pos] + bytearray(other[cut:])
            elif op == 5 and data:
                data[min(pos, len(data) - 1)] = rng.randrange(256)
        yield bytes(data[:max_len])


@contextmanager
def quiet_logs():
    """Every refused input is a logged fault on the box; fuzzing, that is millions of lines.
    (Only while fuzzing: set at import, it silenced other tests' log assertions.)"""
    import logging
    lg = logging.getLogger("fieldguard")
    old = lg.level
    lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        lg.setLevel(old)
