"""The RSS residuals' measured correlation and the covariance it scales (bodyslam.fusion.channel)."""

import numpy as np

from bodyslam.fusion.body_slam import fuse, rts_smooth
from bodyslam.fusion.channel import causal_inflation, inflate, normalised_residuals, residual_correlation
from tests.bodyslam.fusion.test_body_slam import synthetic_run


def ar1(rho, n=400, m=16, seed=0):
    """Unit-variance AR(1) series along the frames, one per sensor."""
    rng = np.random.default_rng(seed)
    z = np.zeros((n, m))
    z[0] = rng.normal(size=m)
    for k in range(1, n):
        z[k] = rho * z[k - 1] + np.sqrt(1 - rho**2) * rng.normal(size=m)
    return z


def test_independent_residuals_leave_the_covariance_alone():
    # 6400 pairs per lag: a lag is significant above 2 / sqrt(6400) = 0.025, which white noise reaches at lag 1
    # about 2% of the time (then kappa ~ 1.05); measured over seeds 0-4: 1.00 each
    for seed in range(5):
        c = residual_correlation(ar1(0.0, seed=seed))
        assert c.kappa < 1.1, (seed, c.kappa)
        assert np.all(causal_inflation(ar1(0.0, seed=seed)) < 1.1)


def test_correlated_residuals_give_their_variance_inflation():
    # AR(1) with rho 0.8: kappa = (1 + rho) / (1 - rho) = 9 summed to infinity; the sum stops at the first lag below
    # 2 / sqrt(pairs) (~lag 17, 0.8^17 = 0.02), which leaves 1 + 2 * 0.8 (1 - 0.8^16) / 0.2 = 8.8; sampling error
    # of a 400-frame series: measured 7.9-9.6 over seeds 0-4
    for seed in range(5):
        c = residual_correlation(ar1(0.8, seed=seed))
        assert 7.0 < c.kappa < 10.5, (seed, c.kappa)
        assert abs(c.rho[0] - 0.8) < 0.05
    # lost readings (NaN) are left out of the pairs, not counted as zero
    z = ar1(0.8, seed=1)
    z[np.random.default_rng(1).random(z.shape) < 0.3] = np.nan
    assert 7.0 < residual_correlation(z).kappa < 10.5


def test_the_online_factor_uses_no_later_frame():
    z = ar1(0.8, seed=2)
    other = z.copy()
    other[201:] = ar1(0.0, seed=3)[201:]
    a, b = causal_inflation(z), causal_inflation(other)
    assert np.array_equal(a[:201], b[:201]) and not np.array_equal(a, b)
    assert a[0] == 1.0 and a[-1] > 5.0  # nothing to measure at the first frame; the correlation found later


def correlated_run(seed, corr_m, n=160):
    """A capsule path (0.4 cm steps) read by the thesis sensors through shadowing correlated over ``corr_m`` along
    the path (Gudmundson); the visual steps carry the filter's assumed noise; fixes at every frame."""
    from testbed.rf import ChannelModel

    return synthetic_run(seed, n=n, fix_frames=n, channel=ChannelModel(shadowing_corr_m=corr_m))


def mean_nees(res, gt, k0=60):
    e = res.positions_w_m - gt
    return float(np.einsum("ni,ni->n", e, np.linalg.solve(res.cov[:, :3, :3], e[..., None])[..., 0])[k0:].mean())


def test_correlated_shadowing_is_measured_and_the_stated_sigma_becomes_honest():
    """Shadowing correlated over 3 cm (consecutive readings 0.875 correlated: kappa 15 in theory) makes the filter
    overconfident by an order of magnitude; scaled by the measured kappa, the NEES is near its honest 3. With
    independent shadowing kappa is 1 and nothing changes. Measured on seeds 0-5 (frames 60-159): raw mean NEES
    14-98 (filter) and 14-76 (smoother), kappa 11.7-15.2, scaled 1.2-8.2 and 1.2-5.4 with means 3.1 and 3.5;
    independent: kappa 1.00 on each. Seeds 0-3 here: bands cover the per-seed spread."""
    raw, scaled = [], []
    for seed in range(4):
        steps, fixes, rss, pos, nrm, pl, gt = correlated_run(seed, 0.03)
        f = fuse(steps, fixes, rss, pos, nrm, pl, mode="rss")
        s = rts_smooth(f)
        kappa = residual_correlation(normalised_residuals(rss, s.positions_w_m, pos, nrm, pl)).kappa
        k_online = causal_inflation(normalised_residuals(rss, f.positions_w_m, pos, nrm, pl))
        assert 8.0 < kappa < 20.0 and 8.0 < k_online[-1] < 20.0, (seed, kappa, k_online[-1])
        raw.append([mean_nees(f, gt), mean_nees(s, gt)])
        scaled.append([mean_nees(inflate(f, k_online), gt), mean_nees(inflate(s, kappa), gt)])
        assert np.array_equal(inflate(s, kappa).positions_w_m, s.positions_w_m)
    assert np.all(np.mean(raw, axis=0) > 15.0), raw
    assert np.all((np.mean(scaled, axis=0) > 1.5) & (np.mean(scaled, axis=0) < 6.0)), scaled
    steps, fixes, rss, pos, nrm, pl, gt = correlated_run(0, 0.0)
    s = rts_smooth(fuse(steps, fixes, rss, pos, nrm, pl, mode="rss"))
    assert residual_correlation(normalised_residuals(rss, s.positions_w_m, pos, nrm, pl)).kappa == 1.0


def test_the_online_factor_over_the_filters_memory_is_an_exponential_averages_inflation():
    """An exponentially weighted mean (weight ``a^i`` on the reading ``i`` frames back: a filter that keeps a share
    ``a`` of its information each frame) of AR(1) residuals has ``1 + 2 sum rho^l a^l`` times the variance it has on
    white ones. With the memory given, the online factor is that, measured on the residuals: here within 3% of the
    simulated ratio (measured: within 0.5% on these three cases, 4000 frames x 16 sensors)."""
    from bodyslam.fusion.channel import filter_memory

    for rho, a in ((0.8, 0.8), (0.9, 0.85), (0.5, 0.9)):
        z, white = ar1(rho, n=4000, seed=1), ar1(0.0, n=4000, seed=2)

        def ew_var(x):
            y = np.zeros_like(x)
            for k in range(1, len(x)):
                y[k] = a * y[k - 1] + (1 - a) * x[k]
            return y[200:].var()

        got = causal_inflation(z, memory=np.full(len(z), a))[-1]
        assert abs(got / (ew_var(z) / ew_var(white)) - 1) < 0.03, (rho, a, got)
        assert got < causal_inflation(z)[-1]  # a short memory counts fewer of the correlated lags
    z = ar1(0.8, seed=2)  # no decay: every lag in full, as without the memory
    assert np.array_equal(causal_inflation(z, memory=np.ones(len(z))), causal_inflation(z))
    steps, fixes, rss, pos, nrm, pl, gt = correlated_run(0, 0.03, n=60)
    mem = filter_memory(fuse(steps, fixes, rss, pos, nrm, pl, mode="rss"))
    assert mem.shape == (60,) and np.all((mem > 0.5) & (mem <= 1.0))  # measured 0.96-0.98 after the start


def test_the_smoothers_factor_is_a_two_sided_exponential_averages_inflation():
    """A two-sided exponential average (weight ``a^|i|`` on the reading ``i`` frames away: the smoother in steady
    state) of AR(1) residuals has ``1 + 2 sum rho_l c_l`` times the variance it has on white ones, ``c_l`` the
    weights' overlap at lag ``l``: checked against the direct sums (to 1e-12), against a simulated average (within
    3%: measured 1.7% and 2.3% low on these cases, 4000 frames x 16 sensors; the measured rho is a sample's),
    and at the ends (``a = 1``: the whole run's kappa; ``a = 0``: 1)."""
    from bodyslam.fusion.channel import smoother_inflation, two_sided_lag_weights

    for a in (0.5, 0.9, 0.97):
        i = np.arange(-2000, 2001)
        w = a ** np.abs(i)
        direct = [np.sum(w[:-l] * w[l:]) / np.sum(w * w) for l in range(1, 31)]
        assert np.allclose(two_sided_lag_weights(np.array([a]), 30)[0], direct, rtol=0, atol=1e-12)
    for rho, a in ((0.8, 0.8), (0.9, 0.85)):
        z, white = ar1(rho, n=4000, seed=1), ar1(0.0, n=4000, seed=2)
        k = np.arange(-60, 61)
        w = a ** np.abs(k)

        def two_sided_var(x):
            y = np.array([np.convolve(x[:, j], w, mode="valid") for j in range(x.shape[1])])
            return y.var()

        corr = residual_correlation(z)
        got = smoother_inflation(corr, np.full(len(z), a))
        assert np.allclose(got, got[0]) and got[0] < corr.kappa
        assert abs(got[0] / (two_sided_var(z) / two_sided_var(white)) - 1) < 0.03, (rho, a, got[0])
    corr = residual_correlation(ar1(0.8, seed=2))
    assert np.allclose(smoother_inflation(corr, np.ones(5)), corr.kappa)
    assert np.allclose(smoother_inflation(corr, np.zeros(5)), 1.0)
    assert smoother_inflation(corr, None) == corr.kappa


def test_the_stated_covariance_counts_a_slow_capsules_long_correlation():
    """A capsule at a real exam's pace crosses the shadowing's correlation distance in ~50 frames: AR(1) with rho
    0.98 per frame has kappa = (1 + rho) / (1 - rho) = 99. Summed to 30 lags that is 1 + 2 * 0.98 (1 - 0.98^30) /
    0.02 = 45.6; to the stated covariance's 120 lags, 90.4 (3000 frames x 16 sensors, seeds 0-2: measured 45.4 /
    46.3 / 44.5 and 92.0 / 92.9 / 80.7)."""
    from bodyslam.fusion.channel import MAX_LAG_FRAMES, STATED_MAX_LAG_FRAMES

    for seed in range(3):
        z = ar1(0.98, n=3000, seed=seed)
        short, long = residual_correlation(z, MAX_LAG_FRAMES), residual_correlation(z, STATED_MAX_LAG_FRAMES)
        assert 35.0 < short.kappa < 55.0 and 70.0 < long.kappa < 110.0, (seed, short.kappa, long.kappa)
        assert causal_inflation(z, STATED_MAX_LAG_FRAMES)[-1] > 1.5 * causal_inflation(z, MAX_LAG_FRAMES)[-1]


def test_lag_sums_are_the_pairs_products_and_counts_whatever_the_block():
    """Each frame's lag sums (one product of its readings with the window before it) against a pass per lag, on
    readings with gaps, for blocks that start at the first frame, inside the exam and past the windows' parts."""
    from bodyslam.fusion.channel import _lag_sums

    rng = np.random.default_rng(4)
    z = rng.normal(size=(1300, 6))
    z[rng.random(z.shape) < 0.25] = np.nan
    z[:2] = np.nan
    ok = np.isfinite(z)
    z0 = np.where(ok, z, 0.0)
    for L in (1, 30, 120):
        for rows in (slice(0, 1300), slice(0, 40), slice(700, 1300), slice(513, 1025)):
            prod, cnt, sq, n_sq = _lag_sums(z, L, rows)
            a, b, _ = rows.indices(len(z))
            for k in (a, a + 1, (a + b) // 2, b - 1):
                for l in (1, L // 2 + 1, L):
                    want = float(np.sum(z0[k] * z0[k - l])) if k >= l else 0.0
                    pairs = int(np.sum(ok[k] & ok[k - l])) if k >= l else 0
                    assert abs(prod[k - a, l - 1] - want) < 1e-12 and cnt[k - a, l - 1] == pairs, (L, rows, k, l)
                assert abs(sq[k - a] - float(np.sum(z0[k] ** 2))) < 1e-12 and n_sq[k - a] == ok[k].sum()


def test_what_the_fit_takes_up_scales_the_summed_correlations():
    """``fitted_dof = p`` scales the summed correlations by ``m / (m - p)``, ``m`` the sensors with a reading (so
    far, online): kappa - 1 by exactly that, the measured rho left as measured; white residuals still give 1."""
    from bodyslam.fusion.channel import smoother_inflation

    z = ar1(0.8, seed=4)  # 16 sensors
    plain, fitted = residual_correlation(z), residual_correlation(z, fitted_dof=3)
    assert np.array_equal(plain.rho, fitted.rho) and fitted.fitted_gain == 16 / 13
    assert np.isclose(fitted.kappa - 1, (plain.kappa - 1) * 16 / 13, rtol=1e-12)
    assert np.allclose(smoother_inflation(fitted, np.full(5, 0.9)) - 1,
                       (smoother_inflation(plain, np.full(5, 0.9)) - 1) * 16 / 13, rtol=1e-12)
    z[:, 0] = np.nan  # a sensor that never read does not count
    assert residual_correlation(z, fitted_dof=3).fitted_gain == 15 / 12
    assert residual_correlation(ar1(0.0, seed=0), fitted_dof=3).kappa < 1.1
    assert np.all(causal_inflation(ar1(0.0, seed=0), fitted_dof=3) < 1.1)
    # online: a sensor that first reads at frame 200 counts from then on
    z = ar1(0.8, seed=5)
    z[:200, 3] = np.nan
    mem = np.full(len(z), 0.95)
    for memory in (None, mem):
        a, b = causal_inflation(z, memory=memory), causal_inflation(z, memory=memory, fitted_dof=3)
        assert np.allclose(b[50:200] - 1, (a[50:200] - 1) * 15 / 12, rtol=1e-12)
        assert np.allclose(b[200:] - 1, (a[200:] - 1) * 16 / 13, rtol=1e-12)


def test_a_position_fitted_to_the_readings_hides_m_minus_3_of_m_of_a_sensors_offset():
    """A capsule at rest read by ``m`` sensors, each off the calibration by its own constant (0.5 sigma) plus white
    shadowing, its position fitted to all the readings at once (as the smoother pools a run's frames): the readings'
    correlation measured at the fitted position shows about ``(m - 3) / m`` of what it is at the true one (the offsets
    along the position's three directions are taken up), and ``fitted_dof = 3`` gives the rest back. Ratio of
    ``kappa - 1`` (fitted / true), mean over seeds 0-19, measured: 8 sensors 0.654 as measured (0.625 in theory),
    1.046 scaled; 32 sensors 0.911 (0.906), 1.006. The means' standard errors over those seeds: 8 sensors 0.076 as
    measured and 0.121 scaled, 32 sensors 0.015 and 0.016; the bands are about 1 (8 sensors) and 2.5 (32) of them
    around 1 for the scaled ratio, and 1.3 above the measured one's mean for its ceiling (the seeds are fixed: the
    figures do not move from run to run; without the scaling the 8-sensor ratio misses its band by 0.23)."""
    from scipy.optimize import least_squares

    from bodyslam.fusion.rf import PathLossModel
    from testbed.rf import SensorLayout

    pl = PathLossModel()
    for n_side, band_scaled, below in ((2, 0.12, 0.75), (4, 0.04, 0.95)):
        layout = SensorLayout.thesis_grids(n_side=n_side)
        s_w, n_w = layout.positions_w_m, layout.normals_w
        m, n = len(s_w), 300
        measured, scaled = [], []
        for seed in range(20):
            rng = np.random.default_rng(seed)
            p0 = rng.uniform(-0.06, 0.06, 3)
            mu, sigma, _ = pl.predict(p0, s_w, n_w)
            rss = mu + sigma * (0.5 * rng.normal(size=m) + rng.normal(size=(n, m)))
            mean = rss.mean(axis=0)
            p_fit = least_squares(lambda q: (mean - pl.predict(q, s_w, n_w)[0]) / sigma, p0 + 0.01).x
            z_fit = normalised_residuals(rss, np.tile(p_fit, (n, 1)), s_w, n_w, pl)
            true = residual_correlation(normalised_residuals(rss, np.tile(p0, (n, 1)), s_w, n_w, pl), 30).kappa - 1
            measured.append((residual_correlation(z_fit, 30).kappa - 1) / true)
            scaled.append((residual_correlation(z_fit, 30, fitted_dof=3).kappa - 1) / true)
        assert np.mean(measured) < below, (m, np.mean(measured))
        assert abs(np.mean(scaled) - 1.0) < band_scaled, (m, np.mean(scaled))
