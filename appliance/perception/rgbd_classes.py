"""The trained class model of the RGB-D pipeline (pure data + the training maths).

One model holds, for each class (e.g. bush, pepper, ground, cover), a Gaussian mixture in each of
the five colour spaces and a normalised 256-bin LBP histogram, so the colour space is a run-time
choice. File I/O (the versioned model file) lives in appliance/rgbd_model.py.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .rgbd_colour import COLOUR_SPACES, GaussianMixture, colour_features, fit_mixture
from .rgbd_texture import normalised_histogram


@dataclass(frozen=True)
class RgbdClassModel:
    classes: tuple[str, ...]
    colour: dict            # space -> tuple[GaussianMixture, ...] (one per class, same order)
    lbp: np.ndarray         # (C, 256) float64 normalised LBP histograms
    meta: dict = field(default_factory=dict)

    def index(self, names) -> list[int]:
        """Class indices of the given names (unknown names are ignored: a config may list a
        traversable class a given model does not have)."""
        return [self.classes.index(n) for n in names if n in self.classes]

    def mixtures(self, space: str) -> list[GaussianMixture]:
        if space not in self.colour:
            raise KeyError(f"model has no colour space {space!r} (has {', '.join(self.colour)})")
        return list(self.colour[space])


def train_model(samples: dict[str, list[tuple[np.ndarray, np.ndarray]]], components: int = 1,
                ridge: float = 1.0, meta: dict | None = None) -> RgbdClassModel:
    """``samples``: class -> list of (bgr pixels (N, 3) uint8, LBP codes (N,) uint8) per
    annotated region. Colour: mean + covariance per class per colour space (``components`` > 1:
    a mixture by EM). Texture: the normalised LBP histogram of all the class's pixels."""
    classes = tuple(samples)
    if not classes:
        raise ValueError("no annotated classes")
    colour = {}
    pix = {}
    for c in classes:
        if not samples[c]:
            raise ValueError(f"class {c!r} has no annotated pixels")
        pix[c] = np.concatenate([p.reshape(-1, 3) for p, _ in samples[c]])
    for space in COLOUR_SPACES:
        colour[space] = tuple(fit_mixture(colour_features(pix[c], space), components, ridge)
                              for c in classes)
    lbp = np.stack([normalised_histogram(np.concatenate([k.ravel() for _, k in samples[c]]))
                    for c in classes])
    m = dict(meta or {})
    m.setdefault("pixels", {c: int(pix[c].shape[0]) for c in classes})
    m.setdefault("components", int(components))
    m.setdefault("ridge", float(ridge))
    return RgbdClassModel(classes, colour, lbp, m)
