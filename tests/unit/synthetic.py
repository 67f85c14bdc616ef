"""A synthetic drive for the core's tests: a level vehicle on a straight line, its IMU, magnetometer
and GNSS in SI units, with small seeded noise; attacks and receiver quirks by parameter. And Runs:
runs that begin alike, their common beginning stepped once."""

import copy
import math

import numpy as np
import pymap3d

from guard.core.monitor import Monitor, MonitorConfig
from guard.model.samples import GnssFix, ImuSample

LAT0, LON0, ALT0 = 47.397742, 8.545594, 488.0
G = 9.80665
IMU_DT_US, GNSS_EVERY = 20_000, 10         # IMU 50 Hz, GNSS 5 Hz
T0_US = 1_000_000
B_H, B_Z = 0.2, 0.4                          # earth's field, horizontal and down (gauss)


def drive(duration_s, speed=5.0, yaw=0.0, seed=0, gnss_offset=None, fix_ok=None, gnss_every=GNSS_EVERY,
          vel_offset=None, with_vel=True, gnss_lag_us=0, mag=None, gyro_bias=None, mag_offset_deg=0.0,
          vel_noise=0.03, vel_acc=0.1, h_acc=0.5, vibration=None, accel_bias=None, mag_turn=None):
    """A level vehicle on a straight line at constant speed; yaw is ENU (0 = east).

    The IMU reads -g on z, the earth's field rotated into the body (FRD): a compass heading chi gives
    m_x = B cos chi, m_y = -B sin chi. gnss_offset(t) -> (de, dn) adds an attack to the position,
    vel_offset(t) -> (dve, dvn) to the velocity; fix_ok(t) -> False sends a no-fix message;
    with_vel=False fixes without a velocity; gnss_lag_us delivers each fix that long after its time
    stamp (after the IMU samples in between, as a receiver's latency does); mag(t) -> False leaves the
    magnetometer out; gyro_bias(t) adds to the yaw rate. A fix every gnss_every IMU samples (50 Hz).
    mag_offset_deg turns the compass that far (east positive: it reads a heading that much larger);
    vel_noise is the GNSS velocity's noise and vel_acc, h_acc what the receiver reports (None: nothing).
    vibration(t) is the sigma of a further white noise on the accelerometers (motors spinning),
    accel_bias(t) a bias added to the forward one, mag_turn(t) a further turn of the compass (degrees, as
    mag_offset_deg: a disturbed or attacked one). Small seeded noise on everything.
    """
    rng = np.random.default_rng(seed)
    chi = math.pi / 2 - yaw
    out, pending = [], []
    for i in range(int(duration_s * 1e6 / IMU_DT_US) + 1):
        t_us, t = T0_US + i * IMU_DT_US, i * IMU_DT_US / 1e6
        if i % gnss_every == 0:
            if fix_ok is None or fix_ok(t):
                de, dn = gnss_offset(t) if gnss_offset else (0.0, 0.0)
                dve, dvn = vel_offset(t) if vel_offset else (0.0, 0.0)
                e = speed * math.cos(yaw) * t + de + rng.normal(0.0, 0.1)
                n = speed * math.sin(yaw) * t + dn + rng.normal(0.0, 0.1)
                lat, lon, _ = pymap3d.enu2geodetic(e, n, 0.0, LAT0, LON0, ALT0)
                vn = speed * math.sin(yaw) + dvn + rng.normal(0.0, vel_noise)
                ve = speed * math.cos(yaw) + dve + rng.normal(0.0, vel_noise)
                fix = GnssFix(t_us, True, float(lat), float(lon), ALT0, vn if with_vel else None,
                              ve if with_vel else None, h_acc, vel_acc)
            else:
                fix = GnssFix(t_us, False, 0.0, 0.0, 0.0, None, None, None, None)
            pending.append((t_us + gnss_lag_us, fix))
        while pending and pending[0][0] <= t_us:
            out.append(pending.pop(0)[1])
        c = chi + math.radians(mag_offset_deg + (mag_turn(t) if mag_turn else 0.0)) + rng.normal(0.0, 0.005)
        a = rng.normal(0.0, 0.03, 3)
        if vibration is not None and vibration(t) > 0.0:
            a = a + rng.normal(0.0, vibration(t), 3)
        if accel_bias is not None:
            a[0] += accel_bias(t)
        w = rng.normal(0.0, 0.001, 3)
        m = (B_H * math.cos(c), -B_H * math.sin(c), B_Z) if mag is None or mag(t) else (None, None, None)
        out.append(ImuSample(t_us, a[0], a[1], -G + a[2], w[0], w[1], w[2] - (gyro_bias(t) if gyro_bias else 0.0),
                             *m))
    return out


def run(samples, cfg=None):
    mon = Monitor(cfg or MonitorConfig(declination_deg=0.0))
    events = [e for s in samples for e in mon.step(s)]
    return mon, events


def of(events, cls):
    return [e for e in events if isinstance(e, cls)]




class Runs:
    """Monitor runs that begin alike, their common beginning stepped once (a test module's `runs` fixture).

    run(samples, cfg, at_us) keeps a copy of the monitor, and the events so far, at each time in at_us
    (before the first sample stamped at or after it). A later run with an equal config whose samples up
    to one of those marks are equal to the earlier run's continues a copy of that monitor from there. The
    core is a pure step (sample in, events out; no clock, no I/O), so the events and the monitor are
    those a fresh monitor gives, to the bit. Not for a run under a monkeypatch of the core, nor after one
    within the module: the kept copies were stepped without it.
    """

    def __init__(self):
        self._kept = []         # (cfg, record_tests, the samples before the mark, the monitor there, events)

    def run(self, samples, cfg=None, at_us=(), record_tests=True):
        cfg = cfg or MonitorConfig(declination_deg=0.0)
        samples = list(samples)
        start, mon, events = 0, None, []
        for kept_cfg, kept_record, head, kept, said in self._kept:
            n = len(head)
            if n > start and kept_record == record_tests and kept_cfg == cfg and samples[:n] == head:
                start, mon, events = n, kept, said
        mon = copy.deepcopy(mon) if mon is not None else Monitor(cfg, record_tests)
        events = list(events)
        marks = {next((i for i, s in enumerate(samples) if getattr(s, "t_us", -1) >= t), len(samples))
                 for t in at_us}
        for i in range(start, len(samples)):
            if i in marks:
                self._kept.append((cfg, record_tests, samples[:i], copy.deepcopy(mon), list(events)))
            events.extend(mon.step(samples[i]))
        return mon, events
