"""Device emulators that speak the real wire protocols, for tests and the bench.

* ``python -m drivers.emulators.sick_lms1xx``: a SICK LMS1xx on TCP (CoLa-A), serving scans of
  the simulated field.
* ``python -m drivers.emulators.strobe``: the strobe/trigger controller on a serial port (pty).
* ``python -m drivers.emulators.fakenect_dump``: writes a libfreenect "fakenect" dump from
  simulated or recorded RGB-D frames.

Each emulator takes fault-injection commands on stdin (one per line, see its module) and prints
JSON events on stdout, so a test or a technician can drive it.
"""
