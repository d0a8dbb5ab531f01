"""fieldguard device drivers: implementations of the hal interfaces, with Sim/Replay twins."""
