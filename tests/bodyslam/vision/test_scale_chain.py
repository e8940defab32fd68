"""Each step's scale tied to its neighbours' (bodyslam.vision.scale_chain)."""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bodyslam.steps import StepMotion, motion_from_transform, rotation_step
from bodyslam.vision.scale_chain import (MIN_LINK_POINTS, Signature, chain_factors, chained, scale_link,
                                         step_signatures)
from tests.bodyslam.vision.test_motion import CAM, R_TUBE, tube_points


def _params(R: Rotation, t) -> np.ndarray:
    """A tube fit's 10-vector with this motion (the tube's own parameters do not enter the triangulation)."""
    return np.r_[R.as_rotvec(), t, 0.0, 0.0, 0.0, 0.0]


def _three_frames(rng, scale_a=1.0, scale_b=1.0, noise_px=0.0):
    """Wall points seen from frames k-1, k, k+1 (a capsule moving 4 mm a frame down a tube, rolling) and the two
    steps' signatures when their fits read the steps ``scale_a`` and ``scale_b`` times too long."""
    Xk = tube_points(600, rng, s_range=(0.004, 0.05))  # in frame k
    Ra, ta = Rotation.from_rotvec([0.02, -0.01, 0.12]), np.array([0.0003, -0.0002, 0.004])  # frame k-1 -> k
    Rb, tb = Rotation.from_rotvec([-0.01, 0.03, -0.08]), np.array([-0.0002, 0.0004, 0.0045])  # frame k -> k+1
    X_prev = Ra.apply(Xk) + ta  # frame k in frame k-1's axes: X_prev = R X_k + t
    X_next = Rb.inv().apply(Xk - tb)
    u_prev, ok0 = CAM.project(X_prev)
    u_k, ok1 = CAM.project(Xk)
    u_next, ok2 = CAM.project(X_next)
    ok = ok0 & ok1 & ok2 & (X_prev[:, 2] > 0) & (X_next[:, 2] > 0) & (Xk[:, 2] > 0)
    u_prev, u_k, u_next = u_prev[ok], u_k[ok], u_next[ok]
    if noise_px:
        u_prev = u_prev + rng.normal(0, noise_px, u_prev.shape)
        u_next = u_next + rng.normal(0, noise_px, u_next.shape)
    sa = step_signatures(u_prev, u_k, _params(Ra, ta * scale_a), CAM)
    sb = step_signatures(u_k, u_next, _params(Rb, tb * scale_b), CAM)
    return sa, sb, Xk[ok]


@pytest.mark.parametrize("scale_a, scale_b", [(1.0, 1.0), (1.0, 1.3), (1.25, 0.8)])
def test_the_link_is_the_ratio_of_the_two_steps_scales(scale_a, scale_b):
    """Triangulated with each step's own motion, the points of their shared frame lie ``scale`` times deeper, so
    the link is log(scale_b / scale_a) -- to 1e-6 without noise (the same rays in both), 0.02 with 0.3 px."""
    sa, sb, Xk = _three_frames(np.random.default_rng(1), scale_a, scale_b)
    # the depths are the true ones times the step's scale (frame k's points: step a's frame 2, step b's frame 1)
    assert len(sb[0].log_depth) > 100
    u_k, _ = CAM.project(Xk)
    _, i = cKDTree(u_k).query(sb[0].pts_px)
    assert np.allclose(np.exp(sb[0].log_depth), scale_b * np.linalg.norm(Xk[i], axis=1), rtol=2e-6)
    link, sd = scale_link(sa[1], sb[0])
    assert link == pytest.approx(math.log(scale_b / scale_a), abs=2e-6)  # the points rounded to 1e-3 px
    assert 0 < sd < 0.2
    sa, sb, _ = _three_frames(np.random.default_rng(2), scale_a, scale_b, noise_px=0.3)
    link, sd = scale_link(sa[1], sb[0])
    assert link == pytest.approx(math.log(scale_b / scale_a), abs=0.02)


def test_no_link_without_shared_points_or_with_an_implausible_ratio():
    sa, sb, _ = _three_frames(np.random.default_rng(3))
    assert all(map(math.isnan, scale_link(None, sb[0])))
    few = Signature(sb[0].pts_px[:MIN_LINK_POINTS - 1], sb[0].log_depth[:MIN_LINK_POINTS - 1])
    assert all(map(math.isnan, scale_link(sa[1], few)))
    elsewhere = Signature(sb[0].pts_px + 1000.0, sb[0].log_depth)  # no point within a pixel
    assert all(map(math.isnan, scale_link(sa[1], elsewhere)))
    deeper = Signature(sb[0].pts_px, sb[0].log_depth + 3.0)  # a factor of 20: a failed fit, not a scale
    assert all(map(math.isnan, scale_link(sa[1], deeper)))
    # a JSON round trip (a batch chunk hands its seam points on) keeps the link
    back = Signature.from_json(sb[0].to_json())
    assert scale_link(sa[1], back) == scale_link(sa[1], sb[0])  # exactly: chunking must not change results


def test_a_poor_step_between_good_ones_is_pulled_to_what_its_links_say():
    """Five steps of 3 mm; the middle one read 1.5x too long with a poor fit (20% relative 1-sigma), its
    neighbours well fitted (1%); its links say +log 1.5 in and -log 1.5 out. The chain brings it most of the way back
    and leaves the good ones within a few percent."""
    d = np.array([0.003, 0.003, 0.0045, 0.003, 0.003])
    sig = np.array([0.00003, 0.00003, 0.0009, 0.00003, 0.00003])
    link = np.array([np.nan, 0.0, math.log(1.5), -math.log(1.5), 0.0])
    link_sd = np.full(5, 0.12)
    f = chain_factors(d, sig, link, link_sd, np.ones(5, bool), R_TUBE)
    # most of the way, not all: its own prior (0.5 x 20% + 5%) holds against two links of 0.12 (x = 0.31 of 0.41)
    assert abs(d[2] * f[2] - 0.003) < 0.3 * (0.0045 - 0.003)
    assert np.all(np.abs(f[[0, 1, 3, 4]] - 1.0) < 0.05)
    # without links nothing moves; steps that take no part keep a factor of exactly 1
    assert np.all(chain_factors(d, sig, np.full(5, np.nan), link_sd, np.ones(5, bool), R_TUBE) == 1.0)
    member = np.array([1, 1, 0, 1, 1], bool)
    f2 = chain_factors(d, sig, link, link_sd, member, R_TUBE)
    assert f2[2] == 1.0 and np.all(np.abs(f2 - 1.0) < 0.05)
    # a step too short to have parallax takes no part
    d0 = d.copy()
    d0[2] = 0.0001
    assert chain_factors(d0, sig, link, link_sd, np.ones(5, bool), R_TUBE)[2] == 1.0


def test_chained_steps_keep_their_direction_rotation_and_1sigma():
    R = Rotation.from_rotvec([0.01, 0.02, 0.1])
    good = [motion_from_transform(R, np.array([0.0, 0.0, 0.003]), 200, 3e-5, 0.001) for _ in range(2)]
    poor = motion_from_transform(R, np.array([0.0001, 0.0, 0.0045]), 40, 9e-4, 0.01)
    steps = [good[0], replace(poor, scale_link=math.log(1.5), scale_link_sd=0.12),
             replace(good[1], scale_link=-math.log(1.5), scale_link_sd=0.12),
             rotation_step(R, 90, 0.05)]
    out, summary = chained(steps, R_TUBE)
    f = out[1].chain_factor
    assert f < 0.8 and out[1].distance_m == pytest.approx(poor.distance_m * f)
    assert np.allclose(out[1].t_c1_c2_m, poor.t_c1_c2_m * f)
    assert np.allclose(out[1].R_c1_c2, poor.R_c1_c2) and out[1].sigma_distance_m == poor.sigma_distance_m
    assert out[3] is steps[3] and math.isnan(out[3].chain_factor)  # a rotation step takes no part
    assert summary["links"] == 2 and summary["steps_chained"] == 3


def test_the_lumen_scale_line_says_what_the_chain_did_whether_or_not_the_factor_was_applied():
    from bodyslam.vision.lumen_scale import lumen_scale_summary, lumen_scale_text

    ch = {"steps_chained": 81, "links": 71, "factor_p10": 0.98, "factor_p90": 1.36}
    applied = lumen_scale_text(lumen_scale_summary(0.832, 31, 4, 0.0125, ch))
    assert "x0.832" in applied and "81 steps' scales tied to their neighbours' by 71 links (factors 0.98-1.36" in applied
    few = lumen_scale_text(lumen_scale_summary(1.0, 3, 2, 0.0125, {**ch, "steps_chained": 0}))
    assert "not applied" in few and "no step's scale tied to its neighbours'" in few
    assert "tied" not in lumen_scale_text(lumen_scale_summary(0.9, 30, 2, 0.0125))  # --no-scale-chain


def test_an_exam_of_one_step_keeps_it():
    """Two frames: one step, no link; the banded solver is not asked a 1 x 1 system (it refuses one)."""
    f = chain_factors(np.array([0.003]), np.array([3e-5]), np.array([np.nan]), np.array([np.nan]),
                      np.array([True]), R_TUBE)
    assert f.tolist() == [1.0]
