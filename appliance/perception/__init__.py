"""Perception pipelines: pure code, arrays in, obstacle points out, no I/O.

Every pipeline registers under a stable name (``laser``, ``stereo``, ``stereo-novelty``,
``rgbd``; ``fused`` runs every configured pipeline the inputs allow) and declares the sensors it
needs. The same code runs on live frames, recordings and simulated scenes.
"""
from __future__ import annotations

import importlib

from hal.errors import ConfigError

from .base import Candidate, Detections, Pipeline, SensorInputs

# name -> "module:Class"; imported lazily so a missing optional dependency of one pipeline
# does not stop the others.
_PIPELINES: dict[str, str] = {
    "laser": "appliance.perception.laser:LaserPipeline",
    "rgbd": "appliance.perception.rgbd:RgbdPipeline",
    "stereo": "appliance.perception.stereo:StereoPipeline",
    "stereo-novelty": "appliance.perception.stereo_novelty:StereoNoveltyPipeline",
}


def register_pipeline(name: str, target: str) -> None:
    _PIPELINES[name] = target


def known_pipelines() -> list[str]:
    return sorted(_PIPELINES) + ["fused"]


def pipeline_class(name: str):
    try:
        target = _PIPELINES[name]
    except KeyError:
        raise ConfigError(f"unknown pipeline {name!r}; known: {', '.join(known_pipelines())}",
                          key="perception.pipelines") from None
    mod, _, attr = target.partition(":")
    return getattr(importlib.import_module(mod), attr)


def pipeline_config_class(name: str):
    """The options dataclass of a pipeline (``[perception.NAME]``), None if unknown."""
    if name not in _PIPELINES:
        return None
    return getattr(pipeline_class(name), "config_class", None)


def pipeline_options(cfg, name: str):
    """The options dataclass of pipeline ``name`` in an appliance config (``cfg.perception``:
    ``laser`` and the ``extra`` tables); its defaults when ``cfg`` is None or has no table.
    Perception never imports the appliance config (config imports this registry)."""
    per = getattr(cfg, "perception", None)
    if per is not None:
        if name == "laser":
            return per.laser
        if name in per.extra:
            return per.extra[name]
    cls = pipeline_config_class(name)
    return cls() if cls is not None else None


def make_pipeline(name: str, config=None) -> Pipeline:
    """Build pipeline ``name`` from the appliance config (its defaults when None; ``fused``
    over the config's pipelines, the laser alone without one)."""
    if name == "fused":
        from .fused import FusedPipeline
        names = config.perception.pipelines if config is not None else ("laser",)
        return FusedPipeline([make_pipeline(n, config) for n in names if n != "fused"])
    cls = pipeline_class(name)
    return cls(pipeline_options(config, name))


__all__ = ["Candidate", "Detections", "Pipeline", "SensorInputs", "make_pipeline", "known_pipelines",
           "register_pipeline", "pipeline_config_class", "pipeline_options"]
