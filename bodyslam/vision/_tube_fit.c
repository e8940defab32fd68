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
   All C-contiguous.

   ring_residuals(P, b1, b2, radius, max_depth, noise_rad, prior_sigma, grid, ring, out) -> None
     The same for the tube with one contraction ring (bodyslam.vision.lumen_scale._ring_residuals): per ray the
     first crossing of the wall on the depth grid, then two regula-falsi steps inside its bracket, as there.
     P            float64 (B, 12)      the 10 above, then the ring's depth parameter and its place in radii
     grid         float64 (G,)         the depths tried, as fractions of max_depth, increasing
     ring         float64 (5,)         max depth |A|, width in radii, the depth's prior 1-sigma, the place's prior
                                       1-sigma in radii, the place's prior centre in radii
     out          float64 (B, 3n + 6)  per ray the three sine components, the four axis priors, the ring's two */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "../_rodrigues.h"

/* the tube's axis from the parameters: its unit direction a (p[6], p[7], 1 normalised) and u = a x o, o = (p[8],
   p[9], 0) its offset from the camera, so that a ray's point lam b lies |lam w - u| from the axis, w = b x a */
static void tube_axis(const double *p, double *ax, double *ay, double *az, double *ux, double *uy, double *uz) {
    double inv = 1.0 / sqrt(p[6] * p[6] + p[7] * p[7] + 1.0);
    double x = p[6] * inv, y = p[7] * inv, z = inv, ox = p[8], oy = p[9];
    *ax = x;
    *ay = y;
    *az = z;
    *ux = oy * z;
    *uy = -ox * z;
    *uz = ox * y - oy * x;
}

/* one ray's three residuals: its frame-1 point at depth lam (X = lam b1 - t) in frame 2's axes, R^T X (column j of
   R dotted with X), crossed with the frame-2 ray b2, over the noise and the point's range (the sine of their angle) */
static void ray_residual(const double R[9], const double *p, double lam, const double *b1, const double *b2,
                         double noise, double *o) {
    double Xx = lam * b1[0] - p[3], Xy = lam * b1[1] - p[4], Xz = lam * b1[2] - p[5];
    double x = R[0] * Xx + R[3] * Xy + R[6] * Xz;
    double y = R[1] * Xx + R[4] * Xy + R[7] * Xz;
    double z = R[2] * Xx + R[5] * Xy + R[8] * Xz;
    double s = 1.0 / (noise * sqrt(x * x + y * y + z * z));
    double cx = b2[0], cy = b2[1], cz = b2[2];
    o[0] = (cy * z - cz * y) * s;
    o[1] = (cz * x - cx * z) * s;
    o[2] = (cx * y - cy * x) * s;
}

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
            double R[9], ax, ay, az, ux, uy, uz;
            rodrigues(p, R);
            tube_axis(p, &ax, &ay, &az, &ux, &uy, &uz);
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
                ray_residual(R, p, lam, b1 + 3 * i, b2 + 3 * i, noise, o + 3 * i);
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

/* the squared distance of the ray's point at depth lam from the ringed tube's axis less the wall's squared radius
   (< 0 inside), as lumen_scale._ring_points' f */
static double ring_f(double lam, double ww, double wu, double uu, double ba, double radius, double A, double c,
                     double w) {
    double q = (lam * ba - c) / w;
    double r = radius * (1.0 - A * exp(-0.5 * (q * q)));
    return lam * lam * ww - 2.0 * lam * wu + uu - r * r;
}

static PyObject *ring_residuals(PyObject *self, PyObject *args) {
    Py_buffer pb, b1b, b2b, prb, gb, rb, outb;
    double radius, max_depth, noise;
    if (!PyArg_ParseTuple(args, "y*y*y*dddy*y*y*w*", &pb, &b1b, &b2b, &radius, &max_depth, &noise, &prb, &gb, &rb,
                          &outb))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t B = pb.len / (Py_ssize_t)(12 * sizeof(double));
    Py_ssize_t n = b1b.len / (Py_ssize_t)(3 * sizeof(double));
    Py_ssize_t G = gb.len / (Py_ssize_t)sizeof(double);
    Py_ssize_t width = 3 * n + 6;
    if (pb.len != B * 12 * (Py_ssize_t)sizeof(double) || b1b.len != n * 3 * (Py_ssize_t)sizeof(double)
        || b2b.len != b1b.len || prb.len != 4 * (Py_ssize_t)sizeof(double) || G < 1
        || gb.len != G * (Py_ssize_t)sizeof(double) || rb.len != 5 * (Py_ssize_t)sizeof(double)
        || outb.len != B * width * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "ring_residuals: P (B, 12), b1 and b2 (n, 3), prior_sigma (4,), grid (G,), "
                                          "ring (5,) and out (B, 3n + 6) float64 arrays");
        goto done;
    }
    {
        const double *P = (const double *)pb.buf, *b1 = (const double *)b1b.buf, *b2 = (const double *)b2b.buf;
        const double *ps = (const double *)prb.buf, *grid = (const double *)gb.buf, *ring = (const double *)rb.buf;
        double *out = (double *)outb.buf;
        double w = ring[1] * radius;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t k = 0; k < B; k++) {
            const double *p = P + 12 * k;
            double *o = out + width * k;
            double R[9], ax, ay, az, ux, uy, uz;
            rodrigues(p, R);
            tube_axis(p, &ax, &ay, &az, &ux, &uy, &uz);
            double A = ring[0] * tanh(p[10] / ring[0]), c = p[11] * radius;
            double uu = ux * ux + uy * uy + uz * uz;
            for (Py_ssize_t i = 0; i < n; i++) {
                double bx = b1[3 * i], by = b1[3 * i + 1], bz = b1[3 * i + 2];
                double wx = by * az - bz * ay, wy = bz * ax - bx * az, wz = bx * ay - by * ax;
                double ww = wx * wx + wy * wy + wz * wz;
                double wu = wx * ux + wy * uy + wz * uz;
                double ba = bx * ax + by * ay + bz * az;
                /* the first grid depth outside the wall (0 where none is: then no crossing) */
                Py_ssize_t first = 0;
                int hit = 0;
                double f1 = 0.0, f0 = 0.0;
                for (Py_ssize_t j = 0; j < G; j++) {
                    double fj = ring_f(max_depth * grid[j], ww, wu, uu, ba, radius, A, c, w);
                    if (fj >= 0.0) {
                        first = j;
                        hit = 1;
                        f1 = fj;
                        break;
                    }
                }
                double lam;
                if (!hit) {
                    lam = max_depth;
                } else {
                    Py_ssize_t j0 = first > 0 ? first - 1 : 0;
                    double l0 = max_depth * grid[j0], l1 = max_depth * grid[first];
                    f0 = j0 == first ? f1 : ring_f(l0, ww, wu, uu, ba, radius, A, c, w);
                    double lh;
                    if (first == 0) {
                        lh = l1;
                    } else {
                        lh = f1 != f0 ? l0 - f0 * (l1 - l0) / (f1 - f0) : l1;
                        for (int it = 0; it < 2; it++) { /* regula falsi inside the bracket */
                            double fh = ring_f(lh, ww, wu, uu, ba, radius, A, c, w);
                            if (fh < 0.0) {
                                l0 = lh;
                                f0 = fh;
                            } else {
                                l1 = lh;
                                f1 = fh;
                            }
                            lh = f1 != f0 ? l0 - f0 * (l1 - l0) / (f1 - f0) : lh;
                        }
                    }
                    lam = lh;
                    if (lam < 1e-4) lam = 1e-4; /* NaN stays NaN, as numpy's clip */
                    if (lam > max_depth) lam = max_depth;
                }
                ray_residual(R, p, lam, b1 + 3 * i, b2 + 3 * i, noise, o + 3 * i);
            }
            for (int q = 0; q < 4; q++)
                o[3 * n + q] = p[6 + q] / ps[q];
            o[3 * n + 4] = p[10] / ring[2];
            o[3 * n + 5] = (p[11] - ring[4]) / ring[3];
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
    PyBuffer_Release(&gb);
    PyBuffer_Release(&rb);
    PyBuffer_Release(&outb);
    return ret;
}

static PyMethodDef methods[] = {
    {"residuals", residuals, METH_VARARGS, "The tube fit's residuals for a batch of parameter vectors."},
    {"ring_residuals", ring_residuals, METH_VARARGS,
     "The residuals of the tube with one contraction ring for a batch of parameter vectors."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_tube_fit", NULL, -1, methods};

PyMODINIT_FUNC PyInit__tube_fit(void) { return PyModule_Create(&module); }
