"""Write a simulated run folder (docs/run-format.md) with drivers.runfolder.RunWriter.

    python -m drivers.sim.record stubble-day 100 runs/stubble-day-0 --scale 0.5
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from hal.types import GateState

from .field import SimField
from .scenes import SCENES


def write_sim_run(scene: str, frames: int, out: str | Path, seed: int = 0,
                  sensors=None, stereo_scale: float = 1.0, progress=None,
                  overwrite: bool = False, stop_before_collisions: bool = False,
                  name: str | None = None) -> Path:
    """Render ``frames`` frames at 10 Hz with the vehicle driving and write a run folder.

    Open loop: the vehicle is never told STOP, unless ``stop_before_collisions`` (then a perfect
    oracle brakes it before each obstacle on its path). ``sensors`` defaults to all three, or
    ``("rgbd",)`` for the greenhouse kinds. ``progress(i, n)`` is called after each frame. Writes
    ``preview.png`` (first frame + map) beside the run's files. Returns the folder.
    """
    from drivers.runfolder import RunWriter   # noqa: PLC0415 (kept lazy: only this needs it)

    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; known scenes: {', '.join(sorted(SCENES))}")
    if frames < 1:
        raise ValueError("frames must be >= 1")
    if sensors is None:
        sensors = ("rgbd",) if scene.startswith("greenhouse") else ("stereo", "laser", "rgbd")
    rate_hz = 10.0
    field = SimField(scene, seed=seed, sensors=tuple(sensors), stereo_scale=stereo_scale,
                     rate_hz=rate_hz)
    out = Path(out)
    extra = {"sim": {"scene": scene, "seed": int(seed), "sensors": list(sensors),
                     "stereo_scale": float(stereo_scale), "frames": int(frames),
                     "stop_before_collisions": bool(stop_before_collisions),
                     "cruise_mps": field.scene.cruise_mps,
                     "obstacles": len(field.world.obstacles),
                     "generator": "drivers.sim"}}
    if "stereo" not in sensors and "rgbd" not in sensors:
        # no camera in the run: say the zone the stereo camera would score (run-format.md)
        extra["scored_zone"] = {"x_min_m": 2.0, "x_max_m": 20.0}
    dt_ns = int(round(1e9 / rate_hz))
    first = None
    with RunWriter(out, name or f"{scene}-{seed}", rate_hz=rate_hz,
                   stereo=field.stereo_calibration, rgbd=field.depth_calibration,
                   laser=field.laser_geometry, extra_run=extra, overwrite=overwrite) as w:
        for i in range(frames):
            stamp = i * dt_ns
            s = field.render(stamp, i)
            if first is None:
                first = s.stereo.left if s.stereo is not None else (
                    s.rgbd.color if s.rgbd is not None else None)
                cv2.imwrite(str(out / "preview.png"), field.preview(first))
            w.write_frame(i, stamp, vehicle=s.vehicle, stereo=s.stereo, rgbd=s.rgbd,
                          laser=s.laser, truth=s.truth, illumination=field.illumination)
            cmd = field.oracle_command() if stop_before_collisions else GateState.CLEAR
            field.step(1.0 / rate_hz, cmd)
            if progress is not None:
                progress(i + 1, frames)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Write a simulated run folder.")
    ap.add_argument("scene", choices=sorted(SCENES))
    ap.add_argument("frames", type=int)
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0, help="stereo_scale")
    ap.add_argument("--sensors", default=None, help="comma list: stereo,laser,rgbd")
    ap.add_argument("--stop-before-collisions", action="store_true")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    sensors = tuple(a.sensors.split(",")) if a.sensors else None

    def progress(i, n):
        print(f"\r{i}/{n}", end="", file=sys.stderr, flush=True)

    p = write_sim_run(a.scene, a.frames, a.out, seed=a.seed, sensors=sensors,
                      stereo_scale=a.scale, progress=progress, overwrite=a.overwrite,
                      stop_before_collisions=a.stop_before_collisions)
    print(f"\nwrote {p}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
