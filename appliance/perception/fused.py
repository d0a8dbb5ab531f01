from __future__ import annotations

import numpy as np

from .base import Detections, Pipeline, SensorInputs


class FusedPipeline(Pipeline):
    """Every configured pipeline whose sensors the inputs have; their points together."""

    name = "fused"

    def __init__(self, parts: list[Pipeline]):
        super().__init__(None)
        self.parts = parts
        # a fused run needs whatever at least one part can run on
        self.requires = ()

    def process(self, inputs: SensorInputs) -> Detections:
        pts, debug, ran = [], {}, []
        for p in self.parts:
            if p.missing(inputs):
                continue
            d = p.process(inputs)
            pts.append(d.points_xy)
            debug[p.name] = d.debug
            ran.append(p.name)
        debug["ran"] = ran
        if not pts:
            return Detections(debug=debug)
        return Detections(points_xy=np.concatenate(pts).astype(np.float32), debug=debug)

    def notes(self) -> dict:
        return {p.name: n for p in self.parts if (n := p.notes())}

    def close(self):
        for p in self.parts:
            p.close()
