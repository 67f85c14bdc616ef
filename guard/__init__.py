"""guard: detects attacks on a vehicle's navigation sensors while it moves.

An extended Kalman filter fuses IMU and GNSS (the paper's model); its innovations are tested with CUSUM
detectors. See README.md for the data flow and the figures, and `guard.core.monitor` for the one pure step
that live, replay and CAN input all share.
"""

__version__ = "0.1.0"

DEFAULT_CONFIG_PATH = "/etc/guard/guard.toml"    # the config read when none is given, where it exists
