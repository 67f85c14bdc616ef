"""PX4's own findings in a ULog, as records of `guard.sources.logs_common` (times: boot microseconds).

EKF2's innovation test ratios (`estimator_innovation_test_ratios`, the first component of a vector;
older logs: `estimator_status`'s *_test_ratio; dimensionless, above 1 the measurement failed its
gate), in episodes above 1, and the autopilot's text messages about GPS.
"""

from __future__ import annotations

import re

import numpy as np
from pyulog import ULog

from guard.sources.logs_common import message_verdict, ratio_episodes
from guard.sources.ulog.streams import timed

GPS_TEXT = re.compile(r"gps|gnss", re.IGNORECASE)
# EKF2 test -> its innovation test ratio fields (estimator_innovation_test_ratios), older estimator_status's
RATIO_FIELDS = {"gnss_vel": ("gps_hvel[0]", "gps_vvel"), "gnss_pos": ("gps_hpos[0]",),
                "height": ("baro_vpos", "gps_vpos"), "mag": ("mag_field[0]", "heading")}
STATUS_FIELDS = {"gnss_vel": ("vel_test_ratio",), "gnss_pos": ("pos_test_ratio",), "height": ("hgt_test_ratio",),
                 "mag": ("mag_test_ratio", "hdg_test_ratio")}


def ekf_verdicts(ratios, status, skipped) -> list[dict]:
    """Episodes from estimator_innovation_test_ratios (instance 0), else from estimator_status: one
    per run of consecutive records whose test ratio is above 1."""
    data, fields = (ratios, RATIO_FIELDS) if ratios is not None else (status, STATUS_FIELDS)
    if data is None:
        return []
    d, t = timed(data, skipped)
    out = []
    for test, names in fields.items():
        present = [d[n].astype(np.float64) for n in names if n in d]
        if present:
            out += ratio_episodes(t, np.fmax.reduce(present), "EKF2", test)
    return out


def message_verdicts(ulog: ULog) -> list[dict]:
    """The autopilot's text messages that mention GPS or GNSS."""
    texts = list(ulog.logged_messages) + [m for ms in ulog.logged_messages_tagged.values() for m in ms]
    return [message_verdict(m.timestamp, m.message, m.log_level_str()) for m in texts if GPS_TEXT.search(m.message)]
