"""Build hook for the one compiled part: SRM's merge loop (bodyslam/vision/_srm_merge.c).

Everything else is in pyproject.toml. The extension is optional: where it cannot be built (no C compiler or no
Python headers) the install goes on and `bodyslam.vision.segmentation` runs the same loop in Python, ~30x slower
(it says so in its log). -ffp-contract=off keeps the double arithmetic identical to Python's (no fused
multiply-add), so both loops give the same regions bit for bit.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("bodyslam.vision._srm_merge", ["bodyslam/vision/_srm_merge.c"], optional=True,
                             extra_compile_args=["-O2", "-ffp-contract=off"])])
