"""ArduPilot DataFlash logs (.bin): the autopilot's own log, read with pymavlink's DFReader.

The format (ArduPilot `libraries/AP_Logger/LogStructure.h`, pymavlink `DFReader.py`): messages
`0xA3 0x95 <type>` + a packed little-endian body, with no checksum; FMT messages (type 128) declare
each type's name, format characters and columns. Time: `TimeUS`, microseconds since boot (older
logs: `TimeMS` ms); all samples are on this one time base. Each part states the units it reads:
- `index`: DFReader's index of the file, and rows of chosen types decoded from it (time columns).
- `survey`: what opening the log finds: rates, instances, the vehicle, the date (GPS week), GPA's
  accuracies, and what could not be framed.
- `verdicts`: the autopilot's own findings: EKF innovation test ratios (XKF4/NKF4/EKF4) and its
  messages about GPS.
- `reader`: `DataFlashReader`, the samples in file order (IMU, MAG, GPS, ATT units and frames).

Damage, as DFReader meets it (a DataFlash message has no checksum): a cut last message is dropped
(`skipped["truncated"]`); garbage between messages is skipped up to the next header
(`garbage_bytes`); a header of a type no FMT declared (a corrupt type byte) stopped DFReader's
indexer, and the rest of the file was not read: guard's index steps past it to the next header
and counts it (`undeclared_type`); a tail DFReader still does not read is `unread_bytes`, with a
note. Values out of any sensor's range, time stamps beyond
~116 days of boot, a GPS status above 8 are corrupt messages (`bad_message`).
"""

from guard.sources.dataflash.index import looks_like_dataflash
from guard.sources.dataflash.reader import DataFlashReader

__all__ = ["DataFlashReader", "looks_like_dataflash"]
