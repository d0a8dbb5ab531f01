"""annotations: the RGB-D pipeline's annotation JSON (``fieldguard train-classes``) and its
class-model file (.npz, read at start by the rgbd pipeline).

The first byte picks the surface: even -> the bytes are an annotation file, loaded with
``rgbd_model.load_annotations`` and every region then rasterised with ``region_mask`` as
training does; odd -> the bytes are a model file, loaded with ``rgbd_model.load``. Refusals
must be RgbdModelError (a ConfigError)."""
from __future__ import annotations

from appliance import rgbd_model
from hal.errors import FieldguardError

from tests.fuzz.common import scratch_dir

_dir = None


def one_input(data: bytes) -> None:
    global _dir
    if _dir is None:
        _dir = scratch_dir("annotations")
    if not data:
        return
    if data[0] % 2 == 0:
        p = _dir / "annotations.json"
        p.write_bytes(data[1:])
        try:
            doc = rgbd_model.load_annotations(p)
            for regions in doc["frames"].values():
                for region in regions:
                    m = rgbd_model.region_mask((12, 16), region)
                    assert m.shape == (12, 16)
        except FieldguardError:
            pass
    else:
        p = _dir / "model.npz"
        p.write_bytes(data[1:])
        try:
            rgbd_model.load(p)
        except FieldguardError:
            pass
