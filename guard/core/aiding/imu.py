"""IMU aiding: the magnetometer's heading, the gyro's yaw rate and the accelerometer's horizontal
specific force, fused as one stacked measurement and tested sensor by sensor.

    z = (theta_mag, omega_z, a_x, a_y[, 0])    h(x) = H x, but for the constraint's row
    H rows: theta + b_psi;  theta_dot + b_theta_dot;  a_x + b_ax;  a_y + b_ay;
            [ground vehicles: v_y - d theta_dot + k_s theta_dot v_x |v_x| = 0, linearised at the state]
A tilted IMU (a flying drone) is first levelled with the autopilot's roll and pitch, and a fast IMU
averaged down to `imu_fusion_hz` (as PX4's EKF2 does): the mean of the samples since the last fusion
is fused at the last one's time, which keeps a 250 Hz IMU affordable on a companion computer.

R is the vehicle's own: the noise of each reading (vibration, on a vehicle with motors: 0.25 to
0.66 m/s^2 on the accelerometers of two real copters logged at 25 Hz, against the simulator's 0.05)
is measured from the differences of consecutive samples (`ImuNoise`; the heading's between consecutive
compass readings, less what the gyro turned in between), over NOISE_TAU_S and over the last NOISE_SHORT
samples (motors spinning up), and used where it exceeds the configured sigma (the floor), up to
NOISE_CAP times it; until it is measured, at NOISE_CAP times it. A bias, a ramp or a slow drift leaves
consecutive samples alike: what an attack of that kind does cannot loosen the test that is to find it.
"""

from __future__ import annotations

import functools
import math
from collections import deque

import numpy as np

from guard.core.aiding import Aid
from guard.core.ekf import AX, AY, BAX, BAY, BM, BW, KS, LA, N_STATES, TH, VX, VY, W, FilterConfig
from guard.core.history import ImuFusion
from guard.model.samples import ImuSample
from guard.model.sensors import Sensor

G = 9.80665

# IMU block: heading, gyro, accel x, accel y
H_IMU = np.zeros((4, N_STATES))
H_IMU[0, TH] = H_IMU[0, BM] = 1.0      # the magnetometer reads the heading plus its offset
H_IMU[1, W] = H_IMU[1, BW] = 1.0
H_IMU[2, AX] = H_IMU[2, BAX] = 1.0
H_IMU[3, AY] = H_IMU[3, BAY] = 1.0
H_IMU_NO_MAG = H_IMU[1:]
# ground vehicles: the same with the sideways constraint appended (its slip columns set per fusion)
H_LATERAL = np.zeros((1, N_STATES)); H_LATERAL[0, VY] = 1.0
H_IMU_GROUND, H_IMU_NO_MAG_GROUND = np.vstack([H_IMU, H_LATERAL]), np.vstack([H_IMU_NO_MAG, H_LATERAL])
# rows of the stacked IMU measurement that belong to each sensor: (sensor, first, last + 1)
IMU_BLOCKS = ((Sensor.MAG, 0, 1), (Sensor.GYRO, 1, 2), (Sensor.ACCEL, 2, 4))
IMU_BLOCKS_NO_MAG = ((Sensor.GYRO, 0, 1), (Sensor.ACCEL, 1, 3))


def lateral_rows(sensor: Sensor, n: int) -> tuple[slice, slice | None]:
    """A tested innovation's rows by the noise that scales them: the sensor's own, and on wheels the
    sideways constraint's, which the accelerometer's test (n = 3) holds too, its noise its own
    (`lateral_sigma_mps`); None where there is none."""
    if sensor == Sensor.ACCEL and n == 3:
        return slice(0, 2), slice(2, 3)
    return slice(0, n), None


@functools.cache
def row_sensors(blocks: tuple[tuple[Sensor, int, int], ...], ground: bool) -> tuple[Sensor | None, ...]:
    """The sensor of each row of a stacked measurement (None: the ground's constraint, the last)."""
    return tuple(sensor for sensor, i, j in blocks for _ in range(i, j)) + (None,) * ground


def level(s: ImuSample, phi: float, p: float):
    """Horizontal specific force (forward, left), ENU yaw rate, the levelled field (m_x, m_y), the
    tilt's sensitivity of the heading (|tan(inclination)| x the body's roll and pitch rate) and that
    roll and pitch rate itself.

    The body axes are FRD; a tilted IMU is rotated to the local level frame with the latest
    roll phi and pitch p: v_level = R_y(p) R_x(phi) v_body. The field's inclination I makes a tilt
    error d turn the levelled heading by up to tan(I) d, and gravity leak into the horizontal specific
    force as g d: with an attitude that lags (the autopilot's, sampled apart from the IMU), d grows
    with the roll and pitch rate.
    """
    tilt_rate = tilt = math.hypot(s.gyro_x_radps, s.gyro_y_radps)
    if phi == 0.0 and p == 0.0:
        fx, fy = s.acc_x_mps2, s.acc_y_mps2
        yaw_rate_ned = s.gyro_z_radps
        mx, my, mz = s.mag_x_gauss, s.mag_y_gauss, s.mag_z_gauss
    else:
        cr, sr, cp, sp = math.cos(phi), math.sin(phi), math.cos(p), math.sin(p)
        fx = cp * s.acc_x_mps2 + sp * sr * s.acc_y_mps2 + sp * cr * s.acc_z_mps2
        fy = cr * s.acc_y_mps2 - sr * s.acc_z_mps2
        yaw_rate_ned = (sr * s.gyro_y_radps + cr * s.gyro_z_radps) / cp
        if s.mag_x_gauss is not None:
            mx = cp * s.mag_x_gauss + sp * sr * s.mag_y_gauss + sp * cr * s.mag_z_gauss
            my = cr * s.mag_y_gauss - sr * s.mag_z_gauss
            mz = -sp * s.mag_x_gauss + cp * sr * s.mag_y_gauss + cp * cr * s.mag_z_gauss
        else:
            mx = my = mz = None
    if mx is not None and math.hypot(mx, my) > 1e-3:
        mag = (mx, my)
        tilt *= abs(mz or 0.0) / math.hypot(mx, my)
    else:
        mag, tilt = None, 0.0
    return fx, -fy, -yaw_rate_ned, mag, tilt, tilt_rate


def heading(mx: float, my: float, declination: float) -> float:
    """ENU yaw from the levelled field: compass chi = atan2(-m_y, m_x) + declination, theta = pi/2 - chi."""
    return math.remainder(math.pi / 2 - (math.atan2(-my, mx) + declination), math.tau)


NOISE_TAU_S = 2.0       # s, the memory of the measured noise
NOISE_CAP = 10.0        # the measured noise counts up to this many times its floor
NOISE_GAP_S = 0.5       # consecutive samples further apart than this are not compared
NOISE_SHORT = 5         # ... and the median of the last this many second differences, at once
NOISE_MIN_READINGS = 20    # the compass's slow memory holds at least this many readings (NOISE_TAU_S of a
                            # 10 Hz one, the rate autopilots log it at)
MAG_GAP_S = 2.5         # consecutive compass readings further apart than this are not compared (a 1 Hz
                        # one's are, the gyro's turn between them taken out)
START_CAP_S = 5.0       # a reading not yet measured is taken at the cap for at most this long after its
                        # first sample, then at what the slow memory holds (below)


class ImuNoise:
    """The variance of each IMU reading (ax, ay, yaw rate, heading), from the squared differences of
    consecutive samples: E[(x_k - x_k-1)^2] / 2 = sigma^2 for white noise on a slow signal.

    Two memories: NOISE_TAU_S, learnt while every test is calm; and the median of the last NOISE_SHORT
    second differences, always. A copter's motors spinning up at take-off bring a vibration ten times
    the one before within a tenth of a second, which the slow memory takes seconds to see: the filter,
    still told the quiet noise, read the first samples of it as an accelerometer attack (the lift-off
    alarms of real flights). Every sample differs from the last in a vibration, so the median sees it
    after NOISE_SHORT / 2 of them; a bias or a step is two second differences, a ramp or a drift one,
    and the median of five does not move for them. The median of a Gaussian's squares is 0.455 of their
    mean: the short memory reads a vibration's sigma at about two thirds, on purpose, as it is there to
    keep the first samples of a vibration from reading as an attack, and the slow memory measures it
    once the tests are calm.

    What this gives up: a vibration that sets in at once is no longer an alarm by itself, whether a
    motor start or a jitter an attacker writes into the accelerometer, and a bias written with such a
    jitter is caught as a bias under a vibration is, the test loosened up to NOISE_CAP (README)."""

    def __init__(self):
        self.var = [0.0, 0.0, 0.0, 0.0]
        self.short: list[deque[float]] = [deque(maxlen=NOISE_SHORT) for _ in range(4)]
        self._median: list[float | None] = [None] * 4  # each short memory's median once full, kept as it moves
        self._d: list[float | None] = [None] * 4        # each reading's last first difference
        self._last: tuple | None = None         # (t_us, ax, ay, rate) of the last IMU sample
        self._mag: tuple[int, float] | None = None      # (t_us, heading) of the last compass reading, and
        self._turn = 0.0                        # what the gyro turned since it (rad)
        self._pending: tuple[float, float] | None = None    # the compass's last difference, not yet learnt
        self._first: list[int | None] = [None] * 4      # each reading's first sample (the start's cap)

    def add(self, t_us: int, ax: float, ay: float, rate: float, theta: float | None, learn: bool = True,
            calm: bool = True) -> None:
        """One sample; `learn` False: remembered for the next difference, not learnt from (a blow);
        `calm` False: learnt by the short memory only (a test is near its threshold).

        The heading's differences are taken between consecutive compass readings, less what the gyro
        turned in between: a magnetometer slower than the IMU (DataFlash MAG at 10 Hz beside a 50 to
        400 Hz IMU, a ULog's at 50 to 100 Hz beside 250) speaks on few consecutive IMU samples, and
        compared sample to sample its noise was never measured: its test ran at the floor,
        heading_sigma_rad, however noisy the compass."""
        last, self._last = self._last, (t_us, ax, ay, rate)
        for i in range(3 if theta is None else 4):
            if self._first[i] is None:
                self._first[i] = t_us
        if not learn or last is None or not 0 < t_us - last[0] <= NOISE_GAP_S * 1e6:
            self._d = [None] * 4                # no difference across a gap or a blow (both memories
            self._mag = None if theta is None else (t_us, theta)     # carry through it: the vehicle
            self._turn, self._pending = 0.0, None                    # is the one it was)
            return
        dt = (t_us - last[0]) / 1e6
        self._turn += rate * dt
        a = min(1.0, dt / NOISE_TAU_S)
        self._learn(0, ax - last[1], a, calm)
        self._learn(1, ay - last[2], a, calm)
        self._learn(2, rate - last[3], a, calm)
        if theta is None:
            return
        mag, self._mag = self._mag, (t_us, theta)
        turn, self._turn = self._turn, 0.0
        # the compass's slow memory learns a difference at the next reading, once the test has seen the
        # one that made it and stayed calm: a 2 Hz compass has 4 readings in NOISE_TAU_S, and the one a
        # step is written into would otherwise loosen its own test before it is tested (a compass faster
        # than the fusions, imu_fusion_hz, may speak again before the test: its readings weigh
        # NOISE_TAU_S's share, a few thousandths, as before). Nor does one reading weigh more than
        # 1 / NOISE_MIN_READINGS (a 2 Hz compass's memory: 10 s)
        pending, self._pending = self._pending, None
        if pending is not None and calm:
            self.var[3] += pending[0] * (0.5 * pending[1] ** 2 - self.var[3])
        if mag is None or not 0 < t_us - mag[0] <= MAG_GAP_S * 1e6:
            self._d[3] = None
            return
        di = math.remainder(theta - mag[1] - turn, math.tau)
        self._pending = (min(1.0 / NOISE_MIN_READINGS, (t_us - mag[0]) / 1e6 / NOISE_TAU_S), di)
        self._learn(3, di, 0.0, False)

    def _learn(self, i: int, di: float, a: float, calm: bool) -> None:
        """One first difference di of reading i; a the slow memory's step."""
        if calm:
            self.var[i] += a * (0.5 * di * di - self.var[i])
        # the short memory takes the second differences, E[(d_k - d_k-1)^2] / 6 = sigma^2 for white
        # noise: a manoeuvre's signal, locally a line, has none (its first differences would be
        # taken for noise in a hard-flown copter's turns)
        d_last = self._d[i]
        if d_last is not None:
            dd = di - d_last
            q = self.short[i]
            q.append(dd * dd / 6.0)
            if len(q) == NOISE_SHORT:
                self._median[i] = sorted(q)[NOISE_SHORT // 2]
        self._d[i] = di

    def vibration(self) -> float | None:
        """The accelerometers' short noise (m/s^2, the larger axis's), None until both are known: what
        guard.core.aiding.motors hears the motors by."""
        x, y = self._short_median(0), self._short_median(1)
        if x is None or y is None:
            return None
        return math.sqrt(max(x, y))

    def _short_median(self, i: int) -> float | None:
        """The short memory's variance of one channel (the median of its last NOISE_SHORT), None
        until it holds that many (_learn keeps it as the memory moves: it is read several times a sample)."""
        return self._median[i]

    def sigmas(self, floors: tuple[float, float, float, float], n: int, n_mag: int | None = None) -> list[float]:
        """The noise of a mean of n samples (of n_mag compass readings, n if None): `floored` of
        `measured`."""
        return self.floored(floors, self.measured(n, n_mag))

    def floored(self, floors: tuple[float, float, float, float], measured: list[float]) -> list[float]:
        """The noise `measured` of a mean of samples (measured()): each reading's (the larger memory's),
        within [floor, NOISE_CAP * floor]. A reading not yet measured (fewer than NOISE_SHORT second
        differences: a run's first few samples, a compass's first readings) is taken at
        NOISE_CAP * floor, the most its test would ever allow, for at most START_CAP_S after
        its first sample: a log that starts in flight, or a coarse compass, was tested at its floor for
        those first samples and alarmed on them (a second compass reading 15 degrees from the first,
        0.1 s into a real flight). One never measured by then (a compass slower than MAG_GAP_S) is
        taken at what the slow memory holds, its floor at least, as before."""
        now = self._last[0] if self._last is not None else None
        return [min(max(f, r), NOISE_CAP * f) if short is not None or first is None or now is None
                or now - first >= START_CAP_S * 1e6 else NOISE_CAP * f
                for f, r, short, first in zip(floors, measured, self._median, self._first)]

    def measured(self, n: int, n_mag: int | None = None) -> list[float]:
        """The noise of a mean of n samples (of n_mag compass readings, n if None) as measured (the
        larger memory's), neither floored nor capped."""
        out = []
        for i, (v, short) in enumerate(zip(self.var, self._median)):
            if short is not None:
                v = max(v, short)
            out.append(math.sqrt(v / (n_mag or n if i == 3 else n)))
        return out


class StreamRate:
    """A stream's rate, from its last SAMPLES intervals (the median: a gap or a burst does not decide it)."""

    SAMPLES = 5

    def __init__(self):
        self.times: deque[int] = deque(maxlen=self.SAMPLES + 1)

    def add(self, t_us: int) -> float | None:
        """The rate in Hz once known (None before)."""
        self.times.append(t_us)
        if len(self.times) <= self.SAMPLES:
            return None
        return 1e6 / float(np.median(np.diff(self.times)))


class RateWatch:
    """Whether an IMU stream is fast enough to integrate (min_hz): judged from its first intervals,
    then watched. A slow one is fast once the median of its last SAMPLES intervals reaches min_hz (the
    autopilot was asked for more, guard.sources.rates); a fast one is slow once SLOW_RUN intervals in
    a row are each longer than 1/min_hz (a ground station on the same port lowered it): a lossy link
    that drops a sample now and then, or a gap, is neither, and does not make the judgement flap.
    While fast it costs a comparison a sample."""

    SLOW_RUN = 20

    def __init__(self, min_hz: float):
        self.min_hz = min_hz
        self.fast: bool | None = None
        self._rate = StreamRate()
        self._last: int | None = None
        self._long = 0

    def add(self, t_us: int) -> tuple[bool, float, bool] | None:
        """(fast, its rate in Hz, first judgement) when the stream is judged or judged anew, else None."""
        if self.fast:
            last, self._last = self._last, t_us
            if last is None or t_us - last <= 1e6 / self.min_hz:
                self._long = 0
                return None
            self._long += 1
            if self._long < self.SLOW_RUN:
                return None
            self.fast, self._long, self._rate = False, 0, StreamRate()
            return False, 1e6 / (t_us - last), False
        hz = self._rate.add(t_us)
        if hz is None or (hz >= self.min_hz) == self.fast:
            return None
        first, self.fast, self._last = self.fast is None, hz >= self.min_hz, t_us
        return self.fast, hz, first


class Averager:
    """The mean of the IMU samples since the last fusion, due every 1/imu_fusion_hz (0: every sample)."""

    def __init__(self, fusion_hz: float):
        self.fusion_hz = fusion_hz
        self.t_us: int | None = None            # time of the last fused IMU measurement
        self._clear()

    def _clear(self) -> None:
        self.sum = [0.0] * 7                    # ax, ay, yaw rate, m_x, m_y, tilt, tilt rate since the last fusion
        self.n = self.mag_n = 0

    def drop(self) -> None:
        """Forget the samples since the last fusion: a blow sets the IMU aside (guard.core.aiding.impact),
        and those before it are not to be averaged with those after it."""
        self._clear()

    def add(self, t_us: int, ax: float, ay: float, rate: float, mag, tilt: float, tilt_rate: float) -> tuple | None:
        """Add a sample; when a fusion is due, (ax, ay, rate, mag, tilt, tilt rate) averaged, the
        number of samples in the mean and of compass readings in it, else None."""
        acc = self.sum
        acc[0] += ax; acc[1] += ay; acc[2] += rate; acc[6] += tilt_rate
        self.n += 1
        if mag is not None:
            acc[3] += mag[0]; acc[4] += mag[1]; acc[5] += tilt
            self.mag_n += 1
        hz = self.fusion_hz
        if hz > 0 and self.t_us is not None and t_us - self.t_us < 0.9e6 / hz:
            return None
        n, nm = self.n, self.mag_n
        out = (acc[0] / n, acc[1] / n, acc[2] / n, (acc[3] / nm, acc[4] / nm) if nm else None,
               acc[5] / nm if nm else 0.0, acc[6] / n, n, nm)
        self._clear()
        self.t_us = t_us
        return out


class ImuAiding:
    """Builds the stacked IMU measurement and the rows each sensor owns."""

    def __init__(self, f: FilterConfig):
        self.f = f
        self.floors = (f.accel_sigma_mps2, f.accel_sigma_mps2, f.gyro_sigma_radps, f.heading_sigma_rad)
        self.noise = ImuNoise()
        self.H = (H_IMU, H_IMU_GROUND)          # indexed by `ground`: for a ground vehicle, v_y = 0 after it
        self.H_no_mag = (H_IMU_NO_MAG, H_IMU_NO_MAG_GROUND)
        self.measured: list[float] = []         # the last fusion's noise as measured (ImuNoise.measured)

    def measurement(self, x: np.ndarray, theta: float | None, rate: float, ax: float, ay: float, ground: bool,
                    tilt: float = 0.0, tilt_rate: float = 0.0, n: int = 1, n_mag: int | None = None):
        """(Aid, blocks, angle_rows) of one fusion of a mean of n samples (n_mag compass readings in it,
        n if None); theta None without a magnetometer; tilt the heading's sensitivity to a lagging
        attitude, tilt_rate the roll and pitch rate (level())."""
        self.measured = self.noise.measured(n, n_mag)
        s_ax, s_ay, s_rate, s_theta = self.noise.floored(self.floors, self.measured)
        leak = G * tilt_rate * self.f.heading_lag_s     # gravity through an attitude that late
        sig = [s_rate, math.hypot(s_ax, leak), math.hypot(s_ay, leak)]
        if theta is None:
            z, H, blocks = [rate, ax, ay], self.H_no_mag[ground], IMU_BLOCKS_NO_MAG
        else:
            z, H, blocks = [theta, rate, ax, ay], self.H[ground], IMU_BLOCKS
            # a heading sampled up to heading_lag_s late is off by up to yaw rate * lag, and levelled
            # with an attitude that late by up to tan(I) * tilt rate * lag
            lag = self.f.heading_lag_s
            sig.insert(0, math.sqrt(s_theta ** 2 + (rate * lag) ** 2 + (tilt * lag) ** 2))
        if ground:
            z.append(0.0)                          # the sideways velocity of a wheeled vehicle: none, but
            v = abs(float(x[VX]))                  # for the slip its tyres need to turn it
            sig.append(math.hypot(self.f.lateral_sigma_mps, self.f.lateral_slip_rad_per_mps2 * abs(rate) * v * v))
        R = np.diag(np.square(sig))
        angle = (0,) if theta is not None else ()
        hx = H @ x
        if ground:      # v_y - d theta_dot + k_s theta_dot v_x |v_x| = 0: the slip the filter has learnt
            vx, w, ks, d = float(x[VX]), float(x[W]), float(x[KS]), float(x[LA])    # is no skid, nor
            H = H.copy()                                                            # the sensors' swing
            H[-1, KS], H[-1, W], H[-1, VX] = w * vx * abs(vx), ks * vx * abs(vx) - d, 2.0 * ks * w * abs(vx)
            H[-1, LA] = -w
            hx[-1] = x[VY] - d * w + ks * w * vx * abs(vx)
        return Aid(np.array(z), hx, H, R), blocks, angle


def fuse_rows(ekf, t_us: int, aid: Aid, r: np.ndarray, S: np.ndarray, PHT: np.ndarray, keep: list[int],
              angle: tuple[int, ...], sensors: tuple[Sensor | None, ...]) -> ImuFusion | None:
    """Fuse the rows `keep` of a stacked measurement (those of the sensors in use); the fusion as the
    history keeps it, each row with its sensor (`sensors`, row_sensors), for a rewind (None: nothing fused).
    A rewind predicts each row as H x: the constraint, not linear, is kept linearised at this state
    (its z taken as r + H x, so that H x' at another state x' is h(x) + H (x' - x))."""
    z = aid.z
    if sensors and sensors[-1] is None:
        z = z.copy()
        z[-1] = r[-1] + float(aid.H[-1] @ ekf.x)
    if len(keep) == len(r):
        ekf.fuse(r, S, aid.H, aid.R, PHT)
        return ImuFusion(t_us, z, aid.H, aid.R, angle, sensors)
    if not keep:
        return None
    ix = np.ix_(keep, keep)
    ekf.fuse(r[keep], S[ix], aid.H[keep], aid.R[ix], PHT[:, keep])
    return ImuFusion(t_us, z[keep], aid.H[keep], aid.R[ix], angle if keep[0] == 0 else (),
                     tuple(sensors[i] for i in keep))
