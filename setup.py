"""Build hook for the four compiled loops; everything else is in pyproject.toml.

- bodyslam/vision/_srm_merge.c: SRM's merge loop (bodyslam.vision.segmentation);
- bodyslam/vision/_tube_fit.c: the tube fit's residuals and its Levenberg-Marquardt loop (bodyslam.vision.motion),
  guided matching's window pairs (bodyslam.vision.guided);
- bodyslam/fusion/_ekf_rss.c: the raw-RSS filter's frames for one candidate (bodyslam.fusion.ekf);
- bodyslam/fusion/_block_tridiag.c: the whole-exam solve's marginal covariances (bodyslam.fusion.refine).

All are optional: where they cannot be built (no C compiler or no Python headers) the install goes on and the
same computations run in Python/numpy, slower (each module says so once in its log). -ffp-contract=off keeps
the double arithmetic as written (no fused multiply-add): the merge loop gives the same regions bit for bit, the
residuals agree with numpy's to ~1e-15.
"""

from setuptools import Extension, setup

FLAGS = ["-O2", "-ffp-contract=off"]
ROD = ["bodyslam/_rodrigues.h"]  # shared by the tube fit and the filter
setup(ext_modules=[
    Extension("bodyslam.vision._srm_merge", ["bodyslam/vision/_srm_merge.c"], optional=True, extra_compile_args=FLAGS),
    Extension("bodyslam.vision._tube_fit", ["bodyslam/vision/_tube_fit.c"], optional=True, extra_compile_args=FLAGS,
              libraries=["m"], depends=ROD),
    Extension("bodyslam.fusion._ekf_rss", ["bodyslam/fusion/_ekf_rss.c"], optional=True, extra_compile_args=FLAGS,
              libraries=["m"], depends=ROD),
    Extension("bodyslam.fusion._block_tridiag", ["bodyslam/fusion/_block_tridiag.c"], optional=True,
              extra_compile_args=FLAGS, libraries=["m"]),
])
