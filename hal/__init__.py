"""fieldguard hardware abstraction layer.

Interfaces and stamped data types only: the standard library and numpy, nothing of ours.
Drivers implement these interfaces; the appliance sees nothing else of a device.

Conventions (see docs/architecture.md):
- time is integer nanoseconds from an injected :class:`Clock` (``stamp_ns``);
- colour images are ``uint8`` HxWx3 in **BGR** order (OpenCV's native order);
- depth is float32 metres of z-depth along the optical axis, 0 where there is no reading;
- laser ranges are float32 metres, NaN where a beam had no return;
- vehicle frame: x forward, y left, z up (ISO 8855 / REP 103); positive pitch looks down.
"""
from .errors import (
    FieldguardError, ConfigError, DeviceError, DeviceInitializationError,
    DeviceOperationError, DeviceTimeoutError, DeviceDataError, RunFormatError,
)
from .types import (
    Mount, PinholeCalibration, StereoCalibration, DepthCalibration, LaserGeometry,
    StereoFrame, DepthFrame, LaserScan, VehicleState, GateState, GateOutput, ObstacleSector,
)
from .health import Health, HealthReport
from .clock import Clock, MonotonicClock, ManualClock
from .devices import (
    Device, StereoCamera, StrobeTrigger, DepthCamera, SafetyLaser, VehicleLink,
)

__all__ = [n for n in dir() if not n.startswith("_")]
