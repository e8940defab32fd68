"""Magnetic capsule localization (paper 001): Appendix B's Jacobians, the force, Eq. 5 and the regime monitor
checked numerically."""

import math

import numpy as np
import pytest

from bodyslam.systems.magnetic import (MU0, ActuatorController, HallArray, Pi, Pi_star, Propulsion, RotationMonitor, Upsilon_star, field_at,
                               field_gradient, measure, measure_jacobian, process, process_jacobian, rotate,
                               rotate_inv, rotation_axis, torque_force)

PROP = Propulsion(9000.0, 17.5, 0.05, (0.0, 0.112, 0.0))
SENSORS = HallArray(np.array([[6, 0, 0], [-6, 0, 0], [0, 6, 0], [0, -6, 0], [0, 0, 6], [0, 0, -6]]) * 1e-3,
                    np.array([[0, 1, 0], [0, 0, 1], [0, 0, 1], [1, 0, 0], [1, 0, 0], [0, 1, 0]]))


def _states(n, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        Q = rng.normal(size=4)
        Q /= np.linalg.norm(Q)
        p = np.array([-0.058, 0.0, -0.1]) + rng.normal(0, 0.02, 3)
        m_a = rng.normal(size=3)
        yield np.concatenate([p, Q]), rng.normal(0, 0.01, 3), m_a * 71 / np.linalg.norm(m_a)


def _numeric(f, x, h):
    cols = []
    for j in range(len(x)):
        e = np.zeros(len(x))
        e[j] = h[j] if np.ndim(h) else h
        cols.append((f(x + e) - f(x - e)) / (2 * e[j]))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_appendix_b_jacobians_match_finite_differences(seed):
    h = np.array([1e-7] * 3 + [1e-6] * 4)
    for s, o, m_a in _states(4, seed):
        G = process_jacobian(s, o, m_a, PROP, 0.01)
        Gn = _numeric(lambda x: process(x, o, m_a, PROP, 0.01), s, h)
        np.testing.assert_allclose(G, Gn, atol=1e-6 * np.abs(Gn).max())
        H = measure_jacobian(s, o, m_a, SENSORS)
        Hn = _numeric(lambda x: measure(x, o, m_a, SENSORS), s, h)
        np.testing.assert_allclose(H, Hn, atol=1e-6 * np.abs(Hn).max())


def test_quaternion_building_blocks():
    rng = np.random.default_rng(3)
    Q, r = rng.normal(size=4), rng.normal(size=3)  # not unit: the blocks are derivatives of Eq. 27/28 as written
    np.testing.assert_allclose(Pi(r, Q), _numeric(lambda q: rotate(q, r), Q, 1e-6), atol=1e-8)
    np.testing.assert_allclose(Pi_star(r, Q), _numeric(lambda q: rotate_inv(q, r), Q, 1e-6), atol=1e-8)
    np.testing.assert_allclose(Upsilon_star(Q), _numeric(lambda v: rotate_inv(Q, v), r, 1e-6), atol=1e-8)
    Qu = Q / np.linalg.norm(Q)
    np.testing.assert_allclose(rotate_inv(Qu, rotate(Qu, r)), r, atol=1e-12)


def test_force_is_the_gradient_and_the_printed_eq17_is_not():
    for s, o, m_a in _states(5, 4):
        p, Q = s[:3] - o, s[3:]
        m_c = rotate(Q, np.array(PROP.m_c_capsule))
        grad = _numeric(lambda x: np.array([m_c @ field_at(x, m_a)]), p, 1e-7)[0]
        _, f = torque_force(p, Q, m_a, np.array(PROP.m_c_capsule))
        np.testing.assert_allclose(f, grad, rtol=1e-6, atol=1e-9 * np.abs(grad).max())
        # Eq. 17 as printed: (m_a p^T + p m_a^T + (p^T Z m_a) I) m_c with Z = I - 5 p_hat p_hat^T
        n = np.linalg.norm(p)
        Z = np.eye(3) - 5 * np.outer(p, p) / n**2
        printed = 3 * MU0 / (4 * np.pi * n**4) * (np.outer(m_a, p) + np.outer(p, m_a) + (p @ Z @ m_a) * np.eye(3)) @ m_c
        assert np.linalg.norm(printed - grad) > 0.1 * np.linalg.norm(grad)
        # the field is curl-free: its gradient is symmetric, and equals the numerical one
        np.testing.assert_allclose(field_gradient(p, m_a), _numeric(lambda x: field_at(x, m_a), p, 1e-7),
                                   atol=1e-6 * np.abs(field_gradient(p, m_a)).max())


def test_eq5_axis_makes_the_field_rotate_about_the_desired_axis():
    rng = np.random.default_rng(5)
    for _ in range(5):
        p = rng.normal(size=3) * 0.1
        w = rng.normal(size=3)
        w /= np.linalg.norm(w)
        Om = rotation_axis(p, w)
        u = np.cross(Om, [1.0, 0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(Om, u)
        for ang in np.linspace(0, 2 * np.pi, 9):  # every actuator dipole perpendicular to Omega
            b = field_at(p, 50 * (np.cos(ang) * u + np.sin(ang) * v))
            assert abs(b @ w) < 1e-9 * np.linalg.norm(b)


def test_rotation_monitor_tells_synchronous_from_step_out():
    rng = np.random.default_rng(6)
    m_c = (0.0, 0.112, 0.0)
    window = 200

    def field(lead):  # the applied field in the capsule frame at a given lead angle
        return 0.01 * np.array([0.0, math.cos(lead), math.sin(lead)])

    sync = RotationMonitor(window, m_c, smooth=25)
    flags = [sync.push(field(math.radians(35)) + rng.normal(0, 0.0016, 3)) for _ in range(600)]
    assert all(flags)  # a 35 deg lead under the paper's sensor noise: never called a step-out
    out = RotationMonitor(window, m_c, smooth=25)
    flags = [out.push(field(0.05 * k) + rng.normal(0, 0.0016, 3)) for k in range(600)]  # the field slips round
    assert not any(flags[window:])


def test_algorithm_1_slows_the_field_to_80_then_50_percent_and_restores_it():
    ctrl = ActuatorController(math.pi, np.array([-0.058, 0.0, -0.1]))
    p, x = np.array([0.1, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    o_a, axis, rate = ctrl.command(p, x, True, 0.01)
    np.testing.assert_allclose(o_a, p - ctrl.p_des_m)
    assert rate == math.pi and abs(np.linalg.norm(axis) - 1) < 1e-12
    t_r = 2 * 2 * math.pi / math.pi  # two rotations at the desired rate: 4 s
    rates = [ctrl.command(p, x, False, 0.01)[2] for _ in range(int(t_r / 0.01) + 50)]
    assert rates[0] == pytest.approx(0.8 * math.pi) and rates[-1] == pytest.approx(0.5 * math.pi)
    assert ctrl.command(p, x, True, 0.01)[2] == math.pi
