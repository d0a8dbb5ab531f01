"""The learned cue's model file (ONNX) and its inference with onnxruntime (issue #8).

A cue model is an ONNX graph written by ``fieldguard train-cue`` (appliance.cue_train):

    input   "features"       float32 [N, F]   F = the number of features of its feature set
    output  "probabilities"  float32 [N, 2]   column 1 = P(obstacle-like) per cell
    metadata (ONNX metadata_props, all strings):
        fieldguard_cue_version   "1"   (a reader refuses any other)
        feature_set              "fieldguard-cell-v2" (images; 59 features) or
                                 "fieldguard-cell-depth-v2" (RGB-D; 65), see
                                 appliance.perception.cue_features
        n_features               "59" / "65"
        cell_px                  cell size the features were computed on, at image width
        image_width_px           ... of this many pixels (the cue rescales to it)
        threshold                P above which a cell is obstacle-like (chosen at training)
        domain                   "stereo" | "rgbd"
        trained_on               JSON: runs, frames, cells, positives per class

Every way a file can be wrong is a :class:`CueModelError` naming the file and what was
expected. The box needs only onnxruntime and numpy for this; training needs the ``train``
extra (scikit-learn, skl2onnx).
"""
from __future__ import annotations

import json
import logging
import os
from contextlib import ExitStack
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from appliance.perception.cue_features import DEPTH_FEATURE_SET, FEATURE_SETS
from hal.errors import ConfigError

log = logging.getLogger("fieldguard.cue")

VERSION = "1"
INPUT_NAME = "features"
OUTPUT_NAME = "probabilities"
DOMAINS = ("stereo", "rgbd")
# shipped models (package data, appliance/models/): one per domain
SHIPPED = {"stereo": "models/cue-stubble.onnx", "rgbd": "models/cue-greenhouse.onnx"}
_REQUIRED_META = ("fieldguard_cue_version", "feature_set", "n_features", "cell_px",
                  "image_width_px", "threshold", "domain")
_RESOURCES = ExitStack()


class CueModelError(ConfigError):
    """A cue model file that is missing, corrupt, of the wrong shape or of an unknown version."""


def shipped_model_path(domain: str) -> Path:
    """Filesystem path of the model shipped for ``domain`` (importlib.resources)."""
    if domain not in SHIPPED:
        raise CueModelError(f"no shipped cue model for {domain!r} (known: {', '.join(DOMAINS)})")
    ref = resources.files("appliance").joinpath(SHIPPED[domain])
    return _RESOURCES.enter_context(resources.as_file(ref))


@dataclass(frozen=True)
class CueModelInfo:
    path: str
    version: str
    feature_set: str
    n_features: int
    cell_px: int
    image_width_px: int
    threshold: float
    domain: str
    trained_on: dict


def _session_options(threads: int):
    import onnxruntime as ort
    so = ort.SessionOptions()
    # one thread, sequential: the cue must not fight the loop's own thread or the novelty
    # update thread for the two cores
    so.intra_op_num_threads = max(1, int(threads))
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.log_severity_level = 3
    return so


class CueModel:
    """A loaded, validated cue model. ``score(features)`` -> P(obstacle-like) per row."""

    def __init__(self, path: str | os.PathLike, threads: int = 1):
        p = Path(path)
        self.path = str(p)
        if not p.is_file():
            raise CueModelError("cue model file not found (expected an ONNX model written "
                                "by `fieldguard train-cue`)", file=self.path)
        try:
            import onnxruntime as ort
        except ImportError as exc:          # pragma: no cover - a dependency of the package
            raise CueModelError(f"onnxruntime is not installed ({exc})", file=self.path)
        try:
            data = p.read_bytes()
            self._session = ort.InferenceSession(data, sess_options=_session_options(threads),
                                                 providers=["CPUExecutionProvider"])
        except OSError as exc:
            raise CueModelError(f"cannot read: {exc.strerror}", file=self.path)
        except Exception as exc:
            first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
            raise CueModelError(f"not a valid ONNX model ({type(exc).__name__}: {first}); "
                                "expected a file written by `fieldguard train-cue`",
                                file=self.path) from None
        self.info = self._validate()

    # ---- validation: every departure names the file and what was expected --------------------
    def _validate(self) -> CueModelInfo:
        fail = lambda msg: CueModelError(msg, file=self.path)  # noqa: E731
        try:
            meta = dict(self._session.get_modelmeta().custom_metadata_map or {})
        except UnicodeDecodeError:          # found by tests/fuzz/fuzz_cue_model.py
            raise fail("its metadata is not UTF-8 text (expected a file written by "
                       "`fieldguard train-cue`)") from None
        if "fieldguard_cue_version" not in meta:
            raise fail("not a fieldguard cue model: its metadata has no fieldguard_cue_version "
                       "(expected a file written by `fieldguard train-cue`)")
        if meta["fieldguard_cue_version"] != VERSION:
            raise fail(f"cue model version {meta['fieldguard_cue_version']!r}; this fieldguard "
                       f"reads version {VERSION!r} (retrain with `fieldguard train-cue`)")
        missing = [k for k in _REQUIRED_META if k not in meta]
        if missing:
            raise fail(f"metadata lacks {', '.join(missing)}")
        if meta["feature_set"] not in FEATURE_SETS:
            raise fail(f"trained on features {meta['feature_set']!r}; this fieldguard computes "
                       f"{' or '.join(map(repr, FEATURE_SETS))} (retrain with "
                       "`fieldguard train-cue`)")
        n_expected = len(FEATURE_SETS[meta["feature_set"]])
        try:
            n_features = int(meta["n_features"])
            cell_px = int(meta["cell_px"])
            width = int(meta["image_width_px"])
            threshold = float(meta["threshold"])
        except ValueError as exc:
            raise fail(f"bad metadata value: {exc}")
        if n_features != n_expected:
            raise fail(f"metadata says {n_features} features; {meta['feature_set']} has "
                       f"{n_expected}")
        if not 4 <= cell_px <= 512 or width < cell_px or not 0.0 < threshold < 1.0:
            raise fail(f"metadata out of range: cell_px={cell_px}, image_width_px={width}, "
                       f"threshold={threshold} (expected 4..512, >= cell_px, 0..1)")
        if meta["domain"] not in DOMAINS:
            raise fail(f"domain {meta['domain']!r}; expected one of {', '.join(DOMAINS)}")
        ins = self._session.get_inputs()
        if len(ins) != 1 or ins[0].name != INPUT_NAME:
            raise fail(f"inputs {[i.name for i in ins]}; expected one input {INPUT_NAME!r}")
        shape = ins[0].shape
        if ins[0].type != "tensor(float)" or len(shape) != 2 or shape[1] != n_expected:
            raise fail(f"input {INPUT_NAME!r} is {ins[0].type} of shape {shape}; expected "
                       f"float32 of shape [N, {n_expected}]")
        outs = {o.name: o for o in self._session.get_outputs()}
        if OUTPUT_NAME not in outs:
            raise fail(f"outputs {sorted(outs)}; expected an output {OUTPUT_NAME!r}")
        oshape = outs[OUTPUT_NAME].shape
        if len(oshape) != 2 or oshape[1] != 2:
            raise fail(f"output {OUTPUT_NAME!r} has shape {oshape}; expected [N, 2]")
        try:
            trained = json.loads(meta.get("trained_on", "{}"))
        except ValueError:
            trained = {}
        return CueModelInfo(self.path, meta["fieldguard_cue_version"], meta["feature_set"],
                            n_features, cell_px, width, threshold, meta["domain"], trained)

    # ---- inference --------------------------------------------------------------------------
    @property
    def uses_depth(self) -> bool:
        return self.info.feature_set == DEPTH_FEATURE_SET

    def score(self, features: np.ndarray) -> np.ndarray:
        """(N, F) float32 features -> (N,) float32 P(obstacle-like)."""
        x = np.ascontiguousarray(features.reshape(-1, self.info.n_features), np.float32)
        if len(x) == 0:
            return np.zeros(0, np.float32)
        out = self._session.run([OUTPUT_NAME], {INPUT_NAME: x})[0]
        return np.asarray(out, np.float32)[:, 1]


def load_cue_model(path: str | os.PathLike | None, domain: str, threads: int = 1) -> CueModel:
    """The model at ``path`` (empty or None: the one shipped for ``domain``), checked to be a
    ``domain`` model."""
    p = Path(path) if path else shipped_model_path(domain)
    m = CueModel(p, threads)
    if m.info.domain != domain:
        raise CueModelError(f"a {m.info.domain!r} cue model; this pipeline needs a {domain!r} "
                            "one", file=m.path)
    return m
