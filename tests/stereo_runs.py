"""Shared by tests that run the stereo-novelty pipeline over rendered frames (open loop)."""
from __future__ import annotations

import dataclasses

import numpy as np


def kept_points(frames, **opts):
    """For each ``(stereo, vehicle, truth)`` of ``frames``: the detections, the kept obstacle
    points' x, y (vehicle frame) and the truth, from one stereo-novelty pipeline with no saved
    model, an update every second frame and ``opts`` over its defaults."""
    from appliance.perception import SensorInputs
    from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline
    o = dataclasses.replace(StereoNoveltyConfig(), model_state="off", update_every_frames=2,
                            **opts)
    pipe = StereoNoveltyPipeline(o, background=False)
    try:
        for st, veh, truth in frames:
            det = pipe.process(SensorInputs(stamp_ns=st.stamp_ns, stereo=st, vehicle=veh))
            pts, _px, _h, keep, _k = pipe.last_points
            yield det, np.asarray(pts[keep, :2]), truth
    finally:
        pipe.close()
