"""Body-SLAM's RF side and the fusion (dissertation Ch. 2.3 and 3.3): RSS localization (``rf``), the
error-state EKF (``ekf``), the start/restart orientation search (``orientation_search``), the fusion over an
exam with RTS smoothing and the dissertation's KF (``body_slam``), and the one localization chain every
command calls (``localize``)."""
