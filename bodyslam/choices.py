"""Names of the pipeline's choices (matchers, estimators, fusion modes, trackers, schemes).

A light module on purpose: the CLIs build their option lists from it without importing OpenCV or SciPy, so
``bodyslam --help`` starts fast. The modules that implement each choice import their names from here and check
against them, so a choice is spelt in one place.
"""

from __future__ import annotations

__all__ = ["MATCH_MODES", "ESTIMATORS", "UNROLL_MODES", "FUSION_MODES", "TRACKERS", "SCHEMES", "CAMERAS"]

MATCH_MODES = ("asift", "sift", "fast")  # bodyslam.vision.matching.Matcher
ESTIMATORS = ("tube", "thesis")  # bodyslam.vision.motion.estimate_tube / estimate_thesis
UNROLL_MODES = ("exact", "thesis")  # bodyslam.vision.unroll.Unroller: camera model, or the linear Eq. 3.11
FUSION_MODES = ("rss", "fix")  # bodyslam.fusion.body_slam.fuse: EKF on raw RSS readings, or on ML position fixes
TRACKERS = ("toa_rssi_pf", "toa_pf_true_eps", "rssi_pf")  # bodyslam.systems.pf.track
SCHEMES = ("toa_doa_imu", "doa_imu", "toa_imu", "rf_only_cv", "rf_only", "imu_only")  # bodyslam.systems.toa_doa.run_scheme
CAMERAS = ("front", "rear")  # which camera of a (dual-camera) capsule
