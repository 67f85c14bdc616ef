"""The vehicle: the paper's planar kinematics and a pure-pursuit controller.

True state: east e, north n (metres from the start), ENU yaw psi (0 = east, counter-clockwise),
forward speed v and yaw rate omega. By default a ground vehicle does not slip sideways, so the body
velocity is (v, 0) and, as in the paper's model,
    e' = v cos(psi),  n' = v sin(psi),  psi' = omega.
A real wheel does slip: its tyre turns the force it carries into a slip angle. With
`route.sideslip_rad_per_mps2` = k the body velocity gains a sideways part w = -k (omega v) v (left
positive: the vehicle slides outward of its turn in proportion to its lateral acceleration omega v;
a car: about 0.005 to 0.01 rad per m/s^2), its course over ground differs from its heading by
atan(w / v), and
    e' = v cos(psi) - w sin(psi),  n' = v sin(psi) + w cos(psi).
The sensors (IMU and GNSS antenna, together) sit `route.sensors_ahead_m` = d ahead of the point that
does not slide (a car's rear axle, a skid-steer's turning centre): w gains d omega, the sideways
velocity of a point of a turning rigid body; the position, velocity and specific force simulated are
that point's (its specific force from w and w' as any other).
How fast the yaw rate follows the controller: by default the yaw acceleration steps, up to
`route.max_yaw_accel_radps2`, the moment the command changes. No tyre does that, and with a slip it
would step the sideways acceleration too (w' carries the yaw acceleration times v^2). With
`route.max_yaw_jerk_radps3` = J > 0 the yaw acceleration itself moves at most J per second, towards
the fastest approach to the commanded rate that a yaw jerk of J can still stop without overshoot
(sign(e) sqrt(2 J |e|), e the rate still to go): the steering of a car, whose yaw rate follows the
wheel through the tyres' lag, and whose lateral jerk (J v) stays bounded.
The controller steers on the position it is *fed* (the GNSS fix, attacked or not, dead-reckoned
between fixes), so a GNSS attack really pulls the vehicle off its path, as in the paper's loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .scenario import Route


@dataclass
class State:
    e: float = 0.0
    n: float = 0.0
    psi: float = 0.0
    v: float = 0.0
    omega: float = 0.0
    accel: float = 0.0      # dv/dt over the last step, m/s^2
    w: float = 0.0          # sideways body velocity (left positive), m/s: the slip
    w_dot: float = 0.0      # dw/dt over the last step, m/s^2
    yaw_accel: float = 0.0  # domega/dt over the last step, rad/s^2


class Vehicle:
    """Integrates the kinematics and follows the route's waypoints."""

    def __init__(self, route: Route, heading_deg: float):
        self.route = route
        self.s = State(psi=math.radians(90.0 - heading_deg))
        self.points = [p[:2] for p in route.waypoints_m]
        self.speeds = [p[2] if len(p) == 3 else route.speed_mps for p in route.waypoints_m]
        self.leg = 0            # heading from points[leg] to points[leg + 1]
        self.done = False

    def _leg(self, i: int) -> tuple[tuple[float, float], tuple[float, float]]:
        n = len(self.points)
        return self.points[i % n], self.points[(i + 1) % n]

    def command(self, fed_e: float, fed_n: float) -> tuple[float, float]:
        """Pure pursuit from the fed position: (target speed, target yaw rate)."""
        r = self.route
        (ax, ay), (bx, by) = self._leg(self.leg)
        dx, dy = bx - ax, by - ay
        length = math.hypot(dx, dy) or 1e-9
        ux, uy = dx / length, dy / length
        along = (fed_e - ax) * ux + (fed_n - ay) * uy
        last = not r.loop and self.leg >= len(self.points) - 2
        if length - along < r.lookahead_m:
            if last:
                if length - along < 1.0 or along > length:
                    self.done = True
            else:
                self.leg += 1
                return self.command(fed_e, fed_n)
        s = min(max(along, 0.0) + r.lookahead_m, length)
        tx, ty = ax + s * ux, ay + s * uy
        alpha = math.atan2(ty - fed_n, tx - fed_e) - self.s.psi
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        speed = 0.0 if self.done else self.speeds[(self.leg + 1) % len(self.points)]
        if last:    # slow down to stop at the final waypoint
            speed = min(speed, math.sqrt(max(0.0, 2 * 0.5 * r.max_accel_mps2 * (length - along))))
        # curvature of the arc through the target: kappa = 2 sin(alpha) / L
        omega = self.s.v * 2.0 * math.sin(alpha) / r.lookahead_m
        if self.s.v < 0.5:      # turn on the spot gently before moving off
            omega = 0.3 * alpha
        lim = r.max_yaw_rate_radps
        return speed, max(-lim, min(lim, omega))

    def _yaw_step(self, dt: float, e: float) -> float:
        """The change of the yaw rate over the next dt, with e the yaw rate still to go."""
        r = self.route
        if r.max_yaw_jerk_radps3 <= 0:          # the yaw acceleration steps: reach the command if allowed
            lim = r.max_yaw_accel_radps2 * dt
            return max(-lim, min(lim, e))
        if dt <= 0:
            return 0.0
        j, a = r.max_yaw_jerk_radps3, self.s.yaw_accel
        want = math.copysign(min(math.sqrt(2.0 * j * abs(e)), r.max_yaw_accel_radps2, abs(e) / dt), e)
        return dt * max(a - j * dt, min(a + j * dt, want))

    def step(self, dt: float, speed_cmd: float, omega_cmd: float) -> None:
        """Advance the true state by dt seconds (accel and yaw acceleration limited)."""
        s, r = self.s, self.route
        dv = max(-r.max_accel_mps2 * dt, min(r.max_accel_mps2 * dt, speed_cmd - s.v))
        domega = self._yaw_step(dt, omega_cmd - s.omega)
        s.yaw_accel = domega / dt if dt > 0 else 0.0
        s.omega += domega
        v_mid = s.v + dv / 2
        w_new = -r.sideslip_rad_per_mps2 * s.omega * (s.v + dv) ** 2 + r.sensors_ahead_m * s.omega
        w_mid = (s.w + w_new) / 2
        psi_mid = s.psi + s.omega * dt / 2
        s.e += dt * (v_mid * math.cos(psi_mid) - w_mid * math.sin(psi_mid))
        s.n += dt * (v_mid * math.sin(psi_mid) + w_mid * math.cos(psi_mid))
        s.psi = math.atan2(math.sin(s.psi + s.omega * dt), math.cos(s.psi + s.omega * dt))
        s.v += dv
        s.accel = dv / dt if dt > 0 else 0.0
        s.w_dot = (w_new - s.w) / dt if dt > 0 else 0.0
        s.w = w_new
