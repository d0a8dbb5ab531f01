"""``fieldguard novelty`` on real photographs (scikit-image textures, Middlebury Aloe)."""
from pathlib import Path

import cv2
import numpy as np

from appliance.cli import main

REAL = Path(__file__).parent / "data" / "real"


def test_novelty_tool_learns_a_field_and_marks_what_is_new(tmp_path, capsys):
    grass = cv2.imread(str(REAL / "textures" / "grass.png"))
    brick = cv2.imread(str(REAL / "textures" / "brick.png"))
    red = (brick * np.array([0.4, 0.6, 1.0])).astype(np.uint8)       # a reddish object
    inp = tmp_path / "in"
    inp.mkdir()
    clear = np.ascontiguousarray(grass[:, ::-1])                       # the same field, mirrored
    scene = clear.copy()
    scene[96:256, 320:480] = red[96:256, 320:480]
    cv2.imwrite(str(inp / "a_clear.png"), clear)
    cv2.imwrite(str(inp / "b_object.png"), scene)
    aloe = REAL / "middlebury_aloe" / "aloeL.jpg"                     # any size: 1282x1110
    out = tmp_path / "out"
    rc = main(["novelty", str(inp), str(aloe), "--learn",
               str(REAL / "textures" / "grass.png"), "--out", str(out)])
    assert rc == 0
    assert "wrote 3" in capsys.readouterr().out
    for name in ("a_clear", "b_object", "aloeL"):
        for suffix in ("novelty.npy", "mask.png", "overlay.png"):
            assert (out / f"{name}.{suffix}").is_file()
    s_clear = np.load(out / "a_clear.novelty.npy")
    s_obj = np.load(out / "b_object.novelty.npy")
    assert s_clear.shape == s_obj.shape == (16, 16) and s_obj.dtype == np.float32
    m_obj = cv2.imread(str(out / "b_object.mask.png"), cv2.IMREAD_GRAYSCALE)
    m_clear = cv2.imread(str(out / "a_clear.mask.png"), cv2.IMREAD_GRAYSCALE)
    assert m_obj.shape == grass.shape[:2]
    assert (m_obj[96:256, 320:480] == 255).mean() > 0.9                 # the object is novel
    outside = np.ones(m_obj.shape, bool)
    outside[64:288, 288:512] = False                                    # object + dilation
    assert (m_obj[outside] == 255).mean() < 0.05 and (m_clear == 255).mean() < 0.05
    assert np.median(s_obj[3:8, 10:15]) > np.median(s_clear[3:8, 10:15]) + 1.0
    # a photograph of a different scene is mostly novel against a grass model; grid follows size
    s_aloe = np.load(out / "aloeL.novelty.npy")
    assert s_aloe.shape == (1110 // 32, 1282 // 32)
    m_aloe = cv2.imread(str(out / "aloeL.mask.png"), cv2.IMREAD_GRAYSCALE)
    assert m_aloe.shape == (1110, 1282) and (m_aloe == 255).mean() > 0.5


def test_novelty_tool_reports_a_missing_input(tmp_path, capsys):
    rc = main(["novelty", str(tmp_path / "nope.png"), "--out", str(tmp_path / "o")])
    assert rc != 0
    assert "no such file" in capsys.readouterr().err
