/* The tube fit's residuals (bodyslam.vision.motion._tube_residuals_batch), compiled.

   The fit evaluates its residuals ~15 times per step on a batch of 11 parameter vectors (the point and its 10
   forward differences) and ~150 rays; in numpy that is ~40 array operations per call, whose per-call cost, not
   arithmetic, is the time (a third of a frame's time in fast mode). This is the same arithmetic written per
   ray: the same formulas as motion.py's numpy version (Rodrigues with its series below 1e-4 rad, the ray-cylinder
   depth capped at max_depth, the sine vector between the frame-2 ray and the tube point over the noise), equal
   to ~1e-15 relative (the order of a few additions differs); tests/bodyslam/vision/test_motion.py compares them.

   residuals(P, b1, b2, radius, max_depth, noise_rad, prior_sigma, out) -> None
     P            float64 (B, 10)      rotation vector of R_c1_c2, t_c1_c2, axis direction (ax, ay), offset
     b1, b2       float64 (n, 3)       unit rays of the matches in frames 1 and 2
     prior_sigma  float64 (4,)         the axis parameters' prior 1-sigma
     out          float64 (B, 3n + 4)  written: per ray the three sine components, then the four priors
   All C-contiguous. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "../_rodrigues.h"

static PyObject *residuals(PyObject *self, PyObject *args) {
    Py_buffer pb, b1b, b2b, prb, outb;
    double radius, max_depth, noise;
    if (!PyArg_ParseTuple(args, "y*y*y*dddy*w*", &pb, &b1b, &b2b, &radius, &max_depth, &noise, &prb, &outb))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t B = pb.len / (Py_ssize_t)(10 * sizeof(double));
    Py_ssize_t n = b1b.len / (Py_ssize_t)(3 * sizeof(double));
    Py_ssize_t width = 3 * n + 4;
    if (pb.len != B * 10 * (Py_ssize_t)sizeof(double) || b1b.len != n * 3 * (Py_ssize_t)sizeof(double)
        || b2b.len != b1b.len || prb.len != 4 * (Py_ssize_t)sizeof(double)
        || outb.len != B * width * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "residuals: P (B, 10), b1 and b2 (n, 3), prior_sigma (4,) and "
                                          "out (B, 3n + 4) float64 arrays");
        goto done;
    }
    {
        const double *P = (const double *)pb.buf, *b1 = (const double *)b1b.buf, *b2 = (const double *)b2b.buf;
        const double *ps = (const double *)prb.buf;
        double *out = (double *)outb.buf;
        double r2 = radius * radius;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t k = 0; k < B; k++) {
            const double *p = P + 10 * k;
            double *o = out + width * k;
            double R[9];
            rodrigues(p, R);
            double ax = p[6], ay = p[7];
            double inv = 1.0 / sqrt(ax * ax + ay * ay + 1.0);
            ax *= inv;
            ay *= inv;
            double az = inv, ox = p[8], oy = p[9];
            double ux = oy * az, uy = -ox * az, uz = ox * ay - oy * ax;
            double uu = ux * ux + uy * uy + uz * uz - r2;
            for (Py_ssize_t i = 0; i < n; i++) {
                double bx = b1[3 * i], by = b1[3 * i + 1], bz = b1[3 * i + 2];
                double wx = by * az - bz * ay, wy = bz * ax - bx * az, wz = bx * ay - by * ax;
                double ww = wx * wx + wy * wy + wz * wz;
                double wu = wx * ux + wy * uy + wz * uz;
                double disc = wu * wu - ww * uu;
                double lam = (wu + sqrt(disc > 0.0 ? disc : 0.0)) / ww;
                if (isfinite(lam) && lam > 0.0)
                    lam = lam < max_depth ? lam : max_depth;
                else
                    lam = max_depth;
                double Xx = lam * bx - p[3], Xy = lam * by - p[4], Xz = lam * bz - p[5];
                /* R^T (X - t): column j of R dotted with X */
                double x = R[0] * Xx + R[3] * Xy + R[6] * Xz;
                double y = R[1] * Xx + R[4] * Xy + R[7] * Xz;
                double z = R[2] * Xx + R[5] * Xy + R[8] * Xz;
                double s = 1.0 / (noise * sqrt(x * x + y * y + z * z));
                double cx = b2[3 * i], cy = b2[3 * i + 1], cz = b2[3 * i + 2];
                o[3 * i] = (cy * z - cz * y) * s;
                o[3 * i + 1] = (cz * x - cx * z) * s;
                o[3 * i + 2] = (cx * y - cy * x) * s;
            }
            for (int q = 0; q < 4; q++)
                o[3 * n + q] = p[6 + q] / ps[q];
        }
        Py_END_ALLOW_THREADS
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    PyBuffer_Release(&pb);
    PyBuffer_Release(&b1b);
    PyBuffer_Release(&b2b);
    PyBuffer_Release(&prb);
    PyBuffer_Release(&outb);
    return ret;
}

static PyMethodDef methods[] = {
    {"residuals", residuals, METH_VARARGS, "The tube fit's residuals for a batch of parameter vectors."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_tube_fit", NULL, -1, methods};

PyMODINIT_FUNC PyInit__tube_fit(void) { return PyModule_Create(&module); }
