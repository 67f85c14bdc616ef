"""PX4 ULog files (.ulg), read with pyulog: the autopilot's own topics, already in SI units.

Time base: every record's `timestamp`, microseconds since the autopilot booted (one clock for all
topics, PX4's hrt). Each part states the units and frames it reads (from PX4's msg/*.msg):
- `framing`: the file's messages walked before pyulog reads it; spans corrupt bytes left unframed
  are skipped (pyulog alone would lose its place and the messages after them).
- `load`: pyulog's reading of the file, what it prints caught and logged, a cut file noticed.
- `streams`: each topic's records as columns, checked, and the samples made from them (GNSS, IMU
  with the latest magnetometer, attitude, vehicle type).
- `verdicts`: PX4's own findings: EKF2's innovation test ratios above 1, its messages about GPS.
- `survey`: what the log is and what it lost, the rates of the topics read, the ones not used, the date.
- `reader`: `UlogReader`, the streams merged by time stamp.

pyulog reads the whole file at once and prints what it finds wrong on stdout (which would corrupt
`guard replay --report -`): its output is caught and logged. It stops silently at a cut message;
the reader notices (the last read came up short) and counts it. Records whose time stamp is
implausible or out of order (corrupt bytes) or whose values are not physical are counted and dropped.
"""

from guard.sources.ulog.load import looks_like_ulog
from guard.sources.ulog.reader import UlogReader

__all__ = ["UlogReader", "looks_like_ulog"]
