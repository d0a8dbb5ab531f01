"""tools/bench_gl.py (the GL-rasteriser measurement of issue #13; moderngl is an optional extra):
a clear one-line exit 2 without moderngl, and a tiny render whose z-depth is the geometry's."""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_without_moderngl_exits_2_with_one_line():
    code = ("import sys; sys.modules['moderngl'] = None; sys.path.insert(0, %r); "
            "from tools.bench_gl import main; raise SystemExit(main(['--no-numba', '--cpu', '-1']))"
            % str(ROOT))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "moderngl is not installed" in lines[0]


def test_tuft_mesh_is_a_closed_fan_of_the_profile():
    from tools.bench_gl import tuft_mesh
    V, I = tuft_mesh(8, 2)
    assert len(I) // 3 == 24 and I.max() == len(V) - 1
    assert V[0, 2] == 1.0 and np.allclose(V[-8:, 2], 0.0)     # apex up, last ring on the ground


def test_gl_z_depth_of_a_flat_quad_is_exact():
    moderngl = pytest.importorskip("moderngl", reason="moderngl (optional extra 'gl') not installed")
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as e:                                     # noqa: BLE001
        pytest.skip(f"no headless EGL context: {e}")
    from hal.types import PinholeCalibration
    from tools.bench_gl import make_program
    prog = make_program(ctx, 4)                                # the bare ground: colour + z
    # a level camera 1.5 m above flat ground z = 0, looking along world x
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])   # optical -> world
    cam = PinholeCalibration(64, 48, 50.0, 50.0, 31.5, 23.5)
    quad = np.array([[0, -50, 0, 0, 0, 1], [100, -50, 0, 0, 0, 1], [100, 50, 0, 0, 0, 1],
                     [0, 50, 0, 0, 0, 1]], np.float32)
    vao = ctx.vertex_array(prog, [(ctx.buffer(quad.tobytes()), "3f 12x", "in_pos")],
                           index_buffer=ctx.buffer(np.array([0, 1, 2, 0, 2, 3], np.int32).tobytes()))
    fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((64, 48), 4),
                                             ctx.renderbuffer((64, 48), 1, dtype="f4")],
                          depth_attachment=ctx.depth_renderbuffer((64, 48)))
    fbo.use()
    fbo.clear(0, 0, 0, 0, depth=1.0)
    prog["Rt"].write(np.ascontiguousarray(R, np.float32).tobytes())
    prog["Crel"].value = (0.0, 0.0, 1.5)
    prog["K"].value = (50.0, 50.0, 32.0, 24.0)
    prog["WH"].value = (64, 48)
    prog["NF"].value = (0.2, 80.0)
    vao.render()
    z = np.frombuffer(fbo.read(components=1, attachment=1, dtype="f4"), np.float32)
    z = z.reshape(48, 64)[::-1]
    # row v sees the ground at z = fy * 1.5 / (v - cy)
    for v in (30, 40, 47):
        assert z[v, 32] == pytest.approx(50.0 * 1.5 / (v - 23.5), rel=1e-4)
    assert np.all(z[:23] == 0.0)                               # above the horizon: sky
    assert math.isfinite(float(z.max()))
