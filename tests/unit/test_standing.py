"""A standing alarm (guard.model.events.Alarm.standing): a sensor re-anchored on, its alarm standing,
that disagrees again is the same news. The core marks it; the re-anchoring's warning is said once per
alarm; STATUSTEXT says it as "GUARD still ..." at most every STANDING_EVERY_S per sensor."""

import pytest

from guard.config import LinkConfig
from guard.core.monitor import MonitorConfig
from guard.model.events import Alarm, Notice
from guard.sinks import statustext
from guard.sinks.statustext import StatusText
from unit.synthetic import T0_US, drive, of, run

AIR = MonitorConfig(declination_deg=0.0, vehicle="air")


def ramp_on_gnss_alone(seed, rate=0.5):
    """An air vehicle without a compass (GNSS tested alone) whose GNSS north drifts at `rate` m/s from 60 s:
    nothing holds the estimate, so each alarm is re-anchored on at once and the drift alarms again."""
    return run(drive(180.0, yaw=0.4, seed=seed, mag=lambda t: False,
                     gnss_offset=lambda t: (0.0, rate * (t - 60.0) if t >= 60.0 else 0.0)), AIR)


@pytest.mark.parametrize("seed", [13, 14, 15])
def test_the_same_disagreement_again_is_marked_standing_and_its_warning_said_once(seed):
    mon, events = ramp_on_gnss_alone(seed)
    alarms = of(events, Alarm)
    assert len(alarms) >= 5 and alarms[0].t_us >= T0_US + 60e6
    assert not alarms[0].standing and all(a.standing for a in alarms[1:]), [a.standing for a in alarms]
    anchored = [n for n in of(events, Notice) if "re-anchored" in n.text]
    assert [n.level for n in anchored] == ["warning"] + ["info"] * (len(anchored) - 1)
    assert all("again" in n.text for n in anchored[1:])


def test_a_standing_alarm_is_said_on_the_link_at_most_every_so_often():
    mon, events = ramp_on_gnss_alone(13)
    lines = []
    sink = StatusText(None, LinkConfig(), lines.append, lambda text, level, send: None)
    sink.on_events(events)
    alarms = of(events, Alarm)
    first, still = [x for x in lines if "GUARD ALARM" in x], [x for x in lines if "GUARD still" in x]
    assert len(first) == 1
    span_s = (alarms[-1].t_us - alarms[1].t_us) / 1e6
    assert 1 <= len(still) <= span_s // statustext.STANDING_EVERY_S + 1, still
    assert len(still) + sink.skipped["standing_alarm_repeats"] == len(alarms) - 1
    assert sink.alarms == len(alarms)
