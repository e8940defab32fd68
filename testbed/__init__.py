"""Virtual intestine testbed: geometry, capsule motion, rendering and evaluation with exact ground truth.

May import :mod:`bodyslam` (camera models, file formats, errors); :mod:`bodyslam` never imports this package.
"""
