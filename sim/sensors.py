"""Sensor models: white noise, a bias drawn once per run, correlated GNSS error, and attacks.

GNSS: position error = white + first-order Gauss-Markov (real receivers' error is correlated over
tens of seconds); velocity white. IMU in body axes FRD (x forward, y right, z down): the
accelerometer measures specific force (-g on z at rest), the gyro the body rate, plus white noise
and a constant bias. Magnetometer: the World Magnetic Model's field at the start, rotated into the
body frame by the vehicle's heading, plus white noise, and where `mag_wander_deg` is set a heading
error that comes and goes, first-order Gauss-Markov over `mag_wander_tau_s` (on a multicopter the
motors' and the wiring's field turn a real compass by degrees over seconds, an error no white noise
model covers: the shipped scenario `wandering_compass`), and where `mag_iron_x`, `mag_iron_y` are set a
hard iron, a field fixed to the body that turns the heading by an amount that depends on it. It reads
with every IMU sample, or at `mag_hz` where that is set, each reading held until the next (an attack on
it shows at its next reading).

A vehicle's own sensors (guard_sim.scenario.Noise): the IMU may be mounted yawed (`imu_yaw_mount_deg`) and
read high or low (`accel_scale`, `gyro_scale`); the compass may be yawed (`mag_offset_deg`). The
true vector in body axes is turned into the sensor's axes first, then scaled, then bias and noise
are added: y = (1 + scale) R_z(a)^T x + b + w.

Attacks add to the measurement, after the noise: y_alpha(k) = C x(k) + alpha(k) + omega(k).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from pygeomag import GeoMag

from .scenario import Attack, Scenario
from .vehicle import State

G = 9.80665


@dataclass(frozen=True)
class GnssReading:
    east_m: float
    north_m: float
    vel_e_mps: float
    vel_n_mps: float


@dataclass(frozen=True)
class ImuReading:
    acc_frd: tuple[float, float, float]      # m/s^2, specific force
    gyro_frd: tuple[float, float, float]     # rad/s
    mag_frd: tuple[float, float, float]      # gauss
    mag_fresh: bool = True                   # False: the compass's last reading, held (Noise.mag_hz)


def earth_field_ned_gauss(lat_deg: float, lon_deg: float, alt_m: float, year: float) -> np.ndarray:
    """The World Magnetic Model's field (north, east, down) in gauss at a decimal year."""
    r = GeoMag().calculate(glat=lat_deg, glon=lon_deg, alt=alt_m / 1000.0, time=year)
    return np.array([r.x, r.y, r.z]) * 1e-5    # nT -> gauss


class Sensors:
    """Draws every error from its own seeded stream, so changing one rate leaves the others alone."""

    def __init__(self, scenario: Scenario, seed: int):
        self.noise = scenario.noise
        self.attacks = scenario.attacks
        gnss, imu, mag, bias = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4))
        self.rng_gnss, self.rng_imu, self.rng_mag = gnss, imu, mag
        n = self.noise
        self.gyro_bias = bias.normal(0.0, n.gyro_bias_radps, 3)
        self.accel_bias = bias.normal(0.0, n.accel_bias_mps2, 3)
        self.markov = gnss.normal(0.0, n.gnss_pos_markov_m, 2)      # (east, north)
        st = scenario.start
        self.field_ned = earth_field_ned_gauss(st.lat_deg, st.lon_deg, st.alt_m, st.year)
        self.frozen: GnssReading | None = None
        self.last_gnss_t: float | None = None
        self.course: float | None = None        # the receiver's last course over ground (gnss_course_hold_mps)
        # the compass's wandering heading error (rad), from a stream of its own: runs without it draw as before
        self.rng_wander = np.random.default_rng(np.random.SeedSequence(seed).spawn(5)[4]) \
            if n.mag_wander_deg > 0 else None
        self.wander = self.rng_wander.normal(0.0, math.radians(n.mag_wander_deg)) if self.rng_wander else 0.0
        self.last_imu_t: float | None = None
        self.mag_held: tuple[float, float, float] | None = None     # the compass's last reading (mag_hz)
        self.mag_next = 0                                          # and the number of its next reading

    def _offset(self, t_s: float, sensor: str, channel: str) -> float:
        total = 0.0
        for a in self.attacks:
            if a.sensor == sensor and a.channel == channel and a.active(t_s):
                total += attack_value(a, t_s)
        return total

    def gnss(self, t_s: float, s: State) -> GnssReading:
        n = self.noise
        if self.last_gnss_t is not None and n.gnss_pos_markov_tau_s > 0:
            # Gauss-Markov: b(k+1) = phi b(k) + sqrt(1 - phi^2) sigma w(k)
            phi = math.exp(-(t_s - self.last_gnss_t) / n.gnss_pos_markov_tau_s)
            self.markov = phi * self.markov + math.sqrt(1 - phi * phi) * self.rng_gnss.normal(0, n.gnss_pos_markov_m, 2)
        self.last_gnss_t = t_s
        white = self.rng_gnss.normal(0.0, n.gnss_pos_white_m, 2)
        vel_noise = self.rng_gnss.normal(0.0, n.gnss_vel_white_mps, 2)
        reading = GnssReading(
            east_m=s.e + self.markov[0] + white[0] + self._offset(t_s, "gnss_pos", "east"),
            north_m=s.n + self.markov[1] + white[1] + self._offset(t_s, "gnss_pos", "north"),
            vel_e_mps=s.v * math.cos(s.psi) - s.w * math.sin(s.psi) + vel_noise[0]
            + self._offset(t_s, "gnss_vel", "east"),
            vel_n_mps=s.v * math.sin(s.psi) + s.w * math.cos(s.psi) + vel_noise[1]
            + self._offset(t_s, "gnss_vel", "north"),
        )
        for a in self.attacks:
            if a.active(t_s) and a.kind == "spoof":
                tau = t_s - a.start_s
                de, dn = (1.0, 0.0) if a.channel == "east" else (0.0, 1.0)
                pos, vel = 0.5 * a.magnitude * tau * tau, a.magnitude * tau
                reading = GnssReading(reading.east_m + de * pos, reading.north_m + dn * pos,
                                      reading.vel_e_mps + de * vel, reading.vel_n_mps + dn * vel)
        reading = self._course_held(reading)
        if any(a.kind == "freeze" and a.active(t_s) for a in self.attacks):
            self.frozen = self.frozen or reading
            return self.frozen
        self.frozen = None
        return reading

    def _course_held(self, reading: GnssReading) -> GnssReading:
        """Below gnss_course_hold_mps the receiver reports its speed along the last course it had above it
        (its first fix's course is its own)."""
        hold = self.noise.gnss_course_hold_mps
        if hold <= 0.0:
            return reading
        speed = math.hypot(reading.vel_e_mps, reading.vel_n_mps)
        if speed >= hold or self.course is None:
            self.course = math.atan2(reading.vel_e_mps, reading.vel_n_mps)
            return reading
        return replace(reading, vel_e_mps=speed * math.sin(self.course), vel_n_mps=speed * math.cos(self.course))

    def imu(self, t_s: float, s: State) -> ImuReading:
        n = self.noise
        # specific force in FRD: forward accel, centripetal (left turn -> -y), -g on z
        # with a slip w (left): forward v' - omega w, left w' + omega v (FRD's y is right)
        acc = np.array([s.accel - s.omega * s.w, -(s.w_dot + s.omega * s.v), -G])
        gyro = np.array([0.0, 0.0, -s.omega])
        # in the IMU's axes, scaled: y = (1 + scale) R_z(mount)^T x + b + w
        mount = math.radians(n.imu_yaw_mount_deg)
        acc = yawed(acc, mount) * (1.0 + n.accel_scale) + self.accel_bias
        acc = acc + self.rng_imu.normal(0, n.accel_white_mps2, 3)
        gyro = yawed(gyro, mount) * (1.0 + n.gyro_scale) + self.gyro_bias
        gyro = gyro + self.rng_imu.normal(0, n.gyro_white_radps, 3)
        # field in body axes: rotate NED by the compass heading chi = pi/2 - psi
        chi = math.pi / 2 - s.psi
        fn, fe, fd = self.field_ned
        mag = np.array([fn * math.cos(chi) + fe * math.sin(chi), -fn * math.sin(chi) + fe * math.cos(chi), fd])
        # a compass yawed by the offset (and the wander) reads the heading chi + offset + wander
        if self.rng_wander is not None and self.last_imu_t is not None:
            # Gauss-Markov: b(k+1) = phi b(k) + sqrt(1 - phi^2) sigma w(k)
            phi = math.exp(-(t_s - self.last_imu_t) / n.mag_wander_tau_s)
            self.wander = phi * self.wander + math.sqrt(1 - phi * phi) * self.rng_wander.normal(
                0.0, math.radians(n.mag_wander_deg))
        self.last_imu_t = t_s
        for i, axis in enumerate("xyz"):
            acc[i] += self._offset(t_s, "accel", axis)
            gyro[i] += self._offset(t_s, "gyro", axis)
        if n.mag_hz > 0:
            # reading j at round(j * 1e6 / mag_hz) us, on the samples' own microsecond clock (a compass as
            # fast as the IMU reads at every sample), each taken by the first IMU sample at or after it
            t_us = round(t_s * 1e6)
            if self.mag_held is not None and t_us < round(self.mag_next * 1e6 / n.mag_hz):
                return ImuReading(tuple(acc), tuple(gyro), self.mag_held, mag_fresh=False)
            while round(self.mag_next * 1e6 / n.mag_hz) <= t_us:
                self.mag_next += 1
        mag = yawed(mag, math.radians(n.mag_offset_deg) + self.wander) + self.rng_mag.normal(0, n.mag_white_gauss, 3)
        if n.mag_iron_x or n.mag_iron_y:        # a field fixed to the body, a fraction of the horizontal one
            mag[:2] += math.hypot(fn, fe) * np.array([n.mag_iron_x, n.mag_iron_y])
        for i, axis in enumerate("xyz"):
            mag[i] += self._offset(t_s, "mag", axis)
        self.mag_held = tuple(mag)
        return ImuReading(tuple(acc), tuple(gyro), self.mag_held)


def yawed(v: np.ndarray, a_rad: float) -> np.ndarray:
    """Body vector v (FRD) in the axes of a sensor yawed by a (clockwise seen from above, right-handed
    about z down): R_z(a)^T v = (x cos a + y sin a, -x sin a + y cos a, z). v itself when a is 0."""
    if a_rad == 0.0:
        return v
    c, s = math.cos(a_rad), math.sin(a_rad)
    return np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])


def attack_value(a: Attack, t_s: float) -> float:
    """alpha(t) of one attack on its channel (step, bias: constant; ramp: linear in time)."""
    if a.kind in ("step", "bias"):
        return a.magnitude
    if a.kind == "ramp":
        return a.magnitude * (t_s - a.start_s)
    return 0.0      # freeze and spoof act on the whole fix, in Sensors.gnss
