"""The simulated field (hardware-in-the-loop mock): one deterministic 3-D world from a seed,
rendered for the stereo pair, the RGB-D camera and the planar laser, with a vehicle that drives a
coverage path and obeys the box's gate. Imports only numpy, cv2, the standard library, ``hal``
and ``drivers.runfolder``.

    from drivers.sim import SimField, write_sim_run, SCENES
"""
from .field import SimField, SimSample, depth_calibration, laser_geometry, preview, stereo_calibration
from .scenes import SCENES, build_scene

__all__ = ["SimField", "SimSample", "SCENES", "build_scene", "preview", "stereo_calibration",
           "depth_calibration", "laser_geometry", "write_sim_run"]


def __getattr__(name):
    # record.py imports drivers.runfolder; load it only when asked for
    if name == "write_sim_run":
        from .record import write_sim_run
        return write_sim_run
    raise AttributeError(name)
