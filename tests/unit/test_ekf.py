"""The EKF's math against independent oracles.

- predict(): the transition written out here from the module docstring (the paper's discrete model
  plus the transport term c), its central-difference Jacobian, and Q = diag(q^2) T from the config.
- innovation() + fuse(): filterpy's ExtendedKalmanFilter.update on the same prior, z, H, R.
- a linear sub-case (theta = 0, yaw rate 0, constant speed): the converged a-priori covariance and
  the gain equal the stabilising solution of the discrete algebraic Riccati equation (scipy).
- P stays symmetric positive definite over many random steps.
"""

import math

import numpy as np
import pytest
import scipy.linalg
from filterpy.kalman import ExtendedKalmanFilter

from guard.core.aiding.gnss import H_POS, gnss_velocity_model
from guard.core.aiding.imu import H_IMU, H_IMU_NO_MAG, ImuAiding
from guard.core.ekf import AX, AY, BAX, BAY, BM, BW, KS, LA, N_STATES, TH, VX, VY, W, X, Y, FilterConfig, NavEKF


# -- oracles written from the docstring -------------------------------------------------------------
def transition(x: np.ndarray, T: float, c: float) -> np.ndarray:
    """x(k+1) = f(x(k)), the module docstring's equations, theta left unwrapped."""
    x = np.asarray(x, dtype=float)
    th, vx, vy, w = x[TH], x[VX], x[VY], x[W]
    out = x.copy()
    out[X] = x[X] + T * (vx * np.cos(th) - vy * np.sin(th))
    out[Y] = x[Y] + T * (vx * np.sin(th) + vy * np.cos(th))
    out[TH] = th + T * w
    out[VX] = vx + T * (x[AX] + c * w * vy)
    out[VY] = vy + T * (x[AY] - c * w * vx)
    return out


def numerical_jacobian(f, x: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """Central differences: J[:, j] = (f(x + eps e_j) - f(x - eps e_j)) / (2 eps)."""
    fx = f(x)
    J = np.zeros((fx.size, x.size))
    for j in range(x.size):
        d = np.zeros(x.size)
        d[j] = eps
        J[:, j] = (f(x + d) - f(x - d)) / (2.0 * eps)
    return J


def process_noise(cfg: FilterConfig, T: float) -> np.ndarray:
    """Q = diag(q^2) T, q the random-walk rates of the config, in state order."""
    q = [cfg.q_pos_m, cfg.q_pos_m, cfg.q_heading_rad, cfg.q_vel_mps, cfg.q_vel_mps, cfg.q_yaw_rate_radps,
         cfg.q_accel_mps2, cfg.q_accel_mps2, cfg.q_gyro_bias_radps, cfg.q_accel_bias_mps2, cfg.q_accel_bias_mps2,
         cfg.q_mag_offset_rad, cfg.q_slip_rad_per_mps2, cfg.q_sensors_ahead_m]
    return np.diag(np.square(q)) * T


def random_state(rng: np.random.Generator) -> np.ndarray:
    x = rng.normal(0.0, 1.0, N_STATES)
    x[[X, Y]] = rng.uniform(-500.0, 500.0, 2)
    x[TH] = rng.uniform(-2.5, 2.5)          # far enough from +-pi that T*theta_dot does not wrap
    x[[VX, VY]] = rng.uniform(-15.0, 15.0, 2)
    x[W] = rng.uniform(-1.0, 1.0)
    x[[BW, BAX, BAY]] *= 0.05
    x[KS] = rng.uniform(0.0, 0.02)
    x[LA] = rng.uniform(-0.5, 1.5)
    return x


def random_spd(rng: np.random.Generator, n: int = N_STATES) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T / n + np.diag(rng.uniform(0.01, 1.0, n))


def wrap(a):
    return np.remainder(np.asarray(a) + np.pi, 2.0 * np.pi) - np.pi


def innovate_and_fuse(ekf: NavEKF, z, hx, H, R, angle_rows=()):
    """innovation() then fuse() as the core calls them; whatever innovation() returns after (r, S)
    (P Hᵀ, kept for fuse) is handed back to fuse(). Returns r and S."""
    r, S, *kept = ekf.innovation(np.asarray(z, dtype=float), hx, H, R, angle_rows)
    ekf.fuse(r, S, H, R, *kept)
    return r, S


R_IMU_CFG = FilterConfig()
R_IMU = np.diag(np.square([R_IMU_CFG.heading_sigma_rad, R_IMU_CFG.gyro_sigma_radps,
                           R_IMU_CFG.accel_sigma_mps2, R_IMU_CFG.accel_sigma_mps2]))
R_POS = np.eye(2) * R_IMU_CFG.gnss_pos_sigma_m ** 2
R_VEL = np.eye(2) * R_IMU_CFG.gnss_vel_sigma_mps ** 2


# -- predict ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("centripetal", [True, False])
def test_predict_matches_transition_and_numerical_jacobian(centripetal):
    cfg = FilterConfig(centripetal=centripetal)
    c = 1.0 if centripetal else 0.0
    rng = np.random.default_rng(1 if centripetal else 2)
    for _ in range(50):
        x0, T = random_state(rng), rng.uniform(0.001, 0.1)         # one step of the discrete model
        P0 = random_spd(rng)
        ekf = NavEKF(cfg, x0)
        ekf.P = P0.copy()
        ekf.predict(T)

        # x after predict = the docstring's transition
        np.testing.assert_allclose(ekf.x, transition(x0, T, c), rtol=0, atol=1e-12)
        # F = df/dx at the prior state (central differences of the oracle transition)
        J = numerical_jacobian(lambda v: transition(v, T, c), x0)
        np.testing.assert_allclose(ekf._F, J, rtol=0, atol=1e-7)
        # P = F P F' + Q, with Q = diag(q^2) T
        np.testing.assert_allclose(ekf.P, J @ P0 @ J.T + process_noise(cfg, T), rtol=1e-7, atol=1e-7)


def test_centripetal_term_only_couples_turning_motion():
    """c = 0 is the paper's model: the body velocities ignore the yaw rate."""
    x0 = np.zeros(N_STATES)
    x0[VX], x0[VY], x0[W] = 10.0, 1.0, 0.2
    on, off = NavEKF(FilterConfig(centripetal=True), x0), NavEKF(FilterConfig(centripetal=False), x0)
    on.predict(0.1), off.predict(0.1)
    assert off.x[VX] == pytest.approx(10.0) and off.x[VY] == pytest.approx(1.0)
    assert on.x[VX] == pytest.approx(10.0 + 0.1 * 0.2 * 1.0)
    assert on.x[VY] == pytest.approx(1.0 - 0.1 * 0.2 * 10.0)


def test_predict_wraps_heading():
    x0 = np.zeros(N_STATES)
    x0[TH], x0[W] = math.radians(179.0), math.radians(20.0)
    ekf = NavEKF(FilterConfig(), x0)
    ekf.predict(0.1)
    assert ekf.x[TH] == pytest.approx(math.radians(-179.0))


def test_a_long_predict_is_steps_of_at_most_max_step():
    """A 1 Hz stream's second is ten steps of 0.1 s, as ten calls would be, not one first-order step."""
    rng = np.random.default_rng(5)
    x0, P0 = random_state(rng), random_spd(rng)
    one, ten = NavEKF(FilterConfig(), x0), NavEKF(FilterConfig(), x0)
    one.P, ten.P = P0.copy(), P0.copy()
    one.predict(1.0)
    for _ in range(10):
        ten.predict(0.1)
    np.testing.assert_allclose(one.x, ten.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(one.P, ten.P, rtol=1e-12, atol=1e-12)


def test_predict_ignores_non_positive_step():
    rng = np.random.default_rng(3)
    ekf = NavEKF(FilterConfig(), random_state(rng))
    x, P = ekf.x.copy(), ekf.P.copy()
    ekf.predict(0.0)
    ekf.predict(-0.1)
    np.testing.assert_array_equal(ekf.x, x)
    np.testing.assert_array_equal(ekf.P, P)


# -- innovation and fuse against filterpy -----------------------------------------------------------
def filterpy_update(x, P, z, Hjac, hx, R, residual=np.subtract):
    kf = ExtendedKalmanFilter(dim_x=N_STATES, dim_z=len(z))
    kf.x, kf.P = x.copy(), P.copy()
    kf.update(np.asarray(z, dtype=float), HJacobian=Hjac, Hx=hx, R=R, residual=residual)
    return kf


def guard_update(x, P, z, hx, H, R, angle_rows=()):
    ekf = NavEKF(FilterConfig(), x)
    ekf.P = P.copy()
    r, S = innovate_and_fuse(ekf, z, hx, H, R, angle_rows)
    return ekf, r, S


@pytest.mark.parametrize("name, H, R", [("gnss_pos", H_POS, R_POS), ("imu", H_IMU, R_IMU),
                                        ("imu_no_mag", H_IMU_NO_MAG, R_IMU[1:, 1:]),
                                        ("stacked", np.vstack([H_POS, H_IMU]), scipy.linalg.block_diag(R_POS, R_IMU))])
def test_linear_update_matches_filterpy(name, H, R):
    rng = np.random.default_rng(10)
    for _ in range(30):
        x, P = random_state(rng), random_spd(rng)
        z = H @ x + rng.normal(0.0, 1.0, H.shape[0]) * np.sqrt(np.diag(R)) * 3.0
        ekf, r, S = guard_update(x, P, z, H @ x, H, R)
        kf = filterpy_update(x, P, z, lambda v: H, lambda v: H @ v, R)
        np.testing.assert_allclose(r, kf.y, rtol=0, atol=1e-12)
        np.testing.assert_allclose(S, kf.S, rtol=1e-12, atol=1e-12)
        d = ekf.x - kf.x
        d[TH] = math.remainder(d[TH], math.tau)     # guard keeps the heading in (-pi, pi]
        np.testing.assert_allclose(d, 0.0, rtol=0, atol=1e-10)
        np.testing.assert_allclose(ekf.P, kf.P, rtol=0, atol=1e-10)


def test_gnss_velocity_jacobian_is_the_derivative_of_h():
    rng = np.random.default_rng(11)
    for _ in range(30):
        x = random_state(rng)
        hx, H = gnss_velocity_model(x)
        th = x[TH]
        # (v_e, v_n) = R(theta) (v_x, v_y)
        Rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        np.testing.assert_allclose(hx, Rot @ x[[VX, VY]], rtol=0, atol=1e-12)
        J = numerical_jacobian(lambda v: gnss_velocity_model(v)[0], x)
        np.testing.assert_allclose(H, J, rtol=0, atol=1e-8)


def test_gnss_velocity_update_matches_filterpy():
    rng = np.random.default_rng(12)
    for _ in range(30):
        x, P = random_state(rng), random_spd(rng)
        hx, H = gnss_velocity_model(x)
        z = hx + rng.normal(0.0, 0.3, 2)
        ekf, r, S = guard_update(x, P, z, hx, H, R_VEL)
        kf = filterpy_update(x, P, z, lambda v: gnss_velocity_model(v)[1], lambda v: gnss_velocity_model(v)[0], R_VEL)
        np.testing.assert_allclose(r, kf.y, rtol=0, atol=1e-12)
        np.testing.assert_allclose(S, kf.S, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ekf.x, kf.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(ekf.P, kf.P, rtol=0, atol=1e-10)


# -- angle wrap --------------------------------------------------------------------------------------
def test_heading_innovation_wraps():
    x = np.zeros(N_STATES)
    x[TH] = math.radians(-179.0)
    ekf = NavEKF(FilterConfig(), x)
    H = H_IMU[:1]
    r = ekf.innovation(np.array([math.radians(179.0)]), H @ ekf.x, H, R_IMU[:1, :1], angle_rows=(0,))[0]
    assert r[0] == pytest.approx(math.radians(-2.0), abs=1e-12)


def test_heading_update_across_pi_matches_filterpy_with_wrapped_residual():
    """The update pulls -179 deg towards +179 deg across +-180, and the state stays in (-pi, pi]."""
    rng = np.random.default_rng(13)
    x, P = random_state(rng), random_spd(rng)
    x[TH], x[BM] = math.radians(-179.0), 0.0
    z = H_IMU @ x
    z[0] = math.radians(179.0)
    ekf, r, _ = guard_update(x, P, z, H_IMU @ x, H_IMU, R_IMU, angle_rows=(0,))
    kf = filterpy_update(x, P, z, lambda v: H_IMU, lambda v: H_IMU @ v, R_IMU,
                         residual=lambda a, b: np.concatenate([wrap(a[:1] - b[:1]), a[1:] - b[1:]]))
    assert r[0] == pytest.approx(math.radians(-2.0))
    assert -math.pi < ekf.x[TH] <= math.pi
    step = wrap(ekf.x[TH] - x[TH])                   # moved the short way, towards -181 = +179 deg
    assert math.radians(-2.0) < step < 0.0
    np.testing.assert_allclose(wrap(ekf.x[TH] - kf.x[TH]), 0.0, atol=1e-12)
    keep = [i for i in range(N_STATES) if i != TH]
    np.testing.assert_allclose(ekf.x[keep], kf.x[keep], rtol=0, atol=1e-10)
    np.testing.assert_allclose(ekf.P, kf.P, rtol=0, atol=1e-10)


# -- steady state against the DARE ------------------------------------------------------------------
T_DARE = 0.1
V0 = 5.0
N_PAPER = 11                # the paper's states: all but the compass offset, the wheels' slip and lever arm


def PAPER_ONLY(centripetal: bool) -> FilterConfig:
    return FilterConfig(centripetal=centripetal, p0_mag_offset_rad=0.0, q_mag_offset_rad=0.0,
                        p0_slip_rad_per_mps2=0.0, q_slip_rad_per_mps2=0.0, p0_sensors_ahead_m=0.0,
                        q_sensors_ahead_m=0.0)


def run_to_steady_state(centripetal: bool, v0: float, T: float = T_DARE, tol: float = 1e-14, max_steps: int = 50_000):
    """Drive the guard filter along a straight line east at v0 (theta = 0, yaw rate 0, ax = 0).

    The same sequence as the core when an IMU sample and a GNSS fix share a time stamp: predict(T),
    then the IMU block (heading, gyro, accel x/y) in one stacked update, then GNSS position. The
    measurements are exact (z = h(x)), so r = 0, x follows the straight line, F is constant and
    the filter is the time-invariant Kalman filter of (F, C, Q, R). Returns the converged
    a-priori and a-posteriori P.
    """
    x0 = np.zeros(N_STATES)
    x0[VX] = v0
    # the compass offset held at 0, without noise: on a straight line in the air it is not observable
    # (a heading error is a sideways velocity), so the paper's 11 states alone have a steady state
    ekf = NavEKF(PAPER_ONLY(centripetal), x0)
    prior = None
    for _ in range(max_steps):
        ekf.predict(T)
        if prior is not None and np.max(np.abs(ekf.P - prior)) < tol * np.max(np.abs(ekf.P)):
            break
        prior = ekf.P.copy()
        for H, R, angles in ((H_IMU, R_IMU, (0,)), (H_POS, R_POS, ())):
            innovate_and_fuse(ekf, H @ ekf.x, H @ ekf.x, H, R, angles)
    else:
        pytest.fail("P did not converge")
    assert ekf.x[TH] == 0.0 and ekf.x[W] == 0.0 and ekf.x[VY] == 0.0 and ekf.x[VX] == v0
    prior = ekf.P.copy()
    for H, R, angles in ((H_IMU, R_IMU, (0,)), (H_POS, R_POS, ())):
        innovate_and_fuse(ekf, H @ ekf.x, H @ ekf.x, H, R, angles)
    return prior, ekf.P.copy()


def dare_filter(A, C, Q, R):
    """A-priori steady-state P of the Kalman filter, its gain K and a-posteriori P.

    scipy solves X = A' X A - A' X B (R + B' X B)^-1 B' X A + Q; the filter's Riccati equation is
    the dual, P = A P A' - A P C' (C P C' + R)^-1 C P A' + Q, hence a = A', b = C'.
    """
    P = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
    K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    return P, K, (np.eye(len(A)) - K @ C) @ P


def assert_rel_close(actual, desired, rtol):
    scale = np.sqrt(np.outer(np.diag(desired), np.diag(desired)))     # compare each entry to its sigmas
    assert np.max(np.abs(actual - desired) / scale) < rtol


@pytest.fixture(scope="module")
def steady():
    return {c: run_to_steady_state(c, V0) for c in (True, False)}


@pytest.mark.parametrize("centripetal", [True, False])
def test_steady_state_axis_subsystem_matches_dare(steady, centripetal):
    """Along x: position, velocity, acceleration and accelerometer bias form a decoupled LTI system.

    x(k+1) = x + T v_x, v_x(k+1) = v_x + T a_x, a_x and b_ax constant; GNSS measures x, the
    accelerometer a_x + b_ax. With theta = 0, v_y = 0 and theta_dot = 0 every cross term of F into
    this block vanishes, and P0 is diagonal, so the block evolves on its own.
    """
    cfg, T = FilterConfig(centripetal=centripetal), T_DARE
    idx = [X, VX, AX, BAX]
    A = np.array([[1.0, T, 0, 0], [0, 1.0, T, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])
    C = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 1.0]])
    Q = np.diag(np.square([cfg.q_pos_m, cfg.q_vel_mps, cfg.q_accel_mps2, cfg.q_accel_bias_mps2])) * T
    R = np.diag([cfg.gnss_pos_sigma_m ** 2, cfg.accel_sigma_mps2 ** 2])
    P_dare, K_dare, P_post_dare = dare_filter(A, C, Q, R)

    prior, post = steady[centripetal]
    sub = np.ix_(idx, idx)
    assert_rel_close(prior[sub], P_dare, 1e-6)
    assert_rel_close(post[sub], P_post_dare, 1e-6)
    # the gain of the block, from the converged guard prior (the IMU and GNSS rows touching it)
    Pk = prior[sub]
    K = Pk @ C.T @ np.linalg.inv(C @ Pk @ C.T + R)
    np.testing.assert_allclose(K, K_dare, rtol=1e-6, atol=1e-9)
    # and nothing else leaks into the block
    others = [i for i in range(N_STATES) if i not in idx]
    assert np.max(np.abs(prior[np.ix_(idx, others)])) == 0.0


@pytest.mark.parametrize("centripetal", [True, False])
def test_steady_state_full_filter_matches_dare(steady, centripetal):
    """The paper's 11 states on the straight line: F is constant (written out here from the docstring).

    At theta = 0, theta_dot = 0, v_y = 0 and v_x = V0 the Jacobian couples heading into north
    (T V0) and, with the transport term, yaw rate into v_y (-c T V0).
    """
    cfg, T, c = FilterConfig(centripetal=centripetal), T_DARE, 1.0 if centripetal else 0.0
    A = np.eye(N_PAPER)
    A[X, VX] = A[Y, VY] = A[TH, W] = A[VX, AX] = A[VY, AY] = T
    A[Y, TH] = T * V0
    A[VY, W] = -c * T * V0
    C = np.vstack([H_IMU, H_POS])[:, :N_PAPER]
    R = scipy.linalg.block_diag(R_IMU, R_POS)
    P_dare, K_dare, P_post_dare = dare_filter(A, C, process_noise(cfg, T)[:N_PAPER, :N_PAPER], R)

    prior, post = (p[:N_PAPER, :N_PAPER] for p in steady[centripetal])
    assert_rel_close(prior, P_dare, 1e-6)
    assert_rel_close(post, P_post_dare, 1e-6)
    K = prior @ C.T @ np.linalg.inv(C @ prior @ C.T + R)
    np.testing.assert_allclose(K, K_dare, rtol=1e-6, atol=1e-9)


# -- numerical health ---------------------------------------------------------------------------------
def test_P_stays_symmetric_positive_definite():
    """10,000 random steps: predict by a random T, then fuse a random subset of the sensors."""
    rng = np.random.default_rng(42)
    cfg = FilterConfig()
    truth = np.zeros(N_STATES)
    truth[VX] = 8.0
    truth[KS] = 0.01
    ekf = NavEKF(cfg, truth + rng.normal(0.0, 0.5, N_STATES) * [2, 2, 0.3, 1, 1, 0.1, 1, 1, 0.01, 0.1, 0.1, 0.05, 0.005,
                                                              0.5])
    ground = ImuAiding(cfg)
    for step in range(10_000):
        T = rng.uniform(0.001, 0.3)
        # a truth that turns and accelerates a little, kept bounded
        truth[W] = 0.3 * math.sin(step / 300.0)
        truth[AX] = 0.5 * math.sin(step / 170.0) - 0.05 * (truth[VX] - 8.0)
        truth = transition(truth, T, 1.0)
        truth[TH] = wrap(truth[TH])
        ekf.predict(T)
        which = rng.integers(0, 6)
        if which == 0:
            H, R = H_POS, R_POS
            z = H @ truth + rng.normal(0.0, cfg.gnss_pos_sigma_m, 2)
            innovate_and_fuse(ekf, z, H @ ekf.x, H, R)
        elif which == 1:
            hz, _ = gnss_velocity_model(truth)
            hx, H = gnss_velocity_model(ekf.x)
            R = R_VEL
            innovate_and_fuse(ekf, hz + rng.normal(0.0, cfg.gnss_vel_sigma_mps, 2), hx, H, R)
        elif which == 2:
            H, R = H_IMU, R_IMU
            z = H @ truth + rng.normal(0.0, 1.0, 4) * np.sqrt(np.diag(R))
            innovate_and_fuse(ekf, z, H @ ekf.x, H, R, angle_rows=(0,))
        elif which == 3:
            H, R = H_IMU_NO_MAG, R_IMU[1:, 1:]
            z = H @ truth + rng.normal(0.0, 1.0, 3) * np.sqrt(np.diag(R))
            innovate_and_fuse(ekf, z, H @ ekf.x, H, R)
        elif which == 4:                               # a wheeled vehicle's, with its slip's constraint
            z = H_IMU @ truth + rng.normal(0.0, 1.0, 4) * np.sqrt(np.diag(R_IMU))
            aid, _, angle = ground.measurement(ekf.x, z[0], z[1], z[2], z[3], True)
            innovate_and_fuse(ekf, aid.z, aid.hx, aid.H, aid.R, angle_rows=angle)
        else:
            continue                                   # predict only: P grows
        P = ekf.P
        assert np.max(np.abs(P - P.T)) <= 1e-12 * np.max(np.abs(P)), step
        np.linalg.cholesky(P)                          # raises if not positive definite
        assert np.all(np.isfinite(ekf.x))
    # and the filter tracked the truth, so the states used in F stayed sensible
    assert abs(ekf.x[X] - truth[X]) < 5.0 and abs(ekf.x[Y] - truth[Y]) < 5.0


# -- the wheels' slip -----------------------------------------------------------------------------------
def test_the_slip_constraint_is_linearised_at_the_state():
    """Ground vehicles: h(x) = v_y - d theta_dot + k_s theta_dot v_x |v_x| (the sideways velocity less
    the sensors' swing ahead of the axle and the slip the filter has learnt); its row of H is the
    derivative of h, forwards and in reverse."""
    rng = np.random.default_rng(21)
    aiding = ImuAiding(FilterConfig())

    def h(x):
        return x[VY] - x[LA] * x[W] + x[KS] * x[W] * x[VX] * abs(x[VX])
    for _ in range(50):
        x = random_state(rng)
        aid, _, _ = aiding.measurement(x, 0.1, x[W], 0.0, 0.0, True)
        assert aid.z[-1] == 0.0 and aid.hx[-1] == pytest.approx(h(x), abs=1e-12)
        np.testing.assert_allclose(aid.H[-1], numerical_jacobian(lambda v: np.array([h(v)]), x)[0],
                                   rtol=0, atol=1e-6)
        np.testing.assert_array_equal(aid.H[:-1], H_IMU)            # the sensors' rows are linear


def test_a_rewind_re_fuses_the_constraint_as_it_was_linearised():
    """The history keeps each IMU fusion as (z, H), and a rewind predicts each row as H x. The
    constraint is not linear (h(x) is not H x where the slip, the lever arm and the yaw rate are
    not 0): its z is kept as r + H x, so that at the state it was fused at a rewind finds the same
    innovation, and elsewhere h linearised there."""
    from guard.core.aiding.imu import IMU_BLOCKS, fuse_rows, row_sensors
    rng = np.random.default_rng(8)
    aiding = ImuAiding(FilterConfig())
    for _ in range(20):
        x = random_state(rng)
        ekf = NavEKF(FilterConfig(), x)
        aid, _, angle = aiding.measurement(ekf.x, 0.1, x[W] + 0.01, 0.0, 0.3, True)
        r, S, PHT = ekf.innovation(aid.z, aid.hx, aid.H, aid.R, angle_rows=angle)
        kept = fuse_rows(ekf, 0, aid, r, S, PHT, list(range(len(r))), angle, row_sensors(IMU_BLOCKS, True))
        assert kept.z[-1] - kept.H[-1] @ x == pytest.approx(r[-1], abs=1e-9)
        np.testing.assert_array_equal(kept.z[:-1], aid.z[:-1])      # the sensors' rows as they were


def test_the_learnt_vehicle_is_held_while_a_test_is_near_its_threshold():
    """learning False: the compass offset, the wheels' slip and the sensors' place ahead of the axle are
    consider states, their gains zeroed; the rest of the state is updated as before."""
    x0 = np.zeros(N_STATES)
    x0[VX], x0[W] = 8.0, 0.3
    aiding = ImuAiding(FilterConfig())
    moved = {}
    for learning in (True, False):
        ekf = NavEKF(FilterConfig(), x0)
        ekf.learning = learning
        aid, _, angle = aiding.measurement(ekf.x, 0.05, 0.3, 0.0, 2.4, True)
        aid.z[-1] = 0.0
        innovate_and_fuse(ekf, aid.z, aid.hx + np.r_[0.0, 0.0, 0.0, 0.0, 0.3], aid.H, aid.R, angle_rows=angle)
        moved[learning] = ekf.x - x0
    assert moved[True][KS] != 0.0 and moved[True][BM] != 0.0 and moved[True][LA] != 0.0
    assert moved[False][KS] == 0.0 and moved[False][BM] == 0.0 and moved[False][LA] == 0.0
    assert moved[False][VY] != 0.0


def test_an_air_vehicle_yaws_faster_than_a_car_and_a_held_heading_stays_held():
    """The yaw rate's random walk: q_yaw_rate_air_radps in the air, q_yaw_rate_radps on wheels; a
    filter on GNSS alone (heading held) keeps it at 0 whatever it flies as."""
    cfg = FilterConfig()
    ekf = NavEKF(cfg, np.zeros(N_STATES))
    ekf.tilting(True)
    assert ekf.q[W] == pytest.approx(cfg.q_yaw_rate_air_radps ** 2) and cfg.q_yaw_rate_air_radps > cfg.q_yaw_rate_radps
    ekf.tilting(False)
    assert ekf.q[W] == pytest.approx(cfg.q_yaw_rate_radps ** 2)
    ekf.hold_heading()
    ekf.tilting(True)
    assert ekf.q[W] == 0.0


# -- the two knobs measured and left off (FilterConfig) ---------------------------------------------
def test_mag_offset_per_turn_grows_b_psi_with_the_angle_turned_only():
    """mag_offset_per_turn_rad: b_psi's variance grows by its square per radian turned, whatever the
    step; nothing while the heading holds, nothing when off (the default), nothing on GNSS alone."""
    x0 = np.zeros(N_STATES)
    x0[W] = 0.5
    per = 0.06
    grown = []
    for steps in (1, 10):
        on, off = NavEKF(FilterConfig(mag_offset_per_turn_rad=per), x0), NavEKF(FilterConfig(), x0)
        for ekf in (on, off):
            for _ in range(steps):
                ekf.predict(1.0 / steps)
        grown.append(on.P[BM, BM] - off.P[BM, BM])
        np.testing.assert_allclose(np.delete(np.delete(on.P, BM, 0), BM, 1),
                                   np.delete(np.delete(off.P, BM, 0), BM, 1), atol=1e-12)
    np.testing.assert_allclose(grown, per ** 2 * 0.5 * 1.0, rtol=0.05)     # 0.5 rad turned, in any steps
    still = np.zeros(N_STATES)
    on, off = NavEKF(FilterConfig(mag_offset_per_turn_rad=per), still), NavEKF(FilterConfig(), still)
    on.predict(1.0), off.predict(1.0)
    assert on.P[BM, BM] == pytest.approx(off.P[BM, BM])
    held = NavEKF(FilterConfig(mag_offset_per_turn_rad=per), x0)
    held.hold_heading()
    held.predict(1.0)
    assert held.P[BM, BM] == 0.0


def test_gnss_latency_widens_the_velocity_variance_along_the_acceleration_only():
    """A receiver's latency known to sigma_L only puts a fix's velocity up to sigma_L |a| behind, along
    the acceleration a since the last fix: R gains sigma_L^2 a a^T, its variance across a and the
    position's R untouched, and nothing without an acceleration or on the first fix."""
    from guard.core.aiding.gnss import GnssAiding
    from guard.model.samples import GnssFix
    fix = GnssFix(0, True, 0.0, 0.0, 0.0, 1.0, 2.0, 1.0, 0.2)
    x = np.zeros(N_STATES)
    a = np.array([3.0, 4.0])                   # east, north: |a| = 5
    off = GnssAiding(FilterConfig())
    on = GnssAiding(FilterConfig(gnss_latency_sigma_air_s=0.2))
    R0, R1 = off.velocity(fix, x, a, False).R, on.velocity(fix, x, a, False).R
    u, n = a / 5.0, np.array([-4.0, 3.0]) / 5.0
    assert u @ R1 @ u == pytest.approx(u @ R0 @ u + (0.2 * 5.0) ** 2)
    assert n @ R1 @ n == pytest.approx(n @ R0 @ n)
    assert on.position(fix, (0.0, 0.0), x).R[0, 0] == off.position(fix, (0.0, 0.0), x).R[0, 0]
    assert np.array_equal(on.velocity(fix, x, np.zeros(2), False).R, R0)
    assert np.array_equal(on.velocity(fix, x, None, False).R, R0)


def test_gnss_latency_is_off_by_default_and_each_vehicle_reads_its_own_key():
    from guard.core.aiding.gnss import GnssAiding
    from guard.model.samples import GnssFix
    fix = GnssFix(0, True, 0.0, 0.0, 0.0, 0.0, 10.0, 1.0, 0.2)
    x, a = np.zeros(N_STATES), np.array([0.0, 3.0])      # a turn to the north at 10 m/s east
    default = GnssAiding(FilterConfig())
    for ground in (False, True):
        assert np.array_equal(default.velocity(fix, x, a, ground).R, default.velocity(fix, x, None, ground).R)
    base = default.velocity(fix, x, None, True).R[1, 1]
    wheels, air = (GnssAiding(FilterConfig(gnss_latency_sigma_s=0.2)),
                   GnssAiding(FilterConfig(gnss_latency_sigma_air_s=0.2)))
    assert wheels.velocity(fix, x, a, True).R[1, 1] == pytest.approx(base + (0.2 * 3.0) ** 2)
    assert wheels.velocity(fix, x, a, False).R[1, 1] == pytest.approx(base)
    assert air.velocity(fix, x, a, False).R[1, 1] == pytest.approx(base + (0.2 * 3.0) ** 2)
    assert air.velocity(fix, x, a, True).R[1, 1] == pytest.approx(base)


def test_fuse_takes_a_full_measurement_covariance_whole():
    """A GNSS velocity whose R holds a latency along a diagonal acceleration: the Joseph update with
    the whole R, as filterpy's, not with its diagonal alone."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(N_STATES, N_STATES))
    P0 = A @ A.T / N_STATES + np.eye(N_STATES) * 0.1
    x0 = rng.normal(size=N_STATES) * 0.1
    H = np.zeros((2, N_STATES)); H[0, VX] = H[1, VY] = 1.0
    lag = 0.15 * np.array([2.0, 2.0])
    R = np.eye(2) * 0.06 ** 2 + np.outer(lag, lag)
    ekf = NavEKF(FilterConfig(), x0.copy())
    ekf.P = P0.copy()
    z = H @ x0 + np.array([0.3, -0.1])
    r, S, PHT = ekf.innovation(z, H @ ekf.x, H, R)
    ekf.fuse(r, S, H, R, PHT)
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + R)
    I_KH = np.eye(N_STATES) - K @ H
    expected = I_KH @ P0 @ I_KH.T + K @ R @ K.T
    assert np.allclose(ekf.P, expected, atol=1e-12)
    diagonal_only = I_KH @ P0 @ I_KH.T + (K * R.diagonal()) @ K.T
    assert not np.allclose(ekf.P, diagonal_only, atol=1e-6)


def test_the_course_witness_takes_the_velocity_noise_across_the_track():
    """The course turns with the velocity's noise across the track: a latency along a (a speed change)
    leaves it, one across (a turn) widens it."""
    from guard.core.aiding.gnss import across_track
    from guard.model.samples import GnssFix
    east = GnssFix(0, True, 0.0, 0.0, 0.0, 0.0, 10.0, 1.0, 0.2)      # moving east
    R = np.diag([0.04 + 0.25, 0.04])                                   # the latency along east
    assert across_track(R, east) == pytest.approx(0.2)
    assert across_track(np.diag([0.04, 0.04 + 0.25]), east) == pytest.approx(math.sqrt(0.29))
    still = GnssFix(0, True, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.2)
    assert across_track(R, still) == pytest.approx(math.sqrt(0.29))
