/* Statistical Region Merging's merge loop (bodyslam.vision.segmentation.srm), compiled.

   The loop is sequential union-find over the pixel pairs in their sorted order, so numpy cannot vectorise it;
   in Python it is ~0.7 us per pair and a quarter of a frame's time in fast mode. This is the same loop, step for
   step (the same path halving, the same order of the three channel tests, the same tie rule for which root
   survives) and the same double arithmetic (built with -ffp-contract=off: no fused multiply-add), so it leaves
   `parent`, `size` and `sums` exactly as the Python loop does; tests/bodyslam/vision/test_segmentation.py checks
   it against the Python loop bit for bit.

   merge(pa, pb, b2_tab, parent, size, sums) -> None
     pa, pb   intp (E,)        the pairs' pixel indices, in merge order (read)
     b2_tab   float64 (n+1,)   b2 of a region of n pixels (read)
     parent   intp (N,)        union-find parents, updated in place (written)
     size     intp (N,)        region sizes at their roots (written)
     sums     float64 (N, 3)   per-channel sums at their roots, C order (written)
   All C-contiguous. Indices are not range-checked here: segmentation.py builds them from the image grid. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

static PyObject *merge(PyObject *self, PyObject *args) {
    Py_buffer pa, pb, tab, par, siz, sums;
    if (!PyArg_ParseTuple(args, "y*y*y*w*w*w*", &pa, &pb, &tab, &par, &siz, &sums))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t n_pairs = pa.len / (Py_ssize_t)sizeof(Py_ssize_t);
    Py_ssize_t n_pix = par.len / (Py_ssize_t)sizeof(Py_ssize_t);
    if (pb.len != pa.len || pa.len % (Py_ssize_t)sizeof(Py_ssize_t) != 0) {
        PyErr_SetString(PyExc_ValueError, "pa and pb must be intp arrays of one length");
        goto done;
    }
    if (siz.len != par.len || sums.len != 3 * n_pix * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "parent, size (intp, N) and sums (float64, N x 3) must agree");
        goto done;
    }
    {
        const Py_ssize_t *A = (const Py_ssize_t *)pa.buf, *B = (const Py_ssize_t *)pb.buf;
        const double *b2 = (const double *)tab.buf;
        Py_ssize_t *parent = (Py_ssize_t *)par.buf, *size = (Py_ssize_t *)siz.buf;
        double *s = (double *)sums.buf;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t e = 0; e < n_pairs; e++) {
            Py_ssize_t a = A[e], b = B[e];
            while (parent[a] != a) {
                parent[a] = parent[parent[a]];
                a = parent[a];
            }
            while (parent[b] != b) {
                parent[b] = parent[parent[b]];
                b = parent[b];
            }
            if (a == b)
                continue;
            Py_ssize_t na = size[a], nb = size[b];
            double thr = b2[na] + b2[nb], d;
            double fa = (double)na, fb = (double)nb;
            d = s[3 * a] / fa - s[3 * b] / fb;
            if (d * d > thr)
                continue;
            d = s[3 * a + 1] / fa - s[3 * b + 1] / fb;
            if (d * d > thr)
                continue;
            d = s[3 * a + 2] / fa - s[3 * b + 2] / fb;
            if (d * d > thr)
                continue;
            if (na < nb) {
                Py_ssize_t tmp = a;
                a = b;
                b = tmp;
            }
            parent[b] = a;
            size[a] = na + nb;
            s[3 * a] += s[3 * b];
            s[3 * a + 1] += s[3 * b + 1];
            s[3 * a + 2] += s[3 * b + 2];
        }
        Py_END_ALLOW_THREADS
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    PyBuffer_Release(&pa);
    PyBuffer_Release(&pb);
    PyBuffer_Release(&tab);
    PyBuffer_Release(&par);
    PyBuffer_Release(&siz);
    PyBuffer_Release(&sums);
    return ret;
}

static PyMethodDef methods[] = {
    {"merge", merge, METH_VARARGS, "SRM's merge loop over sorted pixel pairs (see the file's comment)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_srm_merge", NULL, -1, methods};

PyMODINIT_FUNC PyInit__srm_merge(void) { return PyModule_Create(&module); }
