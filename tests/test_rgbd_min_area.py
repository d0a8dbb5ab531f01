"""``[perception.rgbd] min_area_m2``: an obstacle group's size in square metres, not pixels.
``min_pixels`` (30) is 2 x 2 cm of surface 1.4 m ahead and 7 x 7 cm at 4.5 m; a 35-pixel spot
of bush leaf that the colour model left unclassified, at the stop zone's edge 1.4 m ahead, held
a training greenhouse drive stopped for 11.6 s (docs/rgbd.md 'Small groups near the vehicle')."""
from __future__ import annotations

import numpy as np
import pytest

from appliance.perception.rgbd import (PAPER_RULE, RgbdPipelineConfig, metric_groups)

FX = FY = 525.0
APX = 1.0 / (FX * FY)


def _blob(mask, r0, c0, h, w):
    mask[r0:r0 + h, c0:c0 + w] = True


def test_groups_are_judged_by_their_size_in_square_metres():
    mask = np.zeros((120, 200), bool)
    depth = np.zeros((120, 200), np.float32)
    _blob(mask, 10, 10, 5, 7)          # 35 px at 1.45 m: 2.7 cm^2 ... 0.00027 m^2
    depth[10:15, 10:17] = 1.45
    _blob(mask, 10, 50, 5, 7)          # the same 35 px at 4.5 m: 0.0026 m^2
    depth[10:15, 50:57] = 4.5
    _blob(mask, 50, 10, 20, 20)        # 400 px at 1.45 m: 0.0031 m^2
    depth[50:70, 10:30] = 1.45
    _blob(mask, 50, 100, 6, 6)         # no depth at all: size unknown, kept
    out, n = metric_groups(mask, depth, APX, 0.002)
    assert n == 3
    assert not out[10:15, 10:17].any()                      # the near speck
    assert out[10:15, 50:57].all() and out[50:70, 10:30].all() and out[50:56, 100:106].all()
    # nothing else added, and the area uses the group's mean depth over pixels that have one
    assert not (out & ~mask).any()
    depth[50:60, 10:30] = 0.0                               # half the big group without depth
    out2, _ = metric_groups(mask, depth, APX, 0.002)
    assert out2[50:70, 10:30].all()


def test_all_kept_and_empty_masks():
    mask = np.zeros((40, 40), bool)
    depth = np.full((40, 40), 2.0, np.float32)
    out, n = metric_groups(mask, depth, APX, 0.002, 0)
    assert n == 0 and not out.any()
    _blob(mask, 0, 0, 30, 30)
    out, n = metric_groups(mask, depth, APX, 0.002)
    assert n == 1 and out is mask


def test_option_is_read_checked_and_off_in_the_papers_rule():
    from appliance.config import parse_config, pipeline_options
    from hal.errors import ConfigError
    cfg = parse_config({"perception": {"pipelines": ["rgbd"],
                                       "rgbd": {"min_area_m2": 0.002}}})
    assert pipeline_options(cfg, "rgbd").min_area_m2 == 0.002
    assert PAPER_RULE["min_area_m2"] == 0.0
    with pytest.raises(ConfigError) as e:
        parse_config({"perception": {"pipelines": ["rgbd"], "rgbd": {"min_area_m2": -1}}})
    assert "min_area_m2" in str(e.value)
    assert RgbdPipelineConfig().min_area_m2 >= 0.0
