"""An IMU noisier than the model lets its tests take: said once per sensor, with the factor.

The tests take each IMU reading's measured noise (guard.core.aiding.imu.ImuNoise) up to NOISE_CAP
times the configured floor, and no further: a jitter written into the accelerometers must not blind
the tests that are to find a bias under it. An IMU that vibrates past that is tested tighter than it
is, and an alarm on it may be the vibration, not an attack. Real PX4 copters do: their logged
`sensor_combined` reads at 13 to 73 times the accelerometers' floor (0.15 m/s^2) for much of a
flight on eight of the 47 public flights (README, "Real flights never tuned on"). The cap stays;
what the operator is told is that the model does not fit this IMU, naming the sensor and the factor,
once the mean a fusion takes has stood over the cap for SAY_S of the run: a WARNING, not an alarm.
The fix is the IMU's mounting and damping, or a floor for the vehicle (`guard tune`).
"""

from __future__ import annotations

from guard.model.events import Notice
from guard.model.sensors import Sensor

SAY_S = 5.0             # s of fusions over the cap before it is said (a take-off's jolt is not it)
MAX_STEP_S = 0.5        # a longer step between fusions is not counted (a gap is not time over it)

# the sensor of each measured channel (ax, ay, yaw rate), and how its floor is configured
CHANNELS = ((Sensor.ACCEL, "m/s^2", "accel_sigma_mps2"), (Sensor.ACCEL, "m/s^2", "accel_sigma_mps2"),
            (Sensor.GYRO, "rad/s", "gyro_sigma_radps"))


class NoiseCap:
    def __init__(self, cap: float):
        self.cap = cap
        self.over_s: dict[Sensor, float] = {}       # time each sensor's noise stood over the cap
        self.square: dict[Sensor, float] = {}       # ... and the integral of its square over that time
        self.said: set[Sensor] = set()
        self._last_us: int | None = None

    def step(self, t_us: int, sigmas: list[float], floors: tuple[float, ...]) -> list[Notice]:
        """One fusion: `sigmas` the noise of its mean (ax, ay, yaw rate; not capped), `floors` theirs."""
        dt = 0.0 if self._last_us is None else (t_us - self._last_us) / 1e6
        dt = dt if 0.0 < dt <= MAX_STEP_S else 0.0
        self._last_us = t_us
        worst: dict[Sensor, tuple[float, float, str, str]] = {}
        for (sensor, unit, key), sigma, floor in zip(CHANNELS, sigmas, floors):
            if floor > 0.0 and sigma > self.cap * floor and sigma / floor > worst.get(sensor, (0.0,))[0]:
                worst[sensor] = (sigma / floor, floor, unit, key)
        out = []
        for sensor, (_, floor, unit, key) in worst.items():
            self.over_s[sensor] = self.over_s.get(sensor, 0.0) + dt
            self.square[sensor] = self.square.get(sensor, 0.0) + dt * (worst[sensor][0] * floor) ** 2
            if self.over_s[sensor] >= SAY_S and sensor not in self.said:
                self.said.add(sensor)
                sigma = (self.square[sensor] / self.over_s[sensor]) ** 0.5     # its rms over that time
                factor = sigma / floor
                what = "accelerometers'" if sensor == Sensor.ACCEL else "gyro's"
                out.append(Notice(t_us, "warning", f"the {what} noise reads {sigma:.2g} {unit}, {factor:.0f} times "
                                  f"{key}: guard's tests take an IMU's noise up to {self.cap:g} times it, so they "
                                  f"are tighter than this IMU and its {sensor} alarms may be its vibration (see to "
                                  "its mounting and damping, or give it a floor with guard tune)"))
        return out
