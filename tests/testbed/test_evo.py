"""evo, the standard trajectory tool, reads our TUM files unchanged and reproduces our scores: the position error
(``evo_ape tum``, no alignment: both are in the body frame) and the orientation error (``-r angle_deg``) that
``testbed evaluate`` reports. Runs only where evo is installed (``pip install evo``); skipped otherwise."""

import re
import shutil
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyslam.io import write_tum

EVO_APE = shutil.which("evo_ape")
pytestmark = pytest.mark.skipif(EVO_APE is None, reason="evo is not installed (pip install evo)")


def _stat(out: str, name: str) -> float:
    m = re.search(rf"^\s*{name}\s+([-0-9.e+]+)\s*$", out, re.M)
    assert m, out
    return float(m.group(1))


def test_evo_reads_our_tum_files_and_gets_our_errors(tmp_path):
    rng = np.random.default_rng(3)
    n = 200
    t = np.arange(n) * 0.5
    gt_p = np.cumsum(rng.normal(0, 0.004, (n, 3)), axis=0)
    gt_R = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0))
    est_p = gt_p + rng.normal(0, 0.02, (n, 3))
    est_R = gt_R * Rotation.from_rotvec(rng.normal(0, 0.2, (n, 3)))
    write_tum(tmp_path / "groundtruth.tum", t, gt_p, gt_R)
    write_tum(tmp_path / "estimate.tum", t, est_p, est_R)
    # our scores: the evaluation's per-frame position error and orientation error (testbed.evaluate)
    e = np.linalg.norm(est_p - gt_p, axis=1)
    ang = np.degrees((est_R.inv() * gt_R).magnitude())
    for args, ours in ((["-r", "trans_part"], e), (["-r", "angle_deg"], ang)):
        p = subprocess.run([EVO_APE, "tum", str(tmp_path / "groundtruth.tum"), str(tmp_path / "estimate.tum"),
                            *args], capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        # evo prints 6 decimals (half a unit: 5e-7); TUM files keep 9 significant digits, far below that
        for name, v in (("rmse", np.sqrt(np.mean(ours**2))), ("mean", ours.mean()), ("max", ours.max())):
            assert _stat(p.stdout, name) == pytest.approx(float(v), abs=6e-7), (args, name)
