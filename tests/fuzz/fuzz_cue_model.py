"""cue-model: the learned cue's ONNX file (``cue_model`` in a config, or the shipped one) and
its metadata, read by ``CueModel`` at start.

Two ways in, picked by the first byte. Raw (even): the rest of the input is the file, parsed
by onnxruntime and validated. Metadata (odd): the shipped stubble model with its metadata
replaced by the input (key/value pairs separated by NUL and ``=``; keys may be dropped,
repeated, empty or anything), so the fuzzer works on the validation rather than on getting
past protobuf. A model that loads must score a (3, n_features) array into three
probabilities. Refusals must be CueModelError (a ConfigError)."""
from __future__ import annotations

import numpy as np

from appliance.cue_model import CueModel
from hal.errors import FieldguardError

from tests.fuzz.common import ROOT, scratch_dir

_dir = None
_base = None


def _template():
    global _base
    if _base is None:
        import onnx
        _base = onnx.load(str(ROOT / "appliance/models/cue-stubble.onnx"))
    return _base


def setup() -> None:
    """The one-time costs (importing onnx, the first onnxruntime session) before any input."""
    global _dir
    _dir = scratch_dir("cue-model")
    _template()
    CueModel(ROOT / "appliance/models/cue-stubble.onnx")


def _with_metadata(data: bytes) -> bytes:
    import onnx
    m = onnx.ModelProto()
    m.CopyFrom(_template())
    del m.metadata_props[:]
    for item in data.split(b"\0"):
        k, _, v = item.partition(b"=")
        p = m.metadata_props.add()
        p.key = k.decode("utf-8", "replace")
        p.value = v.decode("utf-8", "replace")
    return m.SerializeToString()


def one_input(data: bytes) -> None:
    global _dir
    if _dir is None:
        _dir = scratch_dir("cue-model")
    if not data:
        return
    body = data[1:] if data[0] % 2 == 0 else _with_metadata(data[1:])
    p = _dir / "cue.onnx"
    p.write_bytes(body)
    try:
        model = CueModel(p)
    except FieldguardError:
        return
    try:
        s = model.score(np.zeros((3, model.info.n_features), np.float32))
    except FieldguardError:
        return
    assert s.shape == (3,)
