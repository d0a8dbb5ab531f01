"""drivers/sim renderer paths: the compiled (numba) renderer against the numpy reference and
against the scene's own geometry on undulating ground with contour banks (the camera pitched and
rolled by the ground), walkers drawn where the truth says they are. Small images: seconds."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import drivers.sim.render as R
from drivers.sim import SimField
from drivers.sim.scenes import build_scene
from drivers.sim.world import MAT_OBSTACLE


@pytest.fixture
def engine():
    old = R.ENGINE
    yield
    R.ENGINE = old


def _view(f: SimField, cam, mount, engine_name: str, **kw):
    R.ENGINE = engine_name
    c, r, _ = f._sensor_pose(mount)
    return R.render_view(f.world, f.lighting, c, r, cam, **kw), c, r


def test_compiled_and_numpy_renderers_agree(engine):
    f = SimField("stubble-day", 0, sensors=("rgbd",))
    f.vehicle.s = 10.0
    cal = f.depth_calibration
    a, _, _ = _view(f, cal.camera, cal.mount, "numpy", t_max=60.0, t_min=0.2, rel_step=0.006,
                    min_step=0.008)
    b, _, _ = _view(f, cal.camera, cal.mount, "numba", t_max=60.0, t_min=0.2, rel_step=0.006,
                    min_step=0.008)
    both = (a.zdepth > 0) & (b.zdepth > 0)
    assert ((a.zdepth > 0) == (b.zdepth > 0)).mean() > 0.99      # same sky line
    assert both.mean() > 0.5
    rel = np.abs(a.zdepth[both] - b.zdepth[both]) / a.zdepth[both]
    assert np.median(rel) < 0.002 and np.percentile(rel, 95) < 0.05
    assert (a.mat == b.mat).mean() > 0.95
    # appearance: same materials, same colours up to float rounding and the ground grid
    d = np.abs(a.radiance - b.radiance)[a.mat == b.mat]
    assert np.median(d) < 0.01
    # laser: identical ranges (same heights, same schedule)
    g = SimField("stubble-day", 0, sensors=("laser",))
    g.vehicle.s = 10.0
    R.ENGINE = "numpy"
    ra = g.render_laser(0, 0).ranges_m
    R.ENGINE = "numba"
    rb = g.render_laser(0, 0).ranges_m
    assert np.array_equal(np.isfinite(ra), np.isfinite(rb))
    ok = np.isfinite(ra)
    assert ok.sum() > 10 and np.abs(ra[ok] - rb[ok]).max() < 1e-4


def _bare_bank_field():
    """A stubble-coverage field with a steep contour bank across lane 0, stubble removed (the
    ground alone is the truth), the vehicle on the bank's flank."""
    for seed in range(200):
        sc = build_scene("stubble-coverage", seed)
        for nx, ny, off, hb, sg in sc.world.banks:
            xb = off / nx
            if 20.0 < xb < 230.0 and hb * abs(nx) / sg > 0.15:
                f = SimField("stubble-coverage", seed, sensors=("stereo", "rgbd"),
                             stereo_scale=0.25)
                f.world.stubble_gap = 1.0              # no tufts: bare undulating ground
                f.world.obstacles[:] = []
                f.vehicle._footprints = []
                f.world._kp = None
                f.scene.bounce_deg = 0.0
                f.vehicle.s = float(xb - sg - 2.0)      # climbing the bank
                return f
    raise AssertionError("no steep bank in 200 seeds")


def _ray_ground(world, c, ray):
    """Distance along ``ray`` (unit z in the optical frame is not assumed) to the ground, by
    bisection on the world's own ground function."""
    ts = np.arange(0.0, 120.0, 0.02)
    p = c[None, :] + ts[:, None] * ray[None, :]
    above = p[:, 2] - world.ground(p[:, 0].astype(np.float32), p[:, 1].astype(np.float32)) > 0
    if above.all():
        return None
    i = int(np.argmin(above))                  # the FIRST sample under the ground
    lo, hi = float(ts[i - 1]), float(ts[i])
    g = lambda t: (c + t * ray)[2] - float(world.ground(np.float32((c + t * ray)[0]),  # noqa: E731
                                                        np.float32((c + t * ray)[1])))
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if g(mid) > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("which", ["stereo", "rgbd"])
def test_depth_on_undulating_ground_with_pitch_and_roll_matches_the_ground(engine, which):
    f = _bare_bank_field()
    roll, pitch, _ = f.vehicle.attitude()
    assert abs(pitch) > math.radians(2.0)                # the bank pitches the vehicle
    if which == "stereo":
        cal = f.stereo_calibration
        cam, mount = cal.camera, cal.mount
        kw = dict(t_max=80.0, rel_step=0.008)
    else:
        cal = f.depth_calibration
        cam, mount = cal.camera, cal.mount
        kw = dict(t_max=60.0, t_min=0.2, rel_step=0.006, min_step=0.008)
    v, c, r = _view(f, cam, mount, "numba", **kw)
    # the camera's attitude includes the ground's pitch and roll
    Rwv, _ = f.vehicle.world_from_vehicle()
    assert np.allclose(r, Rwv @ mount.camera_to_vehicle(), atol=1e-12)
    us = np.linspace(5, cam.width - 6, 9).astype(int)
    vs = np.linspace(cam.height * 0.45, cam.height - 6, 7).astype(int)
    errs = []
    for vv in vs:
        for uu in us:
            ray_opt = np.array([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, 1.0])
            t = _ray_ground(f.world, c, r @ ray_opt)     # ray_opt has unit z: t is z-depth
            if t is None or t > 40.0:
                continue
            z = float(v.zdepth[vv, uu])
            assert z > 0
            errs.append(abs(z - t) / t)
    errs = np.array(errs)
    assert len(errs) > 30
    assert np.median(errs) < 0.005 and errs.max() < 0.03, errs


def test_stereo_disparity_on_the_bank_matches_fx_b_over_z(engine):
    """Disparity of the bare undulating ground (textured) in a rendered pair against the
    scene's geometry, the vehicle pitched by the bank."""
    from tests.test_sim import _match_disparity
    f = _bare_bank_field()
    R.ENGINE = "numba"
    s = f.render_stereo(0, 0)
    cal = s.calib
    cam, B = cal.camera, cal.baseline_m
    c, r, _ = f._sensor_pose(cal.mount)
    checked = 0
    # rows 5-25 m ahead (nearer, the ground's slant across a window biases this simple block
    # matcher by px; the z-depth test above checks the near ground exactly)
    for vv in (int(cam.height * 0.62), int(cam.height * 0.7)):
        for uu in (int(cam.width * 0.45), int(cam.width * 0.6)):
            ray_opt = np.array([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, 1.0])
            z = _ray_ground(f.world, c, r @ ray_opt)
            d_expected = cam.fx * B / z
            # slanted ground: a flat window (the disparity changes from row to row)
            d = _match_disparity(s.left, s.right, uu, vv, half_w=10, half_h=1, d_max=120)
            assert d == pytest.approx(d_expected, abs=1.0), (uu, vv, d, d_expected)
            checked += 1
    assert checked == 4


def test_a_walker_is_drawn_where_the_truth_puts_it(engine):
    for seed in range(100):
        sc = build_scene("stubble-coverage", seed)
        w = [o for o in sc.obstacles if o.moving and o.cls == "person"]
        if w:
            break
    f = SimField("stubble-coverage", seed, sensors=("rgbd",))
    k = next(i for i, o in enumerate(f.world.obstacles) if o.id == w[0].id)
    o = f.world.obstacles[k]
    # walk it, then put the vehicle 4 m behind where it is now, looking at it
    f.vehicle.s = o.walk_trigger_s
    f.step(0.1)
    for _ in range(int(0.4 * o.walk_time_s * 10)):
        f.vehicle.speed = 0.0
        f.step(0.1)
    assert math.hypot(o.x - o.x_start, o.y - o.y_start) > 0.5     # it has moved
    f.vehicle.offset_m = 0.0
    f.vehicle.s = f.scene.route_s_of(o.x, o.y) - 5.0
    f.world.obstacles[:] = [o]
    f.vehicle._footprints = [f.vehicle._footprint_points(o)]
    t = f.truth()
    assert len(t) == 1 and "vx_mps" in t[0]
    Rwv, O = f.vehicle.world_from_vehicle()
    p = O + Rwv @ np.array([t[0]["x_m"], t[0]["y_m"], t[0]["z_m"] + 1.0])   # 1 m up its body
    cal = f.depth_calibration
    R.ENGINE = "numba"
    views = []
    f.render_rgbd(0, 0, view_out=views)
    c, r, _ = f._sensor_pose(cal.mount)
    q = r.T @ (p - c)
    u = int(round(cal.camera.fx * q[0] / q[2] + cal.camera.cx))
    v = int(round(cal.camera.fy * q[1] / q[2] + cal.camera.cy))
    assert 0 <= u < cal.camera.width and 0 <= v < cal.camera.height
    assert views[0].mat[v, u] == MAT_OBSTACLE + 0
    assert views[0].zdepth[v, u] == pytest.approx(q[2], abs=0.35)


def test_compiled_obstacle_shadows_and_laser_bound_match_the_reference(engine):
    """The compiled renderer culls obstacle shadows per column and the laser skips samples above
    the coarse max-ground grid: both must change nothing. Several obstacles cast long shadows
    (low sun ahead) towards the camera over the ground the RGB-D camera sees; where the numpy
    reference puts a shadow (its own _shadows on its own hit points) the compiled image is as
    dark, and the coarse grid bounds the ground everywhere."""
    f = SimField("stubble-coverage", 5, sensors=("rgbd",))
    f.vehicle.s = 20.0
    f.step(0.1)
    Rwv, O = f.vehicle.world_from_vehicle()
    fwd, left = Rwv[:, 0], Rwv[:, 1]
    del f.world.obstacles[1:]
    base = f.world.obstacles[0]
    obs = []
    for i, (ahead, side) in enumerate(((6.0, -0.6), (7.5, 0.9), (9.0, 0.0), (12.0, -1.5))):
        p = O[:2] + ahead * fwd[:2] + side * left[:2]
        o = type(base)(f"t{i}", "drum", "cylinder", float(p[0]), float(p[1]), 0.0, 0.6, 0.6,
                       1.2, (0.1, 0.4, 0.9))
        o.z0 = float(f.world.ground(np.float32(o.x), np.float32(o.y)))
        obs.append(o)
    f.world.obstacles[:] = obs
    f.world._kp = None
    sun = np.array([fwd[0], fwd[1], 0.0]) * math.cos(math.radians(18.0))
    sun[2] = math.sin(math.radians(18.0))
    f.lighting = R.Lighting("day", tuple(sun))
    cal = f.depth_calibration
    kw = dict(t_max=60.0, t_min=0.2, rel_step=0.006, min_step=0.008)
    a, c, r = _view(f, cal.camera, cal.mount, "numpy", **kw)
    b, _, _ = _view(f, cal.camera, cal.mount, "numba", **kw)
    cam = cal.camera
    vv, uu = np.nonzero((a.mat < MAT_OBSTACLE) & (a.mat >= 0) & (a.zdepth > 0))
    z = a.zdepth[vv, uu].astype(np.float64)
    rays = np.stack([(uu - cam.cx) / cam.fx * z, (vv - cam.cy) / cam.fy * z, z])
    P = c[:, None] + r @ rays
    lit = R._shadows(f.world, np.asarray(sun, np.float32), P[0].astype(np.float32),
                     P[1].astype(np.float32), P[2].astype(np.float32), a.mat[vv, uu])
    shadowed = lit == 0
    assert shadowed.sum() > 2000                      # the shadows are in the picture
    same = a.mat[vv, uu] == b.mat[vv, uu]
    la = a.radiance[vv, uu].sum(1)
    lb = b.radiance[vv, uu].sum(1)
    # in the reference's shadow the compiled image is dark too: sun-lit it would be ~1.5x as
    # bright (0.42 + 0.75 sin 18deg against 0.42); the two engines' hit points differ a little
    # (float32 vs float64, the point rebuilt here from the warped z-depth), so a few % of the
    # pixels at shadow edges and on tufts disagree (4a2ef3d, before the culling: 3.0 % / 0.17 %)
    ratio = lb / la
    assert (ratio[shadowed & same] > 1.3).mean() < 0.06
    assert (ratio[~shadowed & same] < 0.77).mean() < 0.01
    # the laser's bound: the coarse grid's node maximum is never under the ground
    kp = f.world.kernel_params()
    G, gp = f.world.ground_grid()
    rng = np.random.default_rng(3)
    x0, y0, x1, y1 = f.world.extent
    xs = rng.uniform(x0 - 5, x1 + 5, 20000)
    ys = rng.uniform(y0 - 5, y1 + 5, 20000)
    from drivers.sim import fastrender as fr
    bound = np.array([fr.coarse_max(kp["Gc"], gp, x, y) for x, y in zip(xs[:2000], ys[:2000])])
    assert np.all(f.world.ground(xs[:2000], ys[:2000]) <= bound + 1e-6)



_CORNER = """
import sys
sys.path.insert(0, {root!r})
import numpy as np
from drivers.sim import fastrender as fr
from drivers.sim.world import _noise_tile
tile = _noise_tile(0xC10D)
cell = 0.37
v = [fr.value_noise(tile, 511.5 * cell + k * 512 * cell, 511.5 * cell, cell) for k in (0, 1, -1)]
w = fr.value_noise_k(np.stack([tile, tile]), 1, 511.9 * cell, 511.9 * cell, cell)
import json
print(json.dumps([float(x) for x in v + [w]]))
"""


def test_the_compiled_value_noise_reads_inside_its_tile_and_the_same_every_run(tmp_path):
    """The compiled value noise at the tile's last lattice cell, with numba's bounds checks on
    (its own cache, so the check is compiled in): it read one float past the array's end there,
    whatever lay in memory, and the same drive rendered differently from run to run (twenty-
    fourth session, docs/proving-ground.md "Determinism"). Twice, the same values; and the
    value is the one the kernel's reads name on the padded tile."""
    import os
    import subprocess
    import sys
    root = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(tmp_path / "nb")}
    outs = []
    for _ in range(2):
        p = subprocess.run([sys.executable, "-c", _CORNER.format(root=root)], env=env,
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr[-1500:]
        outs.append(p.stdout.strip())
    assert outs[0] == outs[1]
    import json
    vals = json.loads(outs[0])
    from drivers.sim.world import _noise_tile
    tile = _noise_tile(0xC10D).astype(np.float64)
    assert len(tile) == 513 * 513 + 1
    i0 = 511 * 513 + 511                                    # the last cell, 0.5 into it
    v00, v10, v01, v11 = tile[i0], tile[i0 + 1], tile[i0 + 514], tile[i0 + 515]
    a, b = (v00 + v10) / 2, (v01 + v11) / 2
    assert vals[0] == pytest.approx((a + b) / 2, abs=1e-6)
    assert vals[1] == pytest.approx(vals[0], abs=1e-6) and vals[2] == pytest.approx(vals[0], abs=1e-6)
