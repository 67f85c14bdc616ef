"""The autopilot's own verdicts in a DataFlash log: EKF innovation test ratios above 1 and its
messages about GPS, as records of `guard.sources.logs_common` (times: boot microseconds).

XKF4 (EKF3), NKF4 (EKF2), EKF4 (EKF1): SV, SP, SH, SM (EKF1: SMX..SMZ), SVT: the square roots of
the EKF's innovation test ratios of GNSS velocity, GNSS position, height, magnetometer and
airspeed, x100 ('c'); above 1 the measurement failed its gate. Core/lane 0 (`C` = 0 where the
column exists; older logs write core 1 as NKF9/XKF9). ERR: Subsys (LogErrorSubsystem) and ECode.
"""

from __future__ import annotations

import re

import numpy as np

from guard.sources.dataflash.index import MAX_BOOT_US, Log
from guard.sources.logs_common import message_verdict, ratio_episodes

EPISODE_GAP_US = 1_000_000        # test ratios above 1 less than this apart are one episode
MAX_VERDICTS = 200
EKF_TESTS = {"SV": "gnss_vel", "SP": "gnss_pos", "SH": "height", "SM": "mag", "SMX": "mag", "SMY": "mag",
             "SMZ": "mag", "SVT": "airspeed"}
EKF_TYPES = {"XKF4": "EKF3", "NKF4": "EKF2", "EKF4": "EKF1"}
ERR_GPS = {11: "GPS", 7: "GPS failsafe"}       # LogErrorSubsystem
GPS_INFO = re.compile(r"detected|HW:|SW:|baud", re.IGNORECASE)     # receiver identification, not a finding


def autopilot_verdicts(log: Log, notes: list[str]) -> list[dict]:
    """All of them in time order, the first MAX_VERDICTS (a note says when there are more)."""
    verdicts = ekf_verdicts(log) + message_verdicts(log)
    verdicts.sort(key=lambda v: v["time_usec"])
    if len(verdicts) > MAX_VERDICTS:
        notes.append(f"{len(verdicts)} autopilot verdicts, the first {MAX_VERDICTS} listed")
        del verdicts[MAX_VERDICTS:]
    return verdicts


def ekf_verdicts(log: Log) -> list[dict]:
    """One record per episode of an EKF innovation test ratio above 1 (core 0)."""
    out = []
    for name, source in EKF_TYPES.items():
        fmt = log.format(name)
        if fmt is None or not log.offsets(name):
            continue
        offs = log.split(name, "C").get(0, []) if "C" in fmt.colhash else log.offsets(name)
        cols = [c for c in EKF_TESTS if c in fmt.colhash]
        rows = [r for r in log.rows(name, cols, offs) if 0 <= r[0] < MAX_BOOT_US]
        t = np.array([r[0] for r in rows])
        for test in dict.fromkeys(EKF_TESTS[c] for c in cols):
            k = [i + 1 for i, c in enumerate(cols) if EKF_TESTS[c] == test]
            ratio = np.array([max(r[i] for i in k) for r in rows], dtype=np.float64)
            out += ratio_episodes(t, ratio, source, test, gap_us=EPISODE_GAP_US, digits=2)
    return out


def message_verdicts(log: Log) -> list[dict]:
    """The autopilot's messages about GPS: MSG texts naming it, ERR of the GPS subsystems."""
    out = [message_verdict(t, text) for t, text in log.texts("MSG", "Message")
           if "GPS" in text and not GPS_INFO.search(text)]
    fmt = log.format("ERR")
    if fmt is not None and {"Subsys", "ECode"} <= set(fmt.colhash):
        for t, subsys, code in log.rows("ERR", ["Subsys", "ECode"]):
            if subsys in ERR_GPS:
                what = "resolved" if code == 0 else "glitch" if (subsys, code) == (11, 2) else f"error {code}"
                out.append(message_verdict(t, f"ERR {ERR_GPS[subsys]}: {what}"))
    return out
