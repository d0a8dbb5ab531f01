"""runfolder: the files of a run folder (docs/run-format.md) that ``fieldguard eval`` and
``fieldguard run --replay`` read: run.toml, frames.csv, truth/NNNNNN.json, laser/NNNNNN.csv and
the PNG images.

The folder starts as a copy of tests/data/contract-example (small images added); the input's
first byte picks which file the rest of the input replaces (so every file is fuzzed with the
others valid). Then the folder is opened (``RunReader``) and every frame's vehicle state,
laser scan, truth, stereo pair and depth frame read. Refusals must be RunFormatError."""
from __future__ import annotations

import shutil

import numpy as np

from drivers.runfolder import RunReader
from hal.errors import FieldguardError

from tests.fuzz.common import ROOT, scratch_dir

FILES = ("run.toml", "frames.csv", "truth/000000.json", "laser/000000.csv",
         "stereo/left/000000.png", "rgbd/depth/000000.png", "rgbd/colour/000000.png")
_base = None


def _template():
    """The contract example with tiny cameras (so image files stay small) and images."""
    global _base
    if _base is not None:
        return _base
    import cv2
    d = scratch_dir("runfolder") / "template"
    if d.exists():
        shutil.rmtree(d)
    shutil.copytree(ROOT / "tests/data/contract-example", d)
    toml = (d / "run.toml").read_text()
    toml = (toml.replace("width = 1280", "width = 16").replace("height = 1024", "height = 8")
            .replace("width = 640", "width = 16").replace("height = 480", "height = 8"))
    (d / "run.toml").write_text(toml)
    for sub in ("stereo/left", "stereo/right", "rgbd/colour"):
        (d / sub).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(d / sub / "000000.png"), np.full((8, 16, 3), 90, np.uint8))
    (d / "rgbd/depth").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(d / "rgbd/depth/000000.png"), np.full((8, 16), 1500, np.uint16))
    _base = {f: (d / f).read_bytes() for f in FILES} | {
        "stereo/right/000000.png": (d / "stereo/right/000000.png").read_bytes()}
    return _base


def setup() -> None:
    _template()


def one_input(data: bytes) -> None:
    base = _template()
    run = scratch_dir("runfolder") / "run"
    if run.exists():
        shutil.rmtree(run)
    which = FILES[data[0] % len(FILES)] if data else FILES[0]
    for rel, content in base.items():
        p = run / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data[1:] if rel == which else content)
    try:
        r = RunReader(run)
    except FieldguardError:
        return
    for i in range(min(len(r), 4)):
        for read in (r.vehicle, r.laser, r.truth, r.stereo, r.rgbd):
            try:
                read(i)
            except FieldguardError:
                pass
