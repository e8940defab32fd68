"""The whole-exam refinement (bodyslam.fusion.refine): its Jacobian, and what it recovers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.fusion.body_slam import fuse, rts_smooth
from bodyslam.fusion.ekf import Z_GATE_999
from bodyslam.fusion.refine import MapProblem, marginal_covariances, refine_map
from bodyslam.geometry import rotvec_to_matrix

from tests.bodyslam.fusion import test_body_slam
from tests.bodyslam.fusion.test_body_slam import DEMO, synthetic_run

demo = test_body_slam.demo  # the demo's true steps with noise, and its RF (a fixture of test_body_slam)

R0_TRUE = Rotation.from_rotvec([0.4, -0.3, 0.2])  # synthetic_run's first orientation


def test_the_jacobian_matches_finite_differences():
    # J dx against r(x + dx) - r(x), the positions and the orientations perturbed separately (rotations turned on
    # the right: R exp([phi]x)), each block of rows on its own: a wrong sign or a transposed block fails by a
    # relative error of order 1. The orientations are chained exactly through steps of 20-40 deg (the rotation
    # residuals are zero there, where the log's Jacobian is exactly the identity, and R_s differs from R_s^T);
    # the positions are off the chain so the position rows are not zero. Measured: below 1e-5 in every block.
    from bodyslam.fusion.rf import PathLossModel
    from bodyslam.steps import motion_from_transform
    from testbed.rf import SensorLayout

    rng = np.random.default_rng(0)
    n = 30
    Rs = [Rotation.from_rotvec(rng.normal(0, 1, 3)) for _ in range(n - 1)]
    Rs = [Rotation.from_rotvec(r.as_rotvec() / r.magnitude() * np.radians(rng.uniform(20, 40))) for r in Rs]
    steps = [motion_from_transform(r, rng.normal(0, 0.004, 3), 50, 3e-4, np.radians(0.2)) for r in Rs]
    R = [Rotation.from_rotvec(rng.normal(0, 1, 3))]
    for r in Rs:
        R.append(R[-1] * Rotation.from_matrix(r.as_matrix()))
    R = np.array([r.as_matrix() for r in R])
    layout = SensorLayout.thesis_grids()
    p = np.array([0.0, 0.0, 0.0]) + rng.normal(0, 0.03, (n, 3))
    pl = PathLossModel()
    rss = np.full((n, len(layout.names)), -60.0) + rng.normal(0, 3, (n, len(layout.names)))
    prob = MapProblem(steps, rss, layout.positions_w_m, layout.normals_w, pl, gate=1e9)
    J, _ = prob.linearise(p, R)
    rp, rr, z = prob.residuals(p, R)
    assert np.abs(rr).max() < 1e-6  # the chain is exact
    for part in (slice(0, 3), slice(3, 6)):
        dx = np.zeros((n, 6))
        dx[:, part] = rng.normal(0, 1e-6, (n, 3))
        rp2, rr2, z2 = prob.residuals(p + dx[:, :3], R @ rotvec_to_matrix(dx[:, 3:]))
        pred = J @ dx.ravel()
        for name, actual, rows in (("step position", rp2 - rp, slice(0, 3 * (n - 1))),
                                   ("step rotation", rr2 - rr, slice(3 * (n - 1), 6 * (n - 1))),
                                   ("readings", z2 - z, slice(6 * (n - 1), None))):
            actual = actual.ravel()
            if np.linalg.norm(actual) == 0:
                continue
            rel = np.linalg.norm(pred[rows] - actual) / np.linalg.norm(actual)
            assert rel < 1e-3, (part, name, rel)


def test_the_block_normal_equations_are_the_sparse_jacobians(monkeypatch):
    # normal_equations builds J^T J and J^T r block by block, the steps and the readings in chunks of frames,
    # without J: they must equal the sparse reference (linearise) to rounding, with chunks smaller than the run (3
    # frames) too, and the chunks must not change a bit (each frame's blocks are its own; D's two step terms are
    # added to zero in either order).
    import bodyslam.fusion.refine as refine

    steps, fixes, rss, pos, nrm, pl, gt = synthetic_run(2, n=25)
    res = rts_smooth(fuse(steps, fixes, rss, pos, nrm, pl, mode="rss"))
    rng = np.random.default_rng(1)
    p = res.positions_w_m + rng.normal(0, 0.01, res.positions_w_m.shape)
    R = res.rotations_w_c.as_matrix() @ rotvec_to_matrix(rng.normal(0, 0.1, (len(p), 3)))
    rss = rss.copy()
    rss[3, 5] = np.nan  # a lost reading
    rss[7, 2] += 60.0  # one beyond the gate
    prob = MapProblem(steps, rss, pos, nrm, pl)
    J, r = prob.linearise(p, R)
    H, gref = (J.T @ J).toarray(), J.T @ r
    first = None
    for chunk, readings in ((4096, 1024), (3, 5), (5, 3)):  # (the readings' rows have their own block size)
        monkeypatch.setattr(refine, "CHUNK_FRAMES", chunk)
        monkeypatch.setattr(refine, "NORMAL_CHUNK_FRAMES", readings)
        D, O, g = prob.normal_equations(p, R)
        first = first or (D, O, g)
        assert all(np.array_equal(a, b) for a, b in zip(first, (D, O, g)))
        Hb = np.zeros_like(H)
        for k in range(len(p)):
            Hb[6 * k:6 * k + 6, 6 * k:6 * k + 6] = D[k]
            if k + 1 < len(p):
                Hb[6 * k:6 * k + 6, 6 * k + 6:6 * k + 12] = O[k]
                Hb[6 * k + 6:6 * k + 12, 6 * k:6 * k + 6] = O[k].T
        assert np.allclose(Hb, H, rtol=1e-10, atol=1e-8 * np.abs(H).max())
        assert np.allclose(g.ravel(), gref, rtol=1e-10, atol=1e-10 * np.abs(gref).max())
        assert np.isclose(prob.cost(p, R), 0.5 * float(r @ r) + 0.5 * Z_GATE_999**2)  # + the capped reading


def _block_tridiagonal(D, O):
    H = np.zeros((6 * len(D), 6 * len(D)))
    for k in range(len(D)):
        H[6 * k:6 * k + 6, 6 * k:6 * k + 6] = D[k]
        if k + 1 < len(D):
            H[6 * k:6 * k + 6, 6 * k + 6:6 * k + 12] = O[k]
            H[6 * k + 6:6 * k + 12, 6 * k:6 * k + 6] = O[k].T
    return H


def _random_system(monkeypatch, compiled: bool, n: int = 9):
    """``(D, O)`` of a random positive definite block-tridiagonal matrix, each diagonal block alone of rank 4 (only
    the chain makes it regular), with the compiled passes (skipped where not built) or numpy's."""
    import bodyslam.fusion.refine as refine_mod

    if compiled and refine_mod._bt is None:
        pytest.skip("bodyslam/fusion/_block_tridiag.c is not built here (no C compiler at install)")
    if not compiled:
        monkeypatch.setattr(refine_mod, "_bt", None)
    rng = np.random.default_rng(3)
    D = np.array([a.T @ a for a in rng.normal(size=(n, 4, 6))])
    O = np.zeros((n - 1, 6, 6))
    for k in range(n - 1):
        a = rng.normal(size=(6, 12))
        B = a.T @ a
        D[k] += B[:6, :6]
        D[k + 1] += B[6:, 6:]
        O[k] = B[:6, 6:]
    return D, O


@pytest.mark.parametrize("compiled", [True, False])
def test_the_marginal_covariances_are_the_inverses_diagonal_blocks(monkeypatch, compiled):
    # The forward-backward recursion against the dense inverse of a random positive definite block-tridiagonal
    # matrix (measured 1e-16 of the largest entry; 1e-10 is rounding with room); a singular one gives None.
    # Both the compiled passes (_block_tridiag.c) and numpy's.
    D, O = _random_system(monkeypatch, compiled)
    n = len(D)
    Hinv = np.linalg.inv(_block_tridiagonal(D, O))
    C = marginal_covariances(D, O)
    for k in range(n):
        assert np.allclose(C[k], Hinv[6 * k:6 * k + 6, 6 * k:6 * k + 6], atol=1e-10 * np.abs(Hinv).max())
    D[4] = 0.0
    O[3] = O[4] = 0.0  # frame 4 carries no information
    assert marginal_covariances(D, O) is None


@pytest.mark.parametrize("compiled", [True, False])
def test_the_readings_share_is_the_dense_sandwich(monkeypatch, compiled):
    # sandwich_share's forward-backward passes against the dense H^-1 W H^-1 of a random positive definite
    # block-tridiagonal H and a random block-diagonal W (measured 9e-16 / 7e-16 of the largest entry, compiled /
    # numpy; 1e-10 is rounding with room). A transposed gain or a pass that drops the frames before k fails by
    # order 1. Its C is marginal_covariances'.
    import bodyslam.fusion.refine as refine_mod

    D, O = _random_system(monkeypatch, compiled)
    n = len(D)
    W = np.array([w.T @ w for w in np.random.default_rng(4).normal(size=(n, 6, 6))])
    Hinv = np.linalg.inv(_block_tridiagonal(D, O))
    Wd = np.zeros_like(Hinv)
    for k in range(n):
        Wd[6 * k:6 * k + 6, 6 * k:6 * k + 6] = W[k]
    dense = Hinv @ Wd @ Hinv
    C, M = refine_mod.sandwich_share(D, O, W)
    for k in range(n):
        blk = slice(6 * k, 6 * k + 6)
        assert np.allclose(M[k], dense[blk, blk], atol=1e-10 * np.abs(dense).max())
        assert np.allclose(C[k], Hinv[blk, blk], atol=1e-10 * np.abs(Hinv).max())
    D[4] = 0.0
    O[3] = O[4] = 0.0
    assert refine_mod.sandwich_share(D, O, W) is None


def test_the_stated_orientation_takes_the_factor_on_the_readings_share_only():
    # refine_map(reading_kappa=...): the position's covariance is kappa times the solution's own, as before; the
    # orientation's is the sandwich H^-1 (H + (kappa - 1) H_rf) H^-1 of the dense system (H_rf: the readings'
    # rows of J^T J), which lies between the solution's own (kappa 1) and kappa times it. A factor of 1 changes
    # nothing. Held to the dense reference to the same rounding as the solution's own covariance (rtol 1e-7: J^T J's
    # condition number is ~1.2e9 here); the cross blocks, whose entries are smaller, relative to their own size
    # (rtol 1e-6). Measured: 2.4e-10 and 2.6e-10 of each block's largest entry.
    from bodyslam.fusion.refine import stated_covariances

    steps, fixes, rss, pos, nrm, pl, gt = synthetic_run(2, n=25)
    rts = rts_smooth(fuse(steps, fixes, rss, pos, nrm, pl, mode="rss"))
    own = refine_map(rts, steps, rss, pos, nrm, pl)
    seen = []
    stated = refine_map(rts, steps, rss, pos, nrm, pl, reading_kappa=lambda p: seen.append(p.copy()) or 4.0)
    assert np.array_equal(stated.positions_w_m, own.positions_w_m) and np.array_equal(seen[0], own.positions_w_m)
    assert np.allclose(stated.cov[:, :3, :3], 4.0 * own.cov[:, :3, :3], rtol=1e-12, atol=0)
    prob = MapProblem(steps, rss, pos, nrm, pl, rts.scale)  # (the problem refine_map solved: its scale states)
    J, _ = prob.linearise(own.positions_w_m, own.rotations_w_c.as_matrix())
    H = (J.T @ J).toarray()
    n_step_rows = 6 * (len(gt) - 1)
    Hrf = (J[n_step_rows:].T @ J[n_step_rows:]).toarray()
    Hinv = np.linalg.inv(H)
    sandwich = Hinv @ (H + 3.0 * Hrf) @ Hinv
    for k in range(len(gt)):
        o = slice(6 * k + 3, 6 * k + 6)
        assert np.allclose(stated.cov[k, 3:, 3:], sandwich[o, o], rtol=1e-7, atol=1e-12)
        assert np.allclose(stated.cov[k, :3, 3:], sandwich[6 * k:6 * k + 3, o], rtol=1e-6, atol=1e-12)
        grow = stated.cov[k, 3:, 3:] - own.cov[k, 3:, 3:]
        assert np.linalg.eigvalsh(grow).min() > -1e-12 and np.trace(grow) > 0
        assert np.linalg.eigvalsh(4.0 * own.cov[k, 3:, 3:] - stated.cov[k, 3:, 3:]).min() > 0
        assert np.linalg.eigvalsh(stated.cov[k]).min() > 0
    assert np.trace(stated.cov[:, 3:, 3:] - own.cov[:, 3:, 3:], axis1=1, axis2=2).max() > 0.1 * np.trace(
        own.cov[:, 3:, 3:], axis1=1, axis2=2).max()  # the readings inform this run's orientation: not a no-op
    D, O, _ = prob.normal_equations(own.positions_w_m, own.rotations_w_c.as_matrix())
    H_rf = np.zeros((len(gt), 3, 3))
    prob.normal_equations(own.positions_w_m, own.rotations_w_c.as_matrix(), readings_out=H_rf)
    assert np.allclose(H_rf, prob.reading_information(own.positions_w_m), rtol=1e-12, atol=0)
    one = stated_covariances(D, O, H_rf, 1.0)
    assert np.array_equal(one, marginal_covariances(D, O))


def test_a_singular_solve_states_the_smoothers_covariance_scaled(monkeypatch):
    # Where the whole-exam solve's information is not positive definite, refine_map keeps the smoother's
    # covariance; with a correlation factor it is scaled by it, as localize scaled it before (not left unscaled).
    import bodyslam.fusion.refine as refine_mod

    steps, fixes, rss, pos, nrm, pl, gt = synthetic_run(2, n=25)
    rts = rts_smooth(fuse(steps, fixes, rss, pos, nrm, pl, mode="rss"))
    monkeypatch.setattr(refine_mod, "sandwich_share", lambda D, O, W: None)
    kappa = np.linspace(1.0, 3.0, len(gt))
    out = refine_map(rts, steps, rss, pos, nrm, pl, reading_kappa=lambda p: kappa)
    assert np.allclose(out.cov, rts.cov * kappa[:, None, None], rtol=1e-15, atol=0)


def test_the_refined_covariance_is_the_solutions_own():
    # refine_map states the inverse of J^T J at its solution (the Gauss-Newton information of every step and
    # reading), not the smoother's covariance: held to the sparse reference's dense inverse to rounding.
    steps, fixes, rss, pos, nrm, pl, gt = synthetic_run(2, n=25)
    rts = rts_smooth(fuse(steps, fixes, rss, pos, nrm, pl, mode="rss"))
    ref = refine_map(rts, steps, rss, pos, nrm, pl)
    J, _ = MapProblem(steps, rss, pos, nrm, pl).linearise(ref.positions_w_m, ref.rotations_w_c.as_matrix())
    Hinv = np.linalg.inv((J.T @ J).toarray())
    # J^T J's condition number is ~1.2e9 here, so its dense inverse is itself good to ~1e-7 relative (cond * eps);
    # measured: within 5e-9 (from the numpy filter's start) and 2e-8 (from the compiled one's, ~1e-15 away)
    for k in range(len(gt)):
        assert np.allclose(ref.cov[k], Hinv[6 * k:6 * k + 6, 6 * k:6 * k + 6], rtol=1e-7, atol=1e-12)
    assert not np.allclose(ref.cov, rts.cov)
    assert np.array_equal(refine_map(rts, steps, rss, pos, nrm, pl, own_cov=False).cov, rts.cov)
    # variance added to the readings (offsets taken as known, their uncertainty not): the same solution, a wider
    # covariance (the difference positive semi-definite on every frame), none added the same covariance
    zero = refine_map(rts, steps, rss, pos, nrm, pl, reading_var_db2=np.zeros(rss.shape))
    assert np.allclose(zero.cov, ref.cov, rtol=1e-12, atol=0)
    wide = refine_map(rts, steps, rss, pos, nrm, pl, reading_var_db2=np.full(rss.shape, 4.0))
    assert np.array_equal(wide.positions_w_m, ref.positions_w_m)
    assert np.linalg.eigvalsh(wide.cov - ref.cov).min() > -1e-12 and np.trace(wide.cov[:, :3, :3] - ref.cov[:, :3, :3],
                                                                               axis1=1, axis2=2).min() > 0


def _turned_start(seed, deg):
    """``synthetic_run``'s truth, and the smoother of a filter started ``deg`` off with a 5 deg 1-sigma (a start
    committed wrongly, no recheck or re-start to save it)."""
    steps, fixes, rss, pos, nrm, pl, gt = synthetic_run(seed, n=120)
    turn = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.6, 0.8]))
    ekf = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss", init=(turn * R0_TRUE, gt[0]), regap_steps=None,
               recheck_start=False)
    return (steps, rss, pos, nrm, pl), gt, rts_smooth(ekf)


def _off_deg(res):
    return float(np.degrees((res.rotations_w_c[0] * R0_TRUE.inv()).magnitude()))


def _err_m(res, gt):
    return float(np.mean(np.linalg.norm(res.positions_w_m - gt, axis=1)))


def test_a_run_started_turned_away_is_turned_back():
    # Started 100 deg off, the smoother, linearised along the filter's wrong run, keeps 28-29 deg at frame 0 and
    # 4.4-4.9 cm mean error (measured, seeds 0-2); the whole-exam solve re-linearises and ends at 1.9-9.2 deg and
    # 0.47-0.84 cm (seed 1's optimum itself is ~9 deg off: a nearly straight path leaves its roll weak).
    for seed in range(3):
        (steps, rss, pos, nrm, pl), gt, rts = _turned_start(seed, 100.0)
        ref = refine_map(rts, steps, rss, pos, nrm, pl)
        assert _off_deg(rts) > 20.0 and _off_deg(ref) < 12.0, (seed, _off_deg(rts), _off_deg(ref))
        assert _err_m(ref, gt) < 0.5 * _err_m(rts, gt), (seed, _err_m(rts, gt), _err_m(ref, gt))
        prob = MapProblem(steps, rss, pos, nrm, pl)
        assert prob.cost(ref.positions_w_m, ref.rotations_w_c.as_matrix()) < prob.cost(
            rts.positions_w_m, rts.rotations_w_c.as_matrix())


def test_the_solution_does_not_depend_on_how_far_off_the_smoother_was():
    # Smoothers 14 and 29 deg off (starts 70 and 100 deg off) refine to the same trajectory: measured 0.003 mm apart
    # on average; 1 mm allows for where each stops (relative cost change 1e-6).
    (steps, rss, pos, nrm, pl), gt, rts70 = _turned_start(0, 70.0)
    _, _, rts100 = _turned_start(0, 100.0)
    a, b = (refine_map(r, steps, rss, pos, nrm, pl) for r in (rts70, rts100))
    assert _err_m(rts70, rts100.positions_w_m) > 0.01
    assert _err_m(a, b.positions_w_m) < 1e-3


def test_localize_ships_the_refined_smoother_and_keeps_the_plain_one(demo):
    # localize's smoothed output is the refinement of its RTS run (kept as loc.rts), both covariances scaled by the
    # same measured correlation; refine=False gives the RTS run itself.
    from bodyslam.fusion.localize import RfInput, localize
    from bodyslam.io import read_json

    steps, *_, gt = demo
    rf = RfInput.read(DEMO / "rf.csv", DEMO / "sensors.csv", read_json(DEMO / "meta.json")["rf"]["pathloss"])
    stamps = np.arange(len(steps) + 1) / 2.0
    loc = localize(steps, stamps, rf, 2.0)
    plain = localize(steps, stamps, rf, 2.0, refine=False)
    assert np.array_equal(plain.smoothed.positions_w_m, plain.rts.positions_w_m)
    assert np.array_equal(loc.rts.positions_w_m, plain.rts.positions_w_m)
    assert np.abs(loc.smoothed.positions_w_m - loc.rts.positions_w_m).max() > 1e-4
    assert not np.allclose(loc.smoothed.cov, loc.rts.cov)  # its own, not the smoother's (refine_map)
    raw = localize(steps, stamps, rf, 2.0, honest_cov=False).smoothed.cov
    assert np.allclose(raw * loc.kappa_smoothed[:, None, None], loc.smoothed.cov)  # scaled as the smoother's
    # on the demo's ideal channel the two are close (measured 1.15 cm refined, 1.24 plain): not worse by 20%
    assert _err_m(loc.smoothed, gt) < 1.2 * _err_m(loc.rts, gt), (_err_m(loc.smoothed, gt), _err_m(loc.rts, gt))


def test_localize_with_bias_states_finds_sensors_reading_high_and_writes_them(demo, tmp_path):
    """``localize(bias_states=True)`` on the demo with four sensors reading 6 dB above the calibration: their mean
    bias estimates stand out from the others', and ``rss_bias.csv`` lists every sensor with them; without the
    states there is nothing to write."""
    import csv

    from bodyslam.fusion.localize import RfInput, localize, write_rss_bias
    from bodyslam.io import read_json

    steps, *_ = demo
    rf = RfInput.read(DEMO / "rf.csv", DEMO / "sensors.csv", read_json(DEMO / "meta.json")["rf"]["pathloss"])
    rf.rss_dbm[:, :4] += 6.0
    stamps = np.arange(len(steps) + 1) / 2.0
    loc = localize(steps, stamps, rf, 2.0, bias_states=True)
    mean = loc.rss_bias_db.mean(axis=0)
    # measured: 1.4-2.2 dB on the four (means over 40 frames from a zero start, shrunk by the 2 dB prior; 2.4-3.9 at
    # the end), |mean| <= 0.9 elsewhere: the four are the four highest
    assert set(np.argsort(mean)[-4:]) == {0, 1, 2, 3} and mean[:4].min() > 1.2, mean
    assert write_rss_bias(tmp_path / "rss_bias.csv", loc)
    rows = list(csv.DictReader((tmp_path / "rss_bias.csv").open()))
    assert [r["sensor"] for r in rows] == list(rf.sensor_names)
    assert float(rows[0]["bias_mean_db"]) == pytest.approx(mean[0]) and int(rows[0]["readings"]) == len(stamps)
    # their variances, kept for the whole-exam solve's 1-sigma: below the 2 dB prior's, above nothing
    var = loc.filtered.passes.post_bias_var_db2
    assert var.shape == loc.rss_bias_db.shape and 0 < var.min() and var.max() <= 2.0**2 + 1e-9
    plain = localize(steps, stamps, rf, 2.0)
    assert plain.rss_bias_db is None and not write_rss_bias(tmp_path / "none.csv", plain)
    assert plain.filtered.passes.post_bias_var_db2 is None
    assert not (tmp_path / "none.csv").exists()
