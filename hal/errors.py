"""One error family for the whole box (modelled on python-can's CanError tree)."""


class FieldguardError(Exception):
    """Base of every error fieldguard raises on purpose."""


class ConfigError(FieldguardError):
    """A configuration file or value is wrong. The message names the file and the key."""

    def __init__(self, message: str, *, file: str | None = None, key: str | None = None):
        self.file = file
        self.key = key
        where = ""
        if file and key:
            where = f"{file}: [{key}] "
        elif file:
            where = f"{file}: "
        elif key:
            where = f"[{key}] "
        super().__init__(where + message)


class RunFormatError(FieldguardError):
    """A run folder does not follow docs/run-format.md. The message names the file."""


class DeviceError(FieldguardError):
    """Something went wrong with a device."""


class DeviceInitializationError(DeviceError):
    """The device could not be opened or configured."""


class DeviceOperationError(DeviceError):
    """The device failed while running (I/O error, cable out, lost connection)."""


class DeviceTimeoutError(DeviceError):
    """The device did not answer or deliver data in time."""


class DeviceDataError(DeviceError):
    """The device delivered data that cannot be used (wrong shape, garbage, bad checksum)."""
