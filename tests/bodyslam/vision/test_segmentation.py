"""SRM's merge loop: the compiled one (``_srm_merge.c``) against the Python one, bit for bit.

(SRM's behaviour on frames is tested in test_classify.py, with the features built on it.)"""

import logging
import shutil

import numpy as np
import pytest

from bodyslam.vision import segmentation
from bodyslam.vision.segmentation import srm

needs_c = pytest.mark.skipif(segmentation._merge_c is None, reason="the compiled merge loop is not built here")


def _images():
    """Images that exercise every branch: few grey levels (ties in the pair order and equal region means), full
    range noise, and blocks that differ in one channel only (merges refused by the second or third test)."""
    rng = np.random.default_rng(7)
    out = []
    for i in range(12):
        levels = (2, 4, 256)[i % 3]
        img = rng.integers(0, levels, (41, 37, 3)).astype(np.uint8) * (255 // max(levels - 1, 1))
        out.append((img, rng.random((41, 37)) < 0.85))
    for c in range(3):
        img = np.full((48, 48, 3), 120, np.uint8)
        img[:, 24:, c] = 200  # two halves that differ in channel c only
        img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
        out.append((img, np.ones((48, 48), bool)))
    yy, xx = np.mgrid[:120, :160]
    disc = (xx - 80) ** 2 + (yy - 60) ** 2 < 55**2
    img = np.stack([150 + 60 * np.sin(xx / 9.0), 90 + 40 * np.cos(yy / 7.0), 70 + 0 * xx], -1)
    img[(xx - 90) ** 2 + (yy - 55) ** 2 < 15**2] = (25, 12, 8)  # a dark tunnel
    out.append((np.clip(img + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8), disc))
    return out


@needs_c
@pytest.mark.parametrize("work_px", [None, 32, 64])
def test_compiled_merge_loop_gives_the_python_loops_regions(monkeypatch, work_px):
    compiled = [srm(img, mask, work_px=work_px) for img, mask in _images()]
    monkeypatch.setattr(segmentation, "_merge_c", None)
    python = [srm(img, mask, work_px=work_px) for img, mask in _images()]
    n_regions = []
    for a, b in zip(compiled, python):
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.sizes, b.sizes)
        np.testing.assert_array_equal(a.means, b.means)  # the same sums in the same order: exactly equal
        n_regions.append(a.n_regions)
    assert len(set(n_regions)) > 3 and max(n_regions) > 10  # not a trivial segmentation everywhere


@needs_c
def test_compiled_merge_loop_checks_its_arrays():
    n = 6
    pa = np.arange(n - 1, dtype=np.intp)
    ok = dict(pa=pa, pb=pa + 1, tab=np.ones(n + 1), parent=np.arange(n, dtype=np.intp), size=np.ones(n, np.intp),
              sums=np.zeros((n, 3)))
    segmentation._merge_c.merge(*ok.values())
    assert (ok["size"][ok["parent"] == np.arange(n)] == n).all()  # equal colours: all merged into one root
    with pytest.raises(ValueError, match="one length"):
        segmentation._merge_c.merge(pa, pa[:-1], *list(ok.values())[2:])
    with pytest.raises(ValueError, match="must agree"):
        segmentation._merge_c.merge(pa, pa + 1, ok["tab"], ok["parent"], ok["size"], np.zeros((n, 2)))


def test_the_compiled_loop_is_built_where_a_compiler_is():
    """``pip install -e .`` builds it where a C compiler is at hand; losing it silently would make classification
    ~3x slower (fast mode's whole exams ~20%)."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler here: the Python loop is used")
    assert segmentation._merge_c is not None, "bodyslam/vision/_srm_merge.c was not built (pip install -e .)"


def test_the_python_loop_says_it_is_used_once(monkeypatch, caplog):
    monkeypatch.setattr(segmentation, "_merge_c", None)
    monkeypatch.setattr(segmentation, "_warned", False)
    img, mask = _images()[0]
    with caplog.at_level(logging.INFO, logger="bodyslam.vision.segmentation"):
        srm(img, mask, work_px=None)
        srm(img, mask, work_px=None)
    assert sum("compiled merge loop" in r.getMessage() for r in caplog.records) == 1


def test_regions_are_numbered_as_np_unique_numbers_their_roots():
    """Regions are numbered by their root pixel's rank among the roots (np.unique's numbering, without its sort),
    -1 outside the field; the working mask is remembered per mask and size, and a mask of another dtype with the
    same pattern is not taken for it (a 0/255 mask averages differently on the field stop's edge)."""
    rng = np.random.default_rng(3)
    for n, n_roots in ((1, 1), (50, 7), (400, 400), (1000, 13)):
        roots_of = rng.choice(n, n_roots, replace=False)
        roots = roots_of[rng.integers(0, n_roots, n)]
        roots[roots_of] = roots_of  # a root is its own root
        out = rng.random(n) < 0.2
        roots[out & ~np.isin(np.arange(n), roots[~out])] = -1  # outside the field (no inside pixel's root)
        uniq, inv = np.unique(roots, return_inverse=True)
        ref = inv.astype(np.int32) - (1 if uniq[0] == -1 else 0)
        ref[roots == -1] = -1
        assert np.array_equal(segmentation._region_labels(roots), ref)
    segmentation._WORK_MASKS.clear()
    disc = _images()[-1][1]
    as_bool = segmentation._work_mask(disc, (40, 30))
    as_u8 = segmentation._work_mask(disc.astype(np.uint8) * 255, (40, 30))
    assert segmentation._work_mask(disc.copy(), (40, 30)) is as_bool and as_u8.sum() > as_bool.sum()
