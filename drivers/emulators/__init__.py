"""Device emulators that speak the real wire protocols, for tests and the bench.

* ``python -m drivers.emulators.sick_lms1xx``: a SICK LMS1xx on TCP (CoLa-A), serving scans of
  the simulated field.
* ``python -m drivers.emulators.strobe``: the strobe/trigger controller on a serial port (pty).
* ``python -m drivers.emulators.fakenect_dump``: writes a libfreenect "fakenect" dump from
  simulated or recorded RGB-D frames.

Each emulator takes fault-injection commands on stdin (one per line, see its module) and prints
JSON events on stdout, so a test or a technician can drive it.
"""


class FaultCommands:
    """The fault-injection command line every emulator takes: one command a line, ``quit``
    ends, an unknown command is an ``error`` event, a done one an ``ok`` event. An emulator
    implements ``handle(word, words) -> bool`` (False: unknown) and has ``log(**event)``."""

    def command(self, line: str) -> bool:
        """One stdin command. False on quit."""
        w = line.split()
        if not w:
            return True
        if w[0] == "quit":
            return False
        if not self.handle(w[0], w):
            self.log(event="error", message=f"unknown command {w[0]!r}")
            return True
        self.log(event="ok", command=line.strip())
        return True

    def handle(self, word: str, words: list[str]) -> bool:  # override
        return False


def serve_commands(emu, lines=None) -> None:
    """Feed fault-injection commands (stdin lines) to ``emu.command(line)`` until it returns
    False ("quit"); if stdin closes first (run in the background), keep serving until killed.
    Always stops the emulator."""
    import sys
    import time
    try:
        for line in (sys.stdin if lines is None else lines):
            if not emu.command(line):
                break
        else:
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
