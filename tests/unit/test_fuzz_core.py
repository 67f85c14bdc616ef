"""One bad frame must never stop the monitor: property-based tests of the core.

`Monitor.step` takes any sequence of samples the edges can let through (tools/fuzzing/contract.py's
envelope: NaN-free, but with extreme values, times that jump, repeat or go back, fixes lost and
found, the vehicle type flipping) and never raises; every estimate it gives is finite and every
variance non-negative. Derandomized and quick; tools/fuzz.py --target core runs the same at scale.
"""

import math
import sys
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st

from guard.core.fit import ModelFit
from guard.core.monitor import Monitor
from guard.model.events import Estimate, Notice
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType
from guard.model.sensors import Sensor

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))    # tools.fuzzing, beside guard
from tools.fuzzing import contract, seeds, targets  # noqa: E402

c = contract


def fuzz(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


DRIVE = targets.samples_from(targets.core_seed())      # a rover's second: GNSS 10 Hz, IMU 20 Hz


def value(limit: float):
    """Ordinary values mostly, the envelope's edges sometimes."""
    return st.one_of(st.floats(-2.0, 2.0), st.floats(-limit, limit), st.sampled_from([-limit, limit, 0.0]))


def maybe(strategy):
    return st.none() | strategy


@st.composite
def gnss(draw, t_us: int):
    fix = draw(st.booleans())
    if fix:
        lat = draw(st.one_of(st.floats(seeds.LAT0 - 1e-3, seeds.LAT0 + 1e-3), st.floats(-90.0, 90.0)))
        lon = draw(st.one_of(st.floats(seeds.LON0 - 1e-3, seeds.LON0 + 1e-3), st.floats(-180.0, 180.0)))
        lat = lat if (lat, lon) != (0.0, 0.0) else 1.0
    else:
        lat, lon = draw(st.floats(allow_nan=False, allow_infinity=False)), draw(st.floats(allow_nan=False,
                                                                                          allow_infinity=False))
    alt = draw(st.one_of(st.floats(-100.0, 5000.0), st.floats(allow_nan=False, allow_infinity=False)))
    vel = draw(maybe(st.tuples(value(c.SPEED_MAX_MPS), value(c.SPEED_MAX_MPS))))
    acc = [draw(maybe(st.floats(0.0, c.ACCURACY_MAX))) for _ in range(2)]
    return GnssFix(t_us, fix, lat, lon, alt, *(vel or (None, None)), *acc)


@st.composite
def imu(draw, t_us: int):
    acc = [draw(value(c.ACC_MAX_MPS2)) for _ in range(3)]
    gyro = [draw(value(c.GYRO_MAX_RADPS)) for _ in range(3)]
    mag = draw(maybe(st.tuples(*[value(c.MAG_MAX_GAUSS)] * 3)))
    return ImuSample(t_us, *acc, *gyro, *(mag or (None, None, None)))


@st.composite
def sample(draw, t_us: int):
    kind = draw(st.sampled_from(["gnss", "imu", "imu", "attitude", "vehicle"]))
    if kind == "gnss":
        return draw(gnss(t_us))
    if kind == "imu":
        return draw(imu(t_us))
    if kind == "attitude":
        return Attitude(t_us, draw(st.floats(-math.pi, math.pi)), draw(st.floats(-c.PITCH_MAX_RAD, c.PITCH_MAX_RAD)))
    return VehicleType(draw(st.booleans()))


# a time step: on (us), repeated, a little or far back, a jump anywhere, or absolute 0 / the envelope's end
STEP = st.one_of(st.integers(1, 200_000), st.just(0), st.integers(-300_000, -1),
                 st.integers(-c.T_MAX_US, c.T_MAX_US), st.sampled_from(["zero", "end"]))


def moved(t_us: int, step) -> int:
    if step == "zero":
        return 0
    if step == "end":
        return c.T_MAX_US
    return min(max(t_us + step, 0), c.T_MAX_US)


@st.composite
def arbitrary_stream(draw):
    t, out = seeds.T0_US, []
    for _ in range(draw(st.integers(1, 30))):
        t = moved(t, draw(STEP))
        out.append(draw(sample(t)))
    return out


@st.composite
def edited_drive(draw):
    """The rover's second with a few samples replaced, repeated, dropped, or shifted in time."""
    out = list(DRIVE)
    for _ in range(draw(st.integers(1, 5))):
        i = draw(st.integers(0, len(out) - 1))
        t = getattr(out[i], "t_us", seeds.T0_US)
        op = draw(st.sampled_from(["replace", "repeat", "drop", "shift"]))
        if op == "replace":
            out[i] = draw(sample(moved(t, draw(STEP))))
        elif op == "repeat":
            out.insert(i, out[i])
        elif op == "drop":
            del out[i]
        elif hasattr(out[i], "t_us"):
            step = draw(STEP)
            out[i:] = [type(s)(moved(s.t_us, step), *[getattr(s, f) for f in s.__slots__[1:]])
                       if hasattr(s, "t_us") else s for s in out[i:]]
    return out


def run(samples) -> list:
    monitor, events = Monitor(), []
    for s in samples:
        contract.check_sample(s)        # the input is inside the envelope
        out = monitor.step(s)
        contract.check_events(out)
        events += out
    out = monitor.finish()
    contract.check_events(out)
    return events + out


@fuzz(60)
@given(samples=arbitrary_stream())
def test_any_stream_of_samples(samples):
    run(samples)


@fuzz(100)
@given(samples=edited_drive())
def test_a_drive_with_bad_samples_in_it(samples):
    run(samples)


def test_the_drive_itself_gives_estimates():
    events = run(DRIVE)
    assert sum(isinstance(e, Estimate) for e in events) == 9        # the first fix starts the filter


# -- regressions: what the fuzzer found ----------------------------------------------------------------

def test_model_fit_across_a_time_base_going_back():
    """ModelFit's forgetting factor was exp((last - t) / 300 s): a time base that went back by more
    than 59 hours (an autopilot rebooted after two and a half days up) overflowed it."""
    fit = ModelFit()
    fit.add(Sensor.GYRO, 3 * 86_400_000_000, np.array([0.1]), np.eye(1))
    fit.add(Sensor.GYRO, 1_000_000, np.array([0.1]), np.eye(1))            # the new time base: no overflow
    fit.add(Sensor.GYRO, 1_000_000 + 300_000_000, np.array([0.1]), np.eye(1))
    total, count, first, last = fit.acc[Sensor.GYRO]
    assert last == 301_000_000 and last - first == 300_000_000       # its age carried over
    assert math.isfinite(total) and 1.0 < count < 3.0


def shifted(samples, dt_us: int):
    return [type(s)(s.t_us + dt_us, *[getattr(s, f) for f in s.__slots__[1:]]) if hasattr(s, "t_us") else s
            for s in samples]


def test_a_fix_after_hours_of_an_imu_not_integrated_starts_a_new_filter():
    """An IMU too slow to integrate, its samples 9 s apart, for five hours without a fix, then one:
    a new filter starts on it (a version that let the IMU keep the clock by any step predicted the
    filter across the hours in 0.1 s steps, a hang the fuzzer found)."""
    first = next(i for i, s in enumerate(DRIVE) if isinstance(s, GnssFix))
    imu = next(s for s in DRIVE if isinstance(s, ImuSample))
    slow = [type(imu)(DRIVE[first].t_us + k * 9_000_000, *[getattr(imu, f) for f in imu.__slots__[1:]])
            for k in range(1, 2000)]
    last = shifted([DRIVE[first]], slow[-1].t_us + 100_000 - DRIVE[first].t_us)
    events = run(DRIVE[:first + 1] + slow + last)
    said = [e.text for e in events if isinstance(e, Notice) and "re-initialised" in e.text]
    assert said and float(said[-1].split(" s")[0].split()[-1].lstrip("+")) > 17_000, said


def test_monitor_through_a_reboot_after_three_days_up():
    """The drive at 72 h after boot, then again 6 s after a reboot: a new time base, not an OverflowError."""
    events = run(shifted(DRIVE, 72 * 3_600_000_000) + shifted(DRIVE[1:], 1_000_000) + shifted(DRIVE[1:], 2_000_000))
    jumped = [e for e in events if isinstance(e, Notice) and "time jumped" in e.text]
    assert len(jumped) == 1
    assert any(isinstance(e, Estimate) and e.t_us < 10_000_000 for e in events)
