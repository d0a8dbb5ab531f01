"""fieldguard appliance: the daemon, its 10 Hz loop, perception, fusion, the safety gate."""

__version__ = "0.1.0"
