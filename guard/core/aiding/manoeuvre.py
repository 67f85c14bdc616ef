"""On GNSS alone, how much the IMU says the acceleration changed between fixes.

An IMU that is not integrated for want of a heading (an air vehicle without a compass) cannot say
where the vehicle's acceleration points. It can still say how much the acceleration changed. The levelled accelerometers read the horizontal specific force,
which is the horizontal acceleration, in the body's own yawed frame; the levelled gyro's yaw rate
turns that frame. Kept in one frame that turns with the gyro (its start arbitrary), the mean of the
readings over each fix interval is the vehicle's mean acceleration there, up to one unknown rotation,
and the length of the difference between two intervals' means does not depend on it:

    da(k)^2 = | mean_k R(psi) f  -  mean_(k-1) R(psi) f |^2 - (sx^2 + sy^2) (1/n_k + 1/n_(k-1)),
    psi = the integral of the yaw rate, sx and sy the accelerometers' measured noise (ImuNoise), n
    the samples of each interval; 0 where that is negative

The filter on GNSS alone models the acceleration as a random walk (`q_accel_no_imu_mps2`), the
vehicle's own manoeuvres between fixes; da(k)^2 is added to the variance of each of its axes at fix k
(`NavEKF.manoeuvred`), as the acceleration may have changed by that much in a direction nothing
measures. A manoeuvre the IMU saw, a plane rolling from one bank to the other (on two real ArduPlane
flights: 20 m/s^2 of turn reversed within a second, 10 m/s^2 a fix interval, where the random walk
allows 2) no longer reads as a GNSS velocity that jumped. A GNSS attack cannot move the IMU: where the
vehicle flies steadily da is mostly 0 (its accelerometers' noise taken out) and the tests are as tight
as before. What it gives up: a GNSS velocity spoof written into a hard manoeuvre is tested against the
looser model for that interval. A specific force beyond IMPACT_G (a landing, a blow) is left out of
the means; an IMU without an attitude to level it reads a tilted multicopter's thrust as no horizontal
force at all, and da stays near zero, the model as before. A stream too slow to integrate (1 to 4 Hz
telemetry) is not heard (the monitor gives it nothing): its samples are points, not means, and its
vibration and the attitude's lag read as changes of several m/s^2.
"""

from __future__ import annotations

import math

from guard.core.aiding.impact import G, IMPACT_G

MAX_DT_S = 1.0          # s: the yaw rate is integrated over no longer a step than this
MAX_APART_S = 3.0       # s: two intervals' means further apart than this are not compared


class AccelChange:
    """The IMU's horizontal specific force, averaged over each fix interval in a frame turned by the
    gyro, and the change of that mean from one interval to the next."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.psi = 0.0                          # rad: the frame's turn, integrated from the gyro
        self.t_us: int | None = None            # the last sample's time
        self.sum_e = self.sum_n = 0.0           # this interval's sums, and how many samples
        self.n = 0
        self.last: tuple[int, float, float, int] | None = None  # the last interval's end time, means
                                                # (east, north of the turning frame) and samples

    def add(self, t_us: int, ax: float, ay: float, rate: float) -> None:
        """A levelled sample: forward and left specific force (m/s^2), yaw rate (rad/s, ENU)."""
        if self.t_us is not None and t_us > self.t_us:
            self.psi += rate * min((t_us - self.t_us) / 1e6, MAX_DT_S)
        self.t_us = t_us
        if math.hypot(ax, ay) > IMPACT_G * G:
            return
        c, s = math.cos(self.psi), math.sin(self.psi)
        self.sum_e += c * ax - s * ay
        self.sum_n += s * ax + c * ay
        self.n += 1

    def change(self, t_us: int, noise_var: float) -> float:
        """At a fix: da (m/s^2) since the interval before, beyond what the accelerometers' own noise
        (noise_var: the two axes' variances of one sample, summed) makes of two means of n and m samples,
        noise_var (1/n + 1/m); and a new interval begun. 0 where either interval heard no sample, or
        they are over MAX_APART_S apart."""
        count = self.n
        if not count:
            return 0.0
        east, north = self.sum_e / count, self.sum_n / count
        last, self.last = self.last, (t_us, east, north, count)
        self.sum_e = self.sum_n = 0.0
        self.n = 0
        if last is None or t_us - last[0] > MAX_APART_S * 1e6:
            return 0.0
        d2 = (east - last[1]) ** 2 + (north - last[2]) ** 2 - noise_var * (1.0 / count + 1.0 / last[3])
        return math.sqrt(d2) if d2 > 0.0 else 0.0
