"""[perception.stereo-novelty] obstacle_margin_ref_px: the obstacle-mask feedback's margin in
pixels of an image of a set width (docs/front-end.md "The feedback margin")."""
import numpy as np
import pytest

from appliance.config import ConfigError, parse_config, pipeline_options
from appliance.perception.novelty import obstacle_cells
from appliance.perception.stereo_novelty import StereoNoveltyConfig, StereoNoveltyPipeline


def _pipe(**opts):
    from dataclasses import replace
    return StereoNoveltyPipeline(replace(StereoNoveltyConfig(), model_state="off", **opts),
                                 background=False)


def _block(margin_px: float, cell_px: int = 16) -> int:
    """Cells each way that one obstacle pixel keeps out of the update."""
    centre = np.array([[20.5 * cell_px, 16.5 * cell_px]])     # the middle of a 40x32 grid
    m = obstacle_cells(centre, (32, 40), cell_px, margin_px)
    rows = np.flatnonzero(m.any(axis=1))
    return (len(rows) - 1) // 2


def test_the_default_is_the_camera_s_own_pixels():
    assert StereoNoveltyConfig().obstacle_margin_ref_px == 0
    assert StereoNoveltyConfig().obstacle_margin_px == 64.0


@pytest.mark.parametrize("ref, width, kd, cells", [
    (0, 640, 1, 4),        # today: 64 px of a 640-px camera, 16-px cells
    (0, 1280, 2, 2),       # the paper's camera: 32 px of the 640-px descriptor image
    (1280, 640, 1, 2),     # given for 1280 px: the same 2 cells at 640 px
    (1280, 1280, 2, 2),
    (1280, 320, 1, 2),     # 8-px cells at 320 px: still 2
])
def test_the_margin_in_cells_each_way(ref, width, kd, cells):
    p = _pipe(obstacle_margin_ref_px=ref)
    try:
        cell = width // kd // 40                      # cell_px = 0: 40 cells across
        assert _block(p._margin_px(width, kd), cell) == cells
    finally:
        p.close()


def test_the_option_is_checked():
    cfg = parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                       "stereo-novelty": {"obstacle_margin_ref_px": 1280}}})
    assert pipeline_options(cfg, "stereo-novelty").obstacle_margin_ref_px == 1280
    for bad in (-1, "wide", 1.5):
        with pytest.raises(ConfigError) as e:
            parse_config({"perception": {"pipelines": ["stereo-novelty"],
                                         "stereo-novelty": {"obstacle_margin_ref_px": bad}}})
        assert "obstacle_margin_ref_px" in str(e.value)
