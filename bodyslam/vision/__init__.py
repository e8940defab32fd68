"""Body-SLAM's vision stages (dissertation Ch. 3.2): SRM segmentation and the FT/FL classifier, feature matching,
unrolling, per-step motion estimators, the visual-odometry engine that runs them over frames, dead reckoning
and speed statistics. Frames come from :mod:`bodyslam.frames`; steps are :class:`bodyslam.steps.StepMotion`."""
