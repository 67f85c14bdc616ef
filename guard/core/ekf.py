"""The paper's extended Kalman filter (11 states), the magnetometer's offset and the wheels' slip and lever arm:
INS/GNSS loosely coupled, multi-rate.

State (paper, Sec. III-B), indices in brackets:
    x[0] x, x[1] y      position east, north (m, local tangent plane)
    x[2] theta          yaw, ENU: 0 = east, counter-clockwise positive (rad)
    x[3] v_x, x[4] v_y  body velocity, forward and left (m/s)
    x[5] theta_dot      yaw rate (rad/s)
    x[6] a_x, x[7] a_y  body acceleration (specific force), forward and left (m/s^2)
    x[8] b_theta_dot, x[9] b_ax, x[10] b_ay   gyro and accelerometer biases
    x[11] b_psi         the magnetometer's heading offset (rad) [beyond the paper]: what the World
                        Magnetic Model's declination, the compass's installation and its hard iron leave,
                        learnt as autopilots learn their compass offsets. A slow random walk
                        (q_mag_offset_rad): a few degrees are learnt in the first minute of moving (the
                        GNSS course and the turns witness the heading), a fast change is not.
    x[12] k_s           a wheeled vehicle's slip (rad per m/s^2 of lateral acceleration) [beyond the
                        paper]: in a turn its tyres slide outward, v_y = -k_s theta_dot v_x |v_x|
                        (a car on tarmac: 0.005 to 0.01). Learnt in the turns, as b_psi is, so that the
                        sideways constraint holds the vehicle to its own slip and not to none.
    x[13] d             how far ahead of the point that does not slide sideways (a car's rear axle, a
                        skid-steer's turning centre) the sensors sit (m) [beyond the paper]: a point of a
                        turning body d ahead of that one moves sideways at d theta_dot, so the constraint
                        is v_y - d theta_dot + k_s theta_dot v_x |v_x| = 0. Learnt in the turns as k_s is
                        (it grows with the yaw rate alone, the slip with the speed too); an autopilot or a
                        GNSS antenna mid-car is 1 to 1.5 m ahead of the rear axle, 1 m/s sideways in a
                        tight turn, which the sideways test would otherwise read as an accelerometer's bias.

Transition with sampling time T (the paper's discrete model):
    x(k+1)  = x + T (v_x cos theta - v_y sin theta)
    y(k+1)  = y + T (v_x sin theta + v_y cos theta)
    theta(k+1) = theta + T theta_dot
    v_x(k+1) = v_x + T (a_x + c theta_dot v_y)
    v_y(k+1) = v_y + T (a_y - c theta_dot v_x)
    the rest constant, plus process noise nu(k) ~ N(0, Q).
c = 1 adds the transport term of a rotating body frame, which the paper leaves out (c = 0): an
accelerometer reads the centripetal acceleration theta_dot * v_x in a turn, and without the term
that reading would be integrated into a sideways velocity. On a straight line both agree.

Measurements (linear in the state but for GNSS velocity), each in its own file of `guard.core.aiding`:
    GNSS position  (x, y);  GNSS velocity (v_e, v_n) = R(theta) (v_x, v_y)   [beyond the paper]
    heading        theta + b_psi;  gyro theta_dot + b;  accelerometer (a_x + b_ax, a_y + b_ay)
    ground vehicles: v_y - d theta_dot + k_s theta_dot v_x |v_x| = 0, a pseudo-measurement (a wheel does
    not slide sideways but by its slip; the sensors ahead of it swing) [beyond the paper]

The sideways constraint (`lateral_sigma_mps`) ties the course over ground to the heading. Without it
a heading error is hidden by a sideways velocity (a multicopter may fly sideways, so it is off in
the air), and the GNSS course cannot witness the gyro: a gyro bias and a magnetometer attack then
look alike. The constraint is fused with every IMU sample, as if its error were new each time; a
slip lasts the whole turn, so with k_s held at 0 the filter would hold the sideways velocity near
zero against the truth, turn its heading towards the course and let its speed drift (on a simulated
car with k_s = 0.011 at 6 m/s: half the slip held, 1.7 degrees and 0.2 m/s off by a turn's end, and
the GNSS velocity at 0.996 of its threshold as the turn ends). Learnt, k_s comes within 0.002 of the
vehicle's by the end of a 10-minute drive. With it, the GNSS course is a third heading witness, the
IMU alone keeps the position through a GNSS outage (its error grows with the speed error only), and
a spoof that moves the GNSS track sideways from the heading shows at once.

Why numpy and not filterpy's ExtendedKalmanFilter: filterpy's update() computes the innovation and
fuses it in one call, and guard must see the innovation r = y - ŷ and S = H P Hᵀ + R *before*
deciding whether to fuse (a sensor judged attacked is tested but no longer fused). The halves are
written here with filterpy's symbols (x, P, F, Q, H, R, S, K) and the Joseph form; the tests check
them against filterpy and against the steady-state gain from the DARE.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_STEP_S = 0.1       # the longest step of the discrete model
N_STATES = 14
X, Y, TH, VX, VY, W, AX, AY, BW, BAX, BAY, BM, KS, LA = range(N_STATES)


def body_velocity(theta: float, ve: float, vn: float) -> tuple[float, float]:
    """v_body = R(theta)^T v_en: (forward, left) of a ground velocity (east, north)."""
    cs, sn = math.cos(theta), math.sin(theta)
    return cs * ve + sn * vn, -sn * ve + cs * vn


# the most guard tune raises the position's random walk to, times its default (guard.runtime.tune's
# position_walk); guard.runtime.position_wander says which receivers wander further than that allows
Q_POS_MAX = 20.0


@dataclass(frozen=True)
class FilterConfig:
    """Noise model of the filter (1-sigma). Process noise is given per second (random-walk rates)."""

    gnss_pos_sigma_m: float = 0.35    # the floor of a fix's position noise (guard.core.aiding.gnss)
    gnss_pos_acc_fraction: float = 0.4   # the share of the receiver's h_acc taken as its epoch-to-epoch noise
    gnss_pos_unreported_m: float = 0.5   # a receiver that reports no accuracy (per unit of HDOP, where it gives one)
    gnss_vel_sigma_mps: float = 0.06  # the floor of a fix's velocity noise
    gnss_vel_unreported_mps: float = 0.3   # a receiver that reports no speed accuracy
    gnss_h_acc_usual_max_m: float = 0.0      # the most a receiver's usual h_acc is believed to be (guard tune: twice
                                             # its clean logs' worst; guard.core.aiding.receiver); 0: unknown
    gnss_vel_acc_usual_max_mps: float = 0.0  # the same for its usual vel_acc
    heading_sigma_rad: float = 0.03   # the magnetometer heading's floor (see gyro_sigma_radps)
    heading_lag_s: float = 0.1        # how late the magnetometer and the attitude that levels the IMU may be:
                                      # adds (yaw rate * lag)^2 to the heading's R, and what a tilt that late
                                      # leaks (tan(I) and g times the roll and pitch rate * lag) to heading and accel.
                                      # The attitude is carried to each IMU sample by the gyro (guard.core.aiding.tilt),
                                      # but the leak stays: it also covers the autopilot's own tilt error in a
                                      # manoeuvre (at 0.05 the 24 external real flights raised 112 alarms against 98)
    gnss_latency_sigma_s: float = 0.0   # off. How far the receiver's latency is unknown, on a ground vehicle: a
                                      # fix's velocity is the vehicle's of up to this long before it, so this^2 a a^T,
                                      # a the mean horizontal acceleration since the last fix, joins its R
                                      # (guard.core.aiding.gnss). Measured, not taken (README, "The receiver's
                                      # latency, unknown"): at 0.15 the second family's vehicles caught their
                                      # sideways accelerometer biases in 1 of 8 against 3
    gnss_latency_sigma_air_s: float = 0.0   # off. The same on an air vehicle. Measured, not taken: at 0.15 the 47
                                      # real flights raise 168 alarms against 175, but an accelerometer bias that
                                      # starts in a turn is caught at 2.5 to 3.6 s against 1.1 to 1.4
    gnss_delay_s: float = 0.0         # the receiver's latency: a fix is compared with the state this long before it
    gyro_sigma_radps: float = 0.01    # the floor: the gyro's own noise, measured from its samples, when larger
    accel_sigma_mps2: float = 0.15    # likewise (vibration: 0.25 to 0.66 m/s^2 in two real copter flights at 25 Hz)
    lateral_sigma_mps: float = 0.1    # ground vehicles: sideways body velocity (skid), the v_y = 0 pseudo-measurement
    lateral_slip_rad_per_mps2: float = 0.02   # ... and in a turn a tyre's slip angle, per m/s^2 of lateral
                                      # acceleration: adds (this * |yaw rate * v| * v)^2 to its R (a car: 0.005 to 0.01)
    q_pos_m: float = 0.1              # position random walk, m/sqrt(s): covers correlated GNSS error (per unit of
                                      # HDOP, guard.core.aiding.gnss)
    q_heading_rad: float = 0.005
    q_vel_mps: float = 0.05
    q_yaw_rate_radps: float = 0.5     # yaw acceleration
    q_yaw_rate_air_radps: float = 3.0  # an air vehicle's: a multicopter yaws by differential torque and starts
                                      # a turn at several rad/s^2 (real copters' gyros stepped 0.35 rad/s in 20 ms)
    q_accel_mps2: float = 2.0         # jerk
    q_accel_no_imu_mps2: float = 5.0  # jerk when no IMU measures the acceleration (GNSS alone): a vehicle's own
                                      # manoeuvres between fixes (a copter tilting 10 degrees in a third of a
                                      # second: 5 m/s^3; at 3, real copters' 1 Hz telemetry alarmed every few minutes),
                                      # widened at each fix by what a fast IMU saw (`manoeuvred`)
    q_gyro_bias_radps: float = 1e-4
    q_accel_bias_mps2: float = 1e-3
    q_accel_bias_air_mps2: float = 0.01   # a vehicle that tilts: its levelled accelerometers carry the attitude's
                                      # error times g (1 degree: 0.17 m/s^2), which moves as it manoeuvres
    mag_offset_per_turn_rad: float = 0.0   # off. A compass's error depends on its heading (a hard iron left over by
                                      # its calibration turns it by B sin + C cos of the heading, a ship's deviation
                                      # curve), so a turn moves the learnt offset b_psi: its variance grows by this^2
                                      # per radian turned. Measured, not taken: 0.06 quiets the compasses of the 24
                                      # real flights first diagnosed but not of 23 found later (README), and on the
                                      # simulator a gyro bias is then caught at 2.2 to 5 s instead of 1.4 to 1.7, a
                                      # 0.01 G/s magnetometer ramp at 25 s instead of 1.8 to 4
    q_mag_offset_rad: float = 3e-4    # the magnetometer's heading offset, rad/sqrt(s): 0.4 degree in 10 minutes
    q_slip_rad_per_mps2: float = 1e-4   # k_s, the wheels' slip (rad per m/s^2 of lateral acceleration),
                                      # per sqrt(s): 0.0025 in 10 minutes (a change of surface)
    q_sensors_ahead_m: float = 1e-3   # d, the sensors ahead of the point that does not slide, m/sqrt(s):
                                      # fixed to the vehicle, 2.5 cm in 10 minutes
    use_gnss_velocity: bool = True
    centripetal: bool = True          # c in the transition; False is the paper's model as written
    p0_pos_m: float = 2.0
    p0_heading_rad: float = 0.3
    p0_vel_mps: float = 1.0
    p0_yaw_rate_radps: float = 0.1
    p0_accel_mps2: float = 1.0
    p0_gyro_bias_radps: float = 0.01
    p0_accel_bias_mps2: float = 0.2
    p0_mag_offset_rad: float = 0.1    # a compass a few degrees off (0.1 rad = 5.7 degrees, 1 sigma)
    p0_slip_rad_per_mps2: float = 0.01   # k_s: a car's 0.005 to 0.01 within 1 sigma of none
    p0_sensors_ahead_m: float = 1.0   # d: a car's autopilot or antenna, mid-car, within 1.5 sigma of the axle
    mag_offset_rad: float = 0.0       # the compass's offset, where known (guard tune): the learnt b_psi starts here
    slip_rad_per_mps2: float = 0.0    # the wheels' slip, where known (guard tune): the learnt k_s starts here
    sensors_ahead_m: float = 0.0      # the sensors ahead of the axle, where known (guard tune): the learnt d
                                      # starts here


class NavEKF:
    """x: state (14,), P: covariance (14, 14). predict() then innovation() then fuse()."""

    def __init__(self, cfg: FilterConfig, x0: np.ndarray):
        self.cfg = cfg
        self.x = np.asarray(x0, dtype=float).copy()
        self.P = np.diag(np.square([cfg.p0_pos_m, cfg.p0_pos_m, cfg.p0_heading_rad, cfg.p0_vel_mps, cfg.p0_vel_mps,
                                    cfg.p0_yaw_rate_radps, cfg.p0_accel_mps2, cfg.p0_accel_mps2,
                                    cfg.p0_gyro_bias_radps, cfg.p0_accel_bias_mps2, cfg.p0_accel_bias_mps2,
                                    cfg.p0_mag_offset_rad, cfg.p0_slip_rad_per_mps2, cfg.p0_sensors_ahead_m]))
        self.q = np.square([cfg.q_pos_m, cfg.q_pos_m, cfg.q_heading_rad, cfg.q_vel_mps, cfg.q_vel_mps,
                            cfg.q_yaw_rate_radps, cfg.q_accel_mps2, cfg.q_accel_mps2, cfg.q_gyro_bias_radps,
                            cfg.q_accel_bias_mps2, cfg.q_accel_bias_mps2, cfg.q_mag_offset_rad,
                            cfg.q_slip_rad_per_mps2, cfg.q_sensors_ahead_m])
        self.c = 1.0 if cfg.centripetal else 0.0
        self._F = np.eye(N_STATES)
        self._I = np.eye(N_STATES)
        # False: b_psi, k_s and d are held as they are, "consider" states (their rows of K zeroed): while a test is near
        # its threshold, what the filter learns of the vehicle could be an attack's doing (Monitor)
        self.learning = True
        self._held_p_th = 0.0       # the heading's variance when an IMU silence held it (unmeasured)

    def predict(self, T: float) -> None:
        """Propagate by T seconds: x = f(x), P = F P Fᵀ + Q, in steps of at most MAX_STEP_S (the
        discrete model is first order: over a long step, a 1 Hz stream's, the position would not
        see the acceleration)."""
        if T <= 0.0:
            return
        n = math.ceil(T / MAX_STEP_S - 1e-9)
        for _ in range(n):
            self._step(T / n)

    def _step(self, T: float) -> None:
        x, c, F = self.x, self.c, self._F
        px, py, th, vx, vy, w, ax, ay = x[:BW].tolist()
        cs, sn = math.cos(th), math.sin(th)
        # F = df/dx, evaluated at the prior state
        F[X, TH], F[X, VX], F[X, VY] = T * (-vx * sn - vy * cs), T * cs, -T * sn
        F[Y, TH], F[Y, VX], F[Y, VY] = T * (vx * cs - vy * sn), T * sn, T * cs
        F[TH, W] = T
        F[VX, VY], F[VX, W], F[VX, AX] = T * c * w, T * c * vy, T
        F[VY, VX], F[VY, W], F[VY, AY] = -T * c * w, -T * c * vx, T
        # x = f(x): x, y, theta, v_x, v_y written at once (python floats, the same operations)
        x[:W] = (px + T * (vx * cs - vy * sn),
                 py + T * (vx * sn + vy * cs),
                 math.remainder(th + T * w, math.tau),
                 vx + T * (ax + c * w * vy),
                 vy + T * (ay - c * w * vx))
        # P = F P Fᵀ + Q,  Q = q T (P.flat[::N_STATES + 1]: P's diagonal)
        P = self.P = F @ self.P @ F.T
        P.flat[::N_STATES + 1] += self.q * T
        if self.cfg.mag_offset_per_turn_rad and self.q[BM] > 0.0:      # off by default: one test
            # P[b_psi, b_psi] += sigma_turn^2 |theta_dot| T: b_psi moves with the heading turned
            P[BM, BM] += self.cfg.mag_offset_per_turn_rad ** 2 * abs(w) * T

    def set_heading(self, theta: float) -> None:
        """Start the heading over at theta (the magnetometer's first reading), the ground velocity kept:
        v_body = R(theta)^T v_en; the heading's uncertainty back to its initial one, uncorrelated."""
        x, c = self.x, self.cfg
        cs, sn = math.cos(x[TH]), math.sin(x[TH])
        ve, vn = x[VX] * cs - x[VY] * sn, x[VX] * sn + x[VY] * cs
        x[TH] = theta
        x[VX], x[VY] = body_velocity(theta, ve, vn)
        self.P[TH, :] = self.P[:, TH] = 0.0
        self.P[TH, TH] = c.p0_heading_rad ** 2

    def tilting(self, air: bool) -> None:
        """An air vehicle's accelerometer biases follow q_accel_bias_air_mps2 and its yaw rate
        q_yaw_rate_air_radps, a ground vehicle's q_accel_bias_mps2 and q_yaw_rate_radps (see
        FilterConfig)."""
        q = self.cfg.q_accel_bias_air_mps2 if air else self.cfg.q_accel_bias_mps2
        self.q[BAX] = self.q[BAY] = q * q
        if self.q[W] > 0.0:                     # a held heading (GNSS alone) stays held
            w = self.cfg.q_yaw_rate_air_radps if air else self.cfg.q_yaw_rate_radps
            self.q[W] = w * w

    def blow(self, dv_var: float) -> None:
        """A blow the IMU could not measure (guard.core.aiding.impact): the velocity's variance grows by
        dv_var, (m/s)^2, and the acceleration is unknown again."""
        self.P[VX, VX] += dv_var
        self.P[VY, VY] += dv_var
        for i in (AX, AY):
            self.P[i, i] = max(self.P[i, i], self.cfg.p0_accel_mps2 ** 2)

    def manoeuvred(self, da: float, T: float) -> None:
        """On GNSS alone, the IMU says the acceleration changed by da (m/s^2) over the T s since the last
        fix, in a direction nothing measures (guard.core.aiding.manoeuvre): each axis's acceleration
        variance grows by da^2 and its velocity's by (da T)^2, as if the change had come at the interval's
        start (the velocity this fix shows has taken it)."""
        dv = da * T
        self.P[AX, AX] += da * da
        self.P[AY, AY] += da * da
        self.P[VX, VX] += dv * dv
        self.P[VY, VY] += dv * dv

    def wander(self, q_pos: float) -> None:
        """The position's random walk (m/sqrt(s)): the receiver's correlated error the estimate follows."""
        self.q[X] = self.q[Y] = q_pos * q_pos

    def unmeasured(self, on: bool, air: bool, widen: bool = True) -> None:
        """An integrated IMU silent (`on`): nothing measures the heading's turns or the acceleration.
        The heading and yaw rate are held where they are, as on GNSS alone (rows and columns zeroed: a
        fix's velocity could otherwise turn the heading through correlations nothing measures, and on
        the tests' drives it turned 130 degrees in 12 s, sure of it to 27), and the acceleration is a
        random walk of the vehicle's own manoeuvres (q_accel_no_imu_mps2). Off (the IMU back): the
        heading as uncertain as at a start, its yaw rate too, the IMU's noise again; what the filter
        learnt (biases, the compass's offset, slip and lever arm) kept throughout. `widen` False: the
        heading as sure as when it was held (its compass's alarm stands: nothing would bring it back)."""
        c = self.cfg
        if on:
            self._held_p_th = float(self.P[TH, TH])
            self.x[W] = 0.0
            for i in (TH, W):
                self.P[i, :] = self.P[:, i] = 0.0
                self.q[i] = 0.0
            self.q[AX] = self.q[AY] = c.q_accel_no_imu_mps2 ** 2
            return
        held = self._held_p_th
        self.P[TH, TH] = max(held, c.p0_heading_rad ** 2) if widen else held
        self.P[W, W] = max(self.P[W, W], c.p0_yaw_rate_radps ** 2)
        self.q[TH] = c.q_heading_rad ** 2
        w = c.q_yaw_rate_air_radps if air else c.q_yaw_rate_radps
        self.q[W] = w * w
        self.q[AX] = self.q[AY] = c.q_accel_mps2 ** 2

    def hold_heading(self) -> None:
        """GNSS alone (no IMU fast enough to integrate): the heading, yaw rate and IMU biases are held
        where they are, without noise, so that the model is the linear one of a body velocity and
        acceleration in a fixed frame (a random walk in acceleration)."""
        for i in (TH, W, BW, BAX, BAY, BM, KS, LA):
            if i != TH:
                self.x[i] = 0.0
            self.P[i, :] = self.P[:, i] = 0.0
            self.q[i] = 0.0
        # nothing measures the acceleration now: its random walk is the vehicle's own manoeuvres
        self.q[AX] = self.q[AY] = self.cfg.q_accel_no_imu_mps2 ** 2

    def innovation(self, z: np.ndarray, hx: np.ndarray, H: np.ndarray, R: np.ndarray,
                   angle_rows: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """r = z - h(x) (angles wrapped), S = H P Hᵀ + R, and P Hᵀ for fuse()."""
        r = z - hx
        for i in angle_rows:
            r[i] = math.remainder(r[i], math.tau)
        PHT = self.P @ H.T
        # S = H P H' + R
        S = H @ PHT + R
        return r, S, PHT

    def fuse(self, r: np.ndarray, S: np.ndarray, H: np.ndarray, R: np.ndarray, PHT: np.ndarray) -> None:
        """x = x + K r, P = (I - K H) P (I - K H)ᵀ + K R Kᵀ (Joseph form). PHT = P Hᵀ.

        R is any covariance (the GNSS velocity's holds the receiver's latency along the acceleration,
        guard.core.aiding.gnss); a diagonal one takes the cheaper (K diag(R)) Kᵀ.
        """
        # K = P H' S^-1
        K = PHT @ np.linalg.inv(S)
        if not self.learning:
            K[BM] = K[KS] = K[LA] = 0.0     # the Joseph form below holds for any gain: P stays theirs
        self.x += K @ r
        self.x[TH] = math.remainder(self.x[TH], math.tau)
        I_KH = self._I - K @ H
        diagonal = np.count_nonzero(R) <= R.shape[0]        # its variances are never 0: nothing off them
        KRKT = (K * R.diagonal()) @ K.T if diagonal else K @ R @ K.T
        self.P = I_KH @ self.P @ I_KH.T + KRKT
