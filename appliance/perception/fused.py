from __future__ import annotations

import numpy as np

from .base import Detections, Pipeline, SensorInputs


class FusedPipeline(Pipeline):
    """Every configured pipeline whose sensors the inputs have; their points together, and
    their candidates together (each candidate names the pipeline that made it)."""

    name = "fused"

    def __init__(self, parts: list[Pipeline]):
        super().__init__(None)
        self.parts = parts
        # a fused run needs whatever at least one part can run on
        self.requires = ()

    def process(self, inputs: SensorInputs) -> Detections:
        pts, debug, ran, cands = [], {}, [], []
        for p in self.parts:
            if p.missing(inputs):
                continue
            d = p.process(inputs)
            pts.append(d.points_xy)
            cands.extend(d.candidates)            # each names its pipeline
            debug[p.name] = d.debug
            ran.append(p.name)
        debug["ran"] = ran
        if not pts:
            return Detections(debug=debug)
        return Detections(points_xy=np.concatenate(pts).astype(np.float32), debug=debug,
                          candidates=tuple(cands))

    def notes(self) -> dict:
        return {p.name: n for p in self.parts if (n := p.notes())}

    def close(self):
        for p in self.parts:
            p.close()
