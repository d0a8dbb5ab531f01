"""A few seconds of every fuzz target (tests/fuzz/): every seed and every input that once
crashed (corpus/TARGET/regress-*), a fixed sample of the coverage finds, then seeded random
mutations of them, each input under a time limit. Any exception outside the project's error
family, or a hang, fails with the input written to tests/fuzz/crashes/ (the long,
coverage-guided runs are tools/fuzz.sh TARGET MINUTES; figures in docs/reliability.md)."""
import importlib
import itertools
import random
import time

import pytest

from tests.fuzz.common import TARGETS, corpus_files, mutations, quiet_logs, time_limit

SECONDS = 1.5          # of mutations per target, after the corpus
LIMIT_S = 10.0         # one input (the status target's snapshot takes ~0.1 s)
SAMPLE = 25            # coverage finds replayed per target (seeds and regress-* always all)


def _crash(target: str, data: bytes) -> str:
    from tests.fuzz.common import ROOT
    d = ROOT / "tests" / "fuzz" / "crashes"
    d.mkdir(exist_ok=True)
    import hashlib
    p = d / f"{target}-{hashlib.sha1(data).hexdigest()[:12]}"
    p.write_bytes(data)
    return str(p)


@pytest.mark.parametrize("target", list(TARGETS))
def test_fuzz_target_short(target):
    with quiet_logs():
        _short_run(target)


def _short_run(target):
    mod = importlib.import_module("tests.fuzz." + TARGETS[target])
    if hasattr(mod, "setup"):
        mod.setup()
    files = corpus_files(target)
    fixed = [p for p in files if p.name.startswith(("seed-", "regress-"))]
    finds = [p for p in files if p not in fixed]
    finds = random.Random(target).sample(finds, min(SAMPLE, len(finds)))
    seeds = [p.read_bytes() for p in fixed + finds]
    assert fixed, f"no seeds for {target} (tests/fuzz/corpus/{target}/seed-*)"
    n = 0
    end = None
    for data in itertools.chain(seeds, mutations(seeds, 10**6, seed=sum(map(ord, target)))):
        if n == len(seeds):
            end = time.monotonic() + SECONDS
        elif end is not None and time.monotonic() > end:
            break
        try:
            with time_limit(LIMIT_S):
                mod.one_input(data)
        except BaseException as exc:
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            pytest.fail(f"{target}: {type(exc).__name__}: {exc} on input {data[:80]!r}... "
                        f"(saved as {_crash(target, data)}; replay: .venv/bin/python -m "
                        f"tests.fuzz.run {target} FILE)")
        n += 1
    assert n > len(seeds)
