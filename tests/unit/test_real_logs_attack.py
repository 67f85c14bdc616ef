"""tools/real_logs.py --attack: the attack written into a log's own sample stream, from its onset to
the end of its window, where the run's stream ends."""

import math
import sys
from pathlib import Path

import pymap3d

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))    # tools, beside guard
from guard.model.samples import Attitude, GnssFix, ImuSample  # noqa: E402
from tools.real_logs import END_MARGIN_S, attack  # noqa: E402

LAT, LON, ALT = 47.0, 8.0, 400.0


def stream(seconds: int = 10):
    """A fix every 0.2 s, IMU samples every 0.05 s and an attitude every 0.1 s, in time order."""
    out = []
    for k in range(seconds * 20):
        t = k * 50_000
        out.append(ImuSample(t, 0.0, 0.0, -9.81, 0.0, 0.0, 0.01, 0.2, 0.0, 0.4))
        if k % 2 == 0:
            out.append(Attitude(t, 0.0, 0.0))
        if k % 4 == 0:
            out.append(GnssFix(t, True, LAT, LON, ALT, 1.0, 0.0, 0.5, 0.1))
    return out


def north_m(fix: GnssFix) -> float:
    _, n, _ = pymap3d.geodetic2enu(fix.lat_deg, fix.lon_deg, fix.alt_m, LAT, LON, ALT)
    return float(n)


def test_the_stream_ends_after_the_window_and_its_margin_and_the_step_is_in_it():
    onset, until = 3_000_000, 5_000_000
    end = until + int(END_MARGIN_S * 1e6)
    got = list(attack("step", 5.0, onset, until)(stream()))
    assert max(s.t_us for s in got) == end          # every sample to the window's end and its margin, none after
    assert len(got) == sum(1 for s in stream() if s.t_us <= end)
    fixes = [s for s in got if isinstance(s, GnssFix)]
    assert all(math.isclose(north_m(f), 5.0 if f.t_us >= onset else 0.0, abs_tol=1e-6) for f in fixes)
    assert all(s.gyro_z_radps == 0.01 for s in got if isinstance(s, ImuSample))     # the IMU untouched


def test_a_sample_stamped_far_off_does_not_end_the_stream():
    """A corrupt stamp far past the window (the core counts and skips it) is passed on, not an end."""
    samples = stream()
    odd = ImuSample(10**12, 0.0, 0.0, -9.81, 0.0, 0.0, 0.01, 0.2, 0.0, 0.4)
    samples.insert(10, odd)
    got = list(attack("step", 5.0, 3_000_000, 5_000_000)(samples))
    assert odd in got and max(s.t_us for s in got if s is not odd) == 5_000_000 + int(END_MARGIN_S * 1e6)


def test_without_an_end_the_whole_stream_runs_and_an_imu_attack_leaves_the_fixes():
    got = list(attack("gyro", 0.05, 3_000_000)(stream()))
    assert len(got) == len(stream())
    assert all(math.isclose(s.gyro_z_radps, 0.06 if s.t_us >= 3_000_000 else 0.01)
               for s in got if isinstance(s, ImuSample))
    assert all(north_m(s) == 0.0 for s in got if isinstance(s, GnssFix))
