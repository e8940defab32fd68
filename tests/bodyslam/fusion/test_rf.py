"""RF fixes for many frames at once (bodyslam.fusion.rf.locate_ml_frames) against the per-frame scipy solves."""

from pathlib import Path

import numpy as np
import pytest

from bodyslam.fusion.rf import PathLossModel, locate_ml, locate_ml_frames


def ml_cost(fix, rss, layout, pl):
    """The soft-L1 cost the ML fix minimises, over the readings it kept (scipy's form, f_scale 2)."""
    ok = np.isfinite(rss)
    mean, sig, _ = pl.predict(fix.position_w_m, layout.positions_w_m[ok], layout.normals_w[ok])
    z = (rss[ok] - mean) / sig
    keep = np.abs(z) < 3.0 if fix.n_sensors < ok.sum() else np.ones(len(z), bool)
    return float(np.sum(4.0 * (np.sqrt(1.0 + (z[keep] / 2.0) ** 2) - 1.0)))


def test_vectorised_fixes_reach_the_per_frame_minima():
    """300 capsule positions in the abdomen read by the thesis sensors with Table 2.2 shadowing, 10% of readings
    lost, 2% off by 15 dB, and three frames with fewer than 4 readings. The model's deep / near-surface switch makes
    the cost discontinuous, so a solver may stop at a kink the other passes: what must hold is that the vectorised
    fixes are as good. Measured (seeds 0-2 of this set-up): status equal on 99.7-100% of frames; positions within
    4.2-4.3 um on the median frame (scipy's own tolerance), within 0.1 mm on 88-92%; the vectorised cost no higher
    than scipy's (+0.01) on 98.6-99.3%; mean error against the truth 5.49 cm either way (0.04 cm apart at most).
    Bands below sit under those with room for another platform's rounding."""
    from testbed.rf import ChannelModel, SensorLayout, emulate_rf

    rng = np.random.default_rng(0)
    layout, pl = SensorLayout.thesis_grids(), PathLossModel()
    truth = rng.uniform([-0.12, -0.1, -0.12], [0.12, 0.1, 0.12], (300, 3))
    rss = emulate_rf(truth, layout, pl, rng=1, channel=ChannelModel(dropout_prob=0.1, outlier_prob=0.02))["rss_dbm"]
    rss[[5, 77, 200], 3:] = np.nan  # 3 readings left: no fix
    ref = [locate_ml(layout.positions_w_m, layout.normals_w, r, pl) for r in rss]
    got = locate_ml_frames(layout.positions_w_m, layout.normals_w, rss, pl, block=128)  # 3 blocks
    assert [g.status for g in got][5] == "too_few_sensors" and got[77].n_sensors == 3
    same = np.mean([a.status == b.status for a, b in zip(ref, got)])
    both = [k for k in range(len(rss)) if ref[k].status == got[k].status == "ok"]
    d = np.array([np.linalg.norm(ref[k].position_w_m - got[k].position_w_m) for k in both])
    no_worse = np.mean([ml_cost(got[k], rss[k], layout, pl) <= ml_cost(ref[k], rss[k], layout, pl) + 0.01
                        for k in both])
    err_ref = np.mean([np.linalg.norm(ref[k].position_w_m - truth[k]) for k in both])
    err_got = np.mean([np.linalg.norm(got[k].position_w_m - truth[k]) for k in both])
    assert same >= 0.98 and np.median(d) < 2e-5 and np.mean(d < 1e-4) > 0.8, (same, np.median(d), np.mean(d < 1e-4))
    assert no_worse > 0.95 and abs(err_got - err_ref) < 0.02 * err_ref, (no_worse, err_ref, err_got)
    # where the positions agree, so do the covariances (scipy's robust-scaled Jacobian)
    agree = [k for k, dk in zip(both, d) if dk < 1e-6]
    for k in agree:
        np.testing.assert_allclose(got[k].cov_m2, ref[k].cov_m2, rtol=1e-3, atol=1e-12)
    assert len(agree) >= 10  # measured 22-30


def test_fixes_on_demand_are_the_same_fixes_solved_only_where_read():
    from testbed.rf import SensorLayout, emulate_rf

    from bodyslam.fusion.rf import FixesOnDemand

    rng = np.random.default_rng(5)
    layout, pl = SensorLayout.thesis_grids(), PathLossModel()
    truth = rng.uniform([-0.1, -0.08, -0.1], [0.1, 0.08, 0.1], (130, 3))
    rss = emulate_rf(truth, layout, pl, rng=6)["rss_dbm"]
    lazy = FixesOnDemand(layout.positions_w_m, layout.normals_w, rss, pl, block=50)
    assert len(lazy) == 130 and lazy.n_solved == 0
    window = lazy[:40]  # a fusion's start window: one block solved, not the exam
    assert len(window) == 40 and lazy.n_solved == 50
    all_at_once = locate_ml_frames(layout.positions_w_m, layout.normals_w, rss, pl)
    for a, b in zip(list(lazy), all_at_once):  # blocks do not change a frame's fix
        assert a.status == b.status and np.array_equal(a.position_w_m, b.position_w_m)
    assert lazy.n_solved == 130
    assert lazy[-1] is lazy[129] and window[3] is lazy[3]
    with pytest.raises(IndexError):
        lazy[130]


def test_rf_csv_read_whole_equals_line_by_line(tmp_path):
    """A plain rf.csv is converted at once (numpy's parser); one with a bad line is read line by line to name it.
    Both give the same table: the same file with one unknown-sensor line appended (so it takes the line-by-line
    path) must give the same readings, bit for bit, and name only that line. Includes a sensor read twice at one
    time (the later line wins) and a blank line."""
    from bodyslam.fusion.rf import read_rf_columns

    rng = np.random.default_rng(3)
    names = ("F00", "F01", "B00")
    lines = ["t,sensor,rss_dbm,extra"]
    for k in range(40):
        for n in names:
            if rng.random() < 0.8:
                lines.append(f"{k * 0.5:g},{n},{rng.normal(-90, 8)!r},{rng.normal()!r}")
    lines[5:5] = ["", f"{lines[3].split(',')[0]},{lines[3].split(',')[1]},-55.25,1"]  # blank; a later duplicate
    plain = tmp_path / "plain.csv"
    plain.write_text("\n".join(lines) + "\n")
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n3.0,XX,-80,0\n")
    from bodyslam.fusion.rf import _rf_numbers

    index = {n: j for j, n in enumerate(names)}  # the two files do take the two paths
    assert _rf_numbers(plain, 0, 1, [2, 3], index) is not None and _rf_numbers(bad, 0, 1, [2, 3], index) is None
    s1, c1, p1 = read_rf_columns(plain, names, ("rss_dbm", "extra"))
    s2, c2, p2 = read_rf_columns(bad, names, ("rss_dbm", "extra"))
    assert p1 == [] and len(p2) == 1 and f"bad.csv:{len(lines) + 1}: unknown sensor 'XX'" in p2[0]
    assert np.array_equal(s1, s2) and len(s1) == 40
    # a sensor the list lacks altogether is one problem, at its first line, with its count (it was one per line:
    # 36,006 for six sensors left out of a 6,001-slot recording)
    many = tmp_path / "many.csv"
    many.write_text("\n".join(lines) + "".join(f"\n{20 + k},YY,-80,0" for k in range(5)) + "\n3.0,XX,-80,0\n")
    _, _, p3 = read_rf_columns(many, names, ("rss_dbm", "extra"))
    assert p3 == [f"{many}:{len(lines) + 1}: unknown sensor 'YY': not in the sensor list, its 5 lines skipped (this "
                  "the first)", f"{many}:{len(lines) + 6}: unknown sensor 'XX'"], p3
    for c in ("rss_dbm", "extra"):
        assert np.array_equal(c1[c], c2[c], equal_nan=True)
    t0, j0 = float(lines[3].split(",")[0]), names.index(lines[3].split(",")[1])
    assert c1["rss_dbm"][np.searchsorted(s1, t0), j0] == -55.25  # the later of the two lines


@pytest.mark.parametrize("block", [1, 2, 5])
def test_rf_csv_read_in_blocks_equals_at_once(tmp_path, monkeypatch, block):
    """rf.csv is read RF_BLOCK_LINES lines at a time (a 100,000-frame exam's 3.2 million lines at once took ~250
    MiB): blocks of 1, 2 and 5 lines -- a time's lines split between blocks, a sensor read again at one time in a
    later block (the later line wins) -- give the table of one block, for lines in time order, out of it (the
    blocks read so far turned back into lines), and with bad lines (read line by line, each named)."""
    import bodyslam.fusion.rf as rf

    rng = np.random.default_rng(4)
    names = ("F00", "F01", "B00")
    body = [f"{k * 0.5:g},{n},{rng.normal(-90, 8)!r}" for k in range(20) for n in names if rng.random() < 0.8]
    dup = [line for line in body if line.startswith("2,")][0]
    again = f"2,{dup.split(',')[1]},-55.25"
    files = {"plain": body[:body.index(dup) + 1] + ["", again] + body[body.index(dup) + 1:],
             "shuffled": [*body[:7], *rng.permutation(body[7:]), again],  # in order for 7 lines, then not
             "bad": [*body[:9], "3.0,XX,-80", *body[9:30], "4.5,F00,oops", *body[30:], again]}
    for name, lines in files.items():
        (tmp_path / f"{name}.csv").write_text("t,sensor,rss_dbm\n" + "\n".join(lines) + "\n")
    monkeypatch.setattr(rf, "RF_BLOCK_LINES", 10**9)
    once = {name: rf.read_rf_columns(tmp_path / f"{name}.csv", names, ("rss_dbm",)) for name in files}
    monkeypatch.setattr(rf, "RF_BLOCK_LINES", block)
    s1, c1, p1 = once["plain"]
    assert p1 == [] and len(s1) == 20 and c1["rss_dbm"][4, names.index(dup.split(",")[1])] == -55.25
    for name in files:
        s2, c2, p2 = rf.read_rf_columns(tmp_path / f"{name}.csv", names, ("rss_dbm",))
        assert p2 == once[name][2] and np.array_equal(s2, s1), name
        assert np.array_equal(c2["rss_dbm"], c1["rss_dbm"], equal_nan=True), name  # the same readings each time
    assert [p.split(":", 1)[1] for p in once["bad"][2]] == [
        "11: unknown sensor 'XX'", f"33: not a number ({{'t': '4.5', 'sensor': 'F00', 'rss_dbm': 'oops'}})"]
    index = {n: j for j, n in enumerate(names)}  # the bad file takes the line-by-line path, the others do not
    with pytest.raises(rf._NotPlain):
        list(rf._plain_blocks(tmp_path / "bad.csv", 0, 1, [2], index))
    assert len(list(rf._plain_blocks(tmp_path / "shuffled.csv", 0, 1, [2], index))) > 1


def test_rf_csv_short_line_with_the_sensor_column_last(tmp_path):
    """A line cut short before its sensor (the sensor column last) is named and skipped; the lines after it keep
    their own sensors (a line's numbers and sensor are taken together or not at all)."""
    from bodyslam.fusion.rf import read_rf_columns

    f = tmp_path / "rf.csv"
    f.write_text("t,rss_dbm,sensor\n0,-80,F00\n0,-81\n0,-82,F01\n0.5,-83,F00\n")
    stamps, cols, problems = read_rf_columns(f, ("F00", "F01"), ("rss_dbm",))
    assert len(problems) == 1 and "rf.csv:3: not a number" in problems[0], problems
    assert np.array_equal(stamps, [0.0, 0.5])
    assert np.array_equal(cols["rss_dbm"], [[-80.0, -82.0], [-83.0, np.nan]], equal_nan=True)


def test_a_sensor_layout_no_body_wears_is_refused(tmp_path):
    """sensors.csv in millimetres ran with a 2.5 m 1-sigma and no word of why; all sensors at one point ended in
    numpy's "SVD did not converge". Both are named, and a layout on a plane (one side of the body) still reads."""
    from bodyslam.errors import InputError
    from bodyslam.fusion.rf import read_sensors

    demo = (Path(__file__).resolve().parents[3] / "data_samples" / "demo_seed0" / "sensors.csv").read_text()
    header, rows = demo.splitlines()[0], [r.split(",") for r in demo.splitlines()[1:]]

    def write(rows_, name):
        p = tmp_path / name
        p.write_text("\n".join([header] + [",".join(r) for r in rows_]) + "\n")
        return p

    mm = [[r[0]] + [f"{1000 * float(v):g}" for v in r[1:4]] + r[4:] for r in rows]
    with pytest.raises(InputError, match="look like millimetres"):
        read_sensors(write(mm, "mm.csv"))
    far = [r[:1] + ["3.0"] + r[2:] if i == 5 else r for i, r in enumerate(rows)]
    with pytest.raises(InputError, match=r"sensor 'F05' is 2\.95 m from") as exc:
        read_sensors(write(far, "far.csv"))
    assert "millimetres" not in str(exc.value)  # one sensor astray is not a units mistake
    with pytest.raises(InputError, match="lie at one point"):
        read_sensors(write([r[:1] + ["0.1", "0.1", "0.1"] + r[4:] for r in rows], "point.csv"))
    with pytest.raises(InputError, match="lie on one line"):
        read_sensors(write([r[:1] + [f"{0.01 * i:g}", "0", "0"] + r[4:] for i, r in enumerate(rows)], "line.csv"))
    names, pos, _ = read_sensors(write([r for r in rows if r[0].startswith("F")], "front.csv"))
    assert len(names) == 16 and np.ptp(pos[:, 1]) == 0.0  # the front plane alone: a layout some systems wear


def test_readings_in_a_linear_unit_are_refused(tmp_path):
    """rss_dbm in mW (small positive numbers) ran with a 154-km 1-sigma and exit 0: a median above the transmit
    power, which no path loss allows, is refused; a few readings above it are outliers and pass to the solvers."""
    from bodyslam.errors import InputError
    from bodyslam.fusion.rf import check_rss_units

    pl = PathLossModel()
    dbm = np.array([[-80.0, -95.0, np.nan], [-70.0, -101.0, -88.0]])
    check_rss_units("rf.csv", dbm, pl)
    check_rss_units("rf.csv", np.where(np.arange(6).reshape(2, 3) == 0, 5.0, dbm), pl)  # one outlier above Pt
    with pytest.raises(InputError, match=r"rf\.csv: the readings' median, 1\.\d+e-09, lies above the transmit power "
                                         r"\(-16 dBm\).*linear unit"):
        check_rss_units("rf.csv", 10 ** (dbm / 10), pl)
