"""tools/low_cell_probe.py: the low points' cells of a head-on dog against the field's."""
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import low_cell_probe  # noqa: E402


def test_a_head_on_dogs_cells_and_the_fields_are_told_apart_and_summarised():
    rows = low_cell_probe.cells_of("stubble-thin", 95, dogs=1, start_m=5.0)
    A = np.array([r[1:] for r in rows], float)
    col = {n: A[:, i] for i, n in enumerate(low_cell_probe.COLUMNS[1:])}
    dog, field = col["is_dog"] == 1, col["is_dog"] == 0
    assert dog.any() and field.any()
    assert set(np.unique(col["dist"] < 5.0)) == {True}            # only from 5 m in
    assert ((col["support"] >= 0) & (col["support"] <= 1)).all()
    # the dog's face stands on the ground (seed 95, 0.45 m high, sparse stubble): its cells
    # carry vertical support where the field's low points mostly do not
    assert np.median(col["support"][dog]) > np.median(col["support"][field]) + 0.2
    text = low_cell_probe.summary(rows)
    assert text.splitlines()[0].endswith("frames; quantiles p10 / p50 / p90 / p99:")
    assert sum("support >= " in line for line in text.splitlines()) == len(low_cell_probe.RULES)


def test_acceptance_seeds_are_refused():
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "low_cell_probe.py"),
                        "stubble-thin", "1038"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "training seeds only" in r.stderr
