"""Body-SLAM: localizing a wireless capsule endoscope from its video and RF signal.

Stages are one module each, in subpackages by system (see README, "Architecture"). This package never imports
:mod:`testbed`: the pipeline sees only what a capsule gives (frames, timestamps, RF readings, camera calibration).
"""

__version__ = "0.1.0"
