/* The tube fit's residuals (bodyslam.vision.motion._tube_residuals_batch), its fitting loop and guided matching's
   window pairs, compiled.

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
     out          float64 (B, 3n + 6)  per ray the three sine components, the four axis priors, the ring's two

   lm(model, p, k, b1, b2, radius, max_depth, noise_rad, prior_sigma, grid, ring, x_scale, h, f_scale, max_iter, xtol,
      ftol, f_out, J_out) -> cost
     The fit's robust Levenberg-Marquardt loop (bodyslam.vision.motion._lm_soft_l1, its forward-difference Jacobian
     included) on one model: 0 the cylinder (10 parameters; grid and ring empty), 1 the ringed tube (12). Numpy's
     loop took ~2.5 ms a fit, 0.4 of it in the compiled residuals (session 67). The same steps, the same
     decisions, the cost summed as np.sum sums it; the normal equations and their solve (Gaussian elimination with
     partial pivoting) sum in another order than BLAS and LAPACK, so solutions agree to the rounding the fit's
     conditioning amplifies (test_motion.py, test_lumen_scale.py compare the two). A forward difference in the
     motion (parameters 0-5) keeps the rays' depths, which depend on the axis and the ring only: the same numbers
     for about half the work.
     p            float64 (10,) or (12,)  the start; overwritten with the solution
     k            the first k parameters are fitted (6: the axis held), the others stay as p gives them
     x_scale, h   float64 (k,)         the parameters' scales (the damping's metric) and forward-difference steps
     f_out        float64 (m,)         written: the residuals at the solution, m = 3n + 4 (model 0) or 3n + 6
     J_out        float64 (m, k)       written: the Jacobian there, rows scaled by (1 + f^2/f_scale^2)^-0.75 as
                                       scipy scales a robust loss's

   guided_pairs(uv, rows, pts2, dist12, radius, min_sep, ratio, out_i, out_j) -> k
     Guided matching's window pairs under one motion hypothesis (bodyslam.vision.guided.guided_candidates; its
     comment below). */
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

/* each frame-1 ray's depth on the cylinder of p's axis (capped at max_depth): lam (n). It depends on p[6:] only */
static void tube_depths(const double *p, const double *b1, Py_ssize_t n, double radius, double max_depth,
                        double *lam) {
    double r2 = radius * radius;
    double ax, ay, az, ux, uy, uz;
    tube_axis(p, &ax, &ay, &az, &ux, &uy, &uz);
    double uu = ux * ux + uy * uy + uz * uz - r2;
    for (Py_ssize_t i = 0; i < n; i++) {
        double bx = b1[3 * i], by = b1[3 * i + 1], bz = b1[3 * i + 2];
        double wx = by * az - bz * ay, wy = bz * ax - bx * az, wz = bx * ay - by * ax;
        double ww = wx * wx + wy * wy + wz * wz;
        double wu = wx * ux + wy * uy + wz * uz;
        double disc = wu * wu - ww * uu;
        double l = (wu + sqrt(disc > 0.0 ? disc : 0.0)) / ww;
        if (isfinite(l) && l > 0.0)
            l = l < max_depth ? l : max_depth;
        else
            l = max_depth;
        lam[i] = l;
    }
}

/* the rays' residuals (3n) of p's motion with the frame-1 points at depths lam */
static void rays_residual(const double *p, const double *lam, const double *b1, const double *b2, Py_ssize_t n,
                          double noise, double *o) {
    double R[9];
    rodrigues(p, R);
    for (Py_ssize_t i = 0; i < n; i++)
        ray_residual(R, p, lam[i], b1 + 3 * i, b2 + 3 * i, noise, o + 3 * i);
}

/* the squared distance of the ray's point at depth lam from the ringed tube's axis less the wall's squared radius
   (< 0 inside), as lumen_scale._ring_points' f */
static double ring_f(double lam, double ww, double wu, double uu, double ba, double radius, double A, double c,
                     double w) {
    double q = (lam * ba - c) / w;
    double r = radius * (1.0 - A * exp(-0.5 * (q * q)));
    return lam * lam * ww - 2.0 * lam * wu + uu - r * r;
}

/* each frame-1 ray's depth on the ringed tube of p's axis and ring: the first crossing of the wall on the depth grid,
   then two regula-falsi steps inside its bracket (lams, n). It depends on p[6:] only */
static void ring_depths(const double *p, const double *b1, Py_ssize_t n, double radius, double max_depth,
                        const double *grid, Py_ssize_t G, const double *ring, double *lams) {
    double w = ring[1] * radius;
    double ax, ay, az, ux, uy, uz;
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
        lams[i] = lam;
    }
}

/* the ringed tube's priors (6) from p (12) */
static void ring_priors(const double *p, const double *ps, const double *ring, double *o) {
    for (int q = 0; q < 4; q++)
        o[q] = p[6 + q] / ps[q];
    o[4] = p[10] / ring[2];
    o[5] = (p[11] - ring[4]) / ring[3];
}

/* a fit's fixed data: the model (0 the cylinder, 10 parameters; 1 the ringed tube, 12), its rays and constants */
typedef struct {
    int model;
    const double *b1, *b2, *ps, *grid, *ring;
    Py_ssize_t n, G;
    double radius, max_depth, noise;
} Problem;

/* the rays' depths (n) under p: they depend on p[6:] only (the axis, and the ring), not on the motion */
static void model_depths(const Problem *pr, const double *p, double *lam) {
    if (pr->model == 0)
        tube_depths(p, pr->b1, pr->n, pr->radius, pr->max_depth, lam);
    else
        ring_depths(p, pr->b1, pr->n, pr->radius, pr->max_depth, pr->grid, pr->G, pr->ring, lam);
}

/* the residuals (m) of p with the rays' depths lam */
static void model_from_depths(const Problem *pr, const double *p, const double *lam, double *o) {
    rays_residual(p, lam, pr->b1, pr->b2, pr->n, pr->noise, o);
    if (pr->model == 0)
        for (int q = 0; q < 4; q++)
            o[3 * pr->n + q] = p[6 + q] / pr->ps[q];
    else
        ring_priors(p, pr->ps, pr->ring, o + 3 * pr->n);
}

/* the residuals (B x m) of B parameter vectors P (B x dim); -1 with MemoryError set where memory ran out */
static int eval_batch(const Problem *pr, const double *P, Py_ssize_t B, double *out) {
    int dim = pr->model == 0 ? 10 : 12;
    Py_ssize_t m = 3 * pr->n + (pr->model == 0 ? 4 : 6);
    double *lam = malloc(sizeof(double) * (size_t)(pr->n > 0 ? pr->n : 1));
    if (!lam) {
        PyErr_NoMemory();
        return -1;
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < B; k++) {
        model_depths(pr, P + dim * k, lam);
        model_from_depths(pr, P + dim * k, lam, out + m * k);
    }
    Py_END_ALLOW_THREADS
    free(lam);
    return 0;
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
        Problem pr = {0, (const double *)b1b.buf, (const double *)b2b.buf, (const double *)prb.buf, NULL, NULL, n, 0,
                      radius, max_depth, noise};
        if (eval_batch(&pr, (const double *)pb.buf, B, (double *)outb.buf) != 0)
            goto done;
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
        Problem pr = {1, (const double *)b1b.buf, (const double *)b2b.buf, (const double *)prb.buf,
                      (const double *)gb.buf, (const double *)rb.buf, n, G, radius, max_depth, noise};
        if (eval_batch(&pr, (const double *)pb.buf, B, (double *)outb.buf) != 0)
            goto done;
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

/* numpy's pairwise summation (8 accumulators, blocks of 128), so that a cost is np.sum's to the last bit */
static double pairwise_sum(const double *a, Py_ssize_t n) {
    if (n < 8) {
        double res = 0.0;
        for (Py_ssize_t i = 0; i < n; i++)
            res += a[i];
        return res;
    }
    if (n <= 128) {
        double r[8];
        Py_ssize_t i;
        for (int j = 0; j < 8; j++)
            r[j] = a[j];
        for (i = 8; i < n - (n % 8); i += 8)
            for (int j = 0; j < 8; j++)
                r[j] += a[i + j];
        double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++)
            res += a[i];
        return res;
    }
    Py_ssize_t n2 = n / 2;
    n2 -= n2 % 8;
    return pairwise_sum(a, n2) + pairwise_sum(a + n2, n - n2);
}

/* 0.5 sum rho(f^2) with scipy's soft_l1 at scale c (c2 = c^2); tmp: m doubles of scratch */
static double soft_l1_cost(const double *f, Py_ssize_t m, double c2, double *tmp) {
    for (Py_ssize_t i = 0; i < m; i++)
        tmp[i] = sqrt(1.0 + f[i] * f[i] / c2) - 1.0;
    return c2 * pairwise_sum(tmp, m);
}

/* f = model(p) and J (m x k, row-major) by forward differences in the first k parameters (steps h). A difference in
   the motion (j < 6) keeps p's depths, which it does not change: the same numbers for ~half the work */
static void fun_jac(const Problem *pr, const double *p, int dim, int k, const double *h, Py_ssize_t m, double *f,
                    double *J, double *pt, double *fj, double *lam0, double *lamj) {
    model_depths(pr, p, lam0);
    model_from_depths(pr, p, lam0, f);
    for (int j = 0; j < k; j++) {
        for (int q = 0; q < dim; q++)
            pt[q] = p[q];
        pt[j] += h[j];
        if (j < 6) {
            model_from_depths(pr, pt, lam0, fj);
        } else {
            model_depths(pr, pt, lamj);
            model_from_depths(pr, pt, lamj, fj);
        }
        for (Py_ssize_t i = 0; i < m; i++)
            J[i * k + j] = (fj[i] - f[i]) / h[j];
    }
}

/* M x = b for a k x k M (row-major, overwritten) by Gaussian elimination with partial pivoting; x in b. -1 where
   a pivot is exactly 0 (LAPACK's singular matrix) */
static int solve_small(double *M, double *b, int k) {
    for (int c = 0; c < k; c++) {
        int piv = c;
        double best = fabs(M[c * k + c]);
        for (int r = c + 1; r < k; r++)
            if (fabs(M[r * k + c]) > best) {
                best = fabs(M[r * k + c]);
                piv = r;
            }
        if (M[piv * k + c] == 0.0)
            return -1;
        if (piv != c) {
            for (int q = 0; q < k; q++) {
                double t = M[c * k + q];
                M[c * k + q] = M[piv * k + q];
                M[piv * k + q] = t;
            }
            double t = b[c];
            b[c] = b[piv];
            b[piv] = t;
        }
        for (int r = c + 1; r < k; r++) {
            double l = M[r * k + c] / M[c * k + c];
            for (int q = c; q < k; q++)
                M[r * k + q] -= l * M[c * k + q];
            b[r] -= l * b[c];
        }
    }
    for (int c = k - 1; c >= 0; c--) {
        double s = b[c];
        for (int q = c + 1; q < k; q++)
            s -= M[c * k + q] * b[q];
        b[c] = s / M[c * k + c];
    }
    return 0;
}

static double scaled_norm(const double *v, const double *xs, int k) {
    double s = 0.0;
    for (int j = 0; j < k; j++)
        s += (v[j] / xs[j]) * (v[j] / xs[j]);
    return sqrt(s);
}

/* motion._lm_soft_l1 on the model: p (dim) in and out, f (m) and J (m x k, scaled as scipy scales a robust loss's)
   out; returns the cost, or -1 where memory ran out */
static double lm_run(const Problem *pr, double *p, int dim, int k, const double *xs, const double *h, double f_scale,
                     int max_iter, double xtol, double ftol, Py_ssize_t m, double *f, double *J) {
    double c2 = f_scale * f_scale;
    double *buf = malloc(sizeof(double) * (size_t)(4 * m + 2 * pr->n + 2 * k * k + 3 * k + 2 * dim));
    if (!buf)
        return -1.0;
    double *fn = buf, *fj = fn + m, *w = fj + m, *tmp = w + m, *lam0 = tmp + m, *lamj = lam0 + pr->n,
           *A = lamj + pr->n, *Mm = A + k * k, *g = Mm + k * k, *step = g + k, *D = step + k, *pt = D + k,
           *pn = pt + dim;
    fun_jac(pr, p, dim, k, h, m, f, J, pt, fj, lam0, lamj);
    double cost = soft_l1_cost(f, m, c2, tmp);
    for (int j = 0; j < k; j++)
        D[j] = 1.0 / (xs[j] * xs[j]);
    double lam = 1e-1;
    for (int it = 0; it < max_iter; it++) {
        for (Py_ssize_t i = 0; i < m; i++)
            w[i] = 1.0 / sqrt(1.0 + f[i] * f[i] / c2);
        /* g = (J w)^T f and A = J^T (J w), each sum over the residuals in their order, row by row */
        for (int a = 0; a < k * k; a++)
            A[a] = 0.0;
        for (int a = 0; a < k; a++)
            g[a] = 0.0;
        for (Py_ssize_t i = 0; i < m; i++) {
            const double *row = J + i * k;
            double wi = w[i], fi = f[i];
            for (int a = 0; a < k; a++) {
                double ra = row[a];
                g[a] += ra * wi * fi;
                for (int b = a; b < k; b++)
                    A[a * k + b] += ra * (row[b] * wi);
            }
        }
        for (int a = 0; a < k; a++)
            for (int b = a + 1; b < k; b++)
                A[b * k + a] = A[a * k + b];
        double cost_new = 0.0;
        int accepted = 0;
        for (;;) {
            for (int a = 0; a < k * k; a++)
                Mm[a] = A[a];
            for (int a = 0; a < k; a++) {
                Mm[a * k + a] += lam * (A[a * k + a] > D[a] ? A[a * k + a] : D[a]);
                step[a] = g[a];
            }
            if (solve_small(Mm, step, k) != 0) {
                lam *= 10.0;
                if (lam > 1e12)
                    break;
                continue;
            }
            for (int a = 0; a < k; a++)
                step[a] = -step[a];
            for (int q = 0; q < dim; q++)
                pn[q] = p[q];
            for (int a = 0; a < k; a++)
                pn[a] = p[a] + step[a];
            model_depths(pr, pn, lamj);
            model_from_depths(pr, pn, lamj, fn);
            cost_new = soft_l1_cost(fn, m, c2, tmp);
            if (isfinite(cost_new) && cost_new < cost) {
                accepted = 1;
                break;
            }
            lam *= 10.0;
            if (lam > 1e12)
                break;
        }
        if (!accepted)
            break;
        for (int a = 0; a < k; a++)
            p[a] = pn[a];
        int done = (cost - cost_new) < ftol * cost || scaled_norm(step, xs, k) < xtol * (scaled_norm(p, xs, k) + xtol);
        fun_jac(pr, p, dim, k, h, m, f, J, pt, fj, lam0, lamj);
        cost = cost_new;
        lam = lam / 10.0 > 1e-9 ? lam / 10.0 : 1e-9;
        if (done)
            break;
    }
    for (Py_ssize_t i = 0; i < m; i++) {
        double s = pow(1.0 + f[i] * f[i] / c2, -0.75);
        for (int a = 0; a < k; a++)
            J[i * k + a] *= s;
    }
    free(buf);
    return cost;
}

/* lm(model, p, k, b1, b2, radius, max_depth, noise, prior_sigma, grid, ring, x_scale, h, f_scale, max_iter, xtol,
      ftol, f_out, J_out) -> cost; p (dim,) is the start and is overwritten with the solution */
static PyObject *lm(PyObject *self, PyObject *args) {
    int model, k, max_iter;
    Py_buffer pb, b1b, b2b, prb, gb, rb, xsb, hb, fb, jb;
    double radius, max_depth, noise, f_scale, xtol, ftol;
    if (!PyArg_ParseTuple(args, "iw*iy*y*dddy*y*y*y*y*diddw*w*", &model, &pb, &k, &b1b, &b2b, &radius, &max_depth,
                          &noise, &prb, &gb, &rb, &xsb, &hb, &f_scale, &max_iter, &xtol, &ftol, &fb, &jb))
        return NULL;
    PyObject *ret = NULL;
    int dim = model == 0 ? 10 : 12;
    Py_ssize_t n = b1b.len / (Py_ssize_t)(3 * sizeof(double));
    Py_ssize_t m = 3 * n + (model == 0 ? 4 : 6);
    Py_ssize_t G = gb.len / (Py_ssize_t)sizeof(double);
    Py_ssize_t D8 = (Py_ssize_t)sizeof(double);
    if ((model != 0 && model != 1) || k < 1 || k > dim || pb.len != dim * D8 || b1b.len != n * 3 * D8
        || b2b.len != b1b.len || prb.len != 4 * D8 || (model == 1 && (G < 1 || gb.len != G * D8 || rb.len != 5 * D8))
        || xsb.len != k * D8 || hb.len != k * D8 || fb.len != m * D8 || jb.len != m * k * D8) {
        PyErr_SetString(PyExc_ValueError, "lm: model 0 or 1, p (10 or 12,), k free parameters, b1 and b2 (n, 3), "
                                          "prior_sigma (4,), grid (G,) and ring (5,) for model 1, x_scale and h (k,), "
                                          "f_out (m,) and J_out (m, k) float64 arrays");
        goto done;
    }
    {
        Problem pr = {model, (const double *)b1b.buf, (const double *)b2b.buf, (const double *)prb.buf,
                      (const double *)gb.buf, (const double *)rb.buf, n, G, radius, max_depth, noise};
        double cost;
        Py_BEGIN_ALLOW_THREADS
        cost = lm_run(&pr, (double *)pb.buf, dim, k, (const double *)xsb.buf, (const double *)hb.buf, f_scale,
                      max_iter, xtol, ftol, m, (double *)fb.buf, (double *)jb.buf);
        Py_END_ALLOW_THREADS
        if (cost == -1.0)
            PyErr_NoMemory();
        else
            ret = PyFloat_FromDouble(cost);
    }
done:
    PyBuffer_Release(&pb);
    PyBuffer_Release(&b1b);
    PyBuffer_Release(&b2b);
    PyBuffer_Release(&prb);
    PyBuffer_Release(&gb);
    PyBuffer_Release(&rb);
    PyBuffer_Release(&xsb);
    PyBuffer_Release(&hb);
    PyBuffer_Release(&fb);
    PyBuffer_Release(&jb);
    return ret;
}

/* ---- guided matching's candidate pairs (bodyslam.vision.guided.guided_candidates) ---- */

/* guided_pairs(uv, rows, pts2, dist12, radius, min_sep, ratio, out_i, out_j) -> k
     For each predicted frame-1 keypoint uv[r] (in order), the frame-2 keypoints within radius (d^2 <= radius^2, as
     scipy's cKDTree.sparse_distance_matrix keeps them); among them the nearest descriptor (dist12[rows[r], j],
     float32; ties: the lower j) and the nearest among those more than min_sep from it; kept where best < ratio x
     second, in float32 as numpy computes it. Writes out_i = rows[r], out_j = the best j of the k rows kept.
     uv (m, 2) float64, rows (m,) int64, pts2 (n2, 2) float64, dist12 (n1, n2) float32, out_i and out_j (m,) int64.
     The same pairs as the numpy version (tests/bodyslam/vision/test_guided.py), ~5x faster: a grid of cells at
     least radius wide instead of a kd-tree, and no arrays of every candidate pair. */
static PyObject *guided_pairs(PyObject *self, PyObject *args) {
    Py_buffer ub, rb, pb, db, oib, ojb;
    double radius, min_sep, ratio;
    if (!PyArg_ParseTuple(args, "y*y*y*y*dddw*w*", &ub, &rb, &pb, &db, &radius, &min_sep, &ratio, &oib, &ojb))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m = rb.len / (Py_ssize_t)sizeof(long long), n2 = pb.len / (Py_ssize_t)(2 * sizeof(double));
    Py_ssize_t n1 = n2 > 0 ? db.len / (Py_ssize_t)(n2 * sizeof(float)) : 0;
    if (ub.len != m * 2 * (Py_ssize_t)sizeof(double) || pb.len != n2 * 2 * (Py_ssize_t)sizeof(double)
        || (n2 > 0 && db.len != n1 * n2 * (Py_ssize_t)sizeof(float)) || oib.len != m * (Py_ssize_t)sizeof(long long)
        || ojb.len != oib.len || !(radius >= 0.0)) {
        PyErr_SetString(PyExc_ValueError, "guided_pairs: uv (m, 2) and pts2 (n2, 2) float64, rows (m,) int64, "
                                          "dist12 (n1, n2) float32, out_i and out_j (m,) int64, radius >= 0");
        goto done;
    }
    {
        const double *uv = (const double *)ub.buf, *p2 = (const double *)pb.buf;
        const long long *rows = (const long long *)rb.buf;
        const float *d12 = (const float *)db.buf;
        long long *oi = (long long *)oib.buf, *oj = (long long *)ojb.buf;
        for (Py_ssize_t r = 0; r < m; r++)
            if (rows[r] < 0 || rows[r] >= n1) {
                PyErr_SetString(PyExc_ValueError, "guided_pairs: a row outside dist12");
                goto done;
            }
        Py_ssize_t k = 0;
        if (n2 > 0 && m > 0) {
            /* the grid: cells at least radius wide (so a window spans 3 x 3 of them), at most ~1024 a side */
            double x0 = p2[0], y0 = p2[1], x1 = p2[0], y1 = p2[1];
            for (Py_ssize_t j = 1; j < n2; j++) {
                x0 = p2[2 * j] < x0 ? p2[2 * j] : x0;
                x1 = p2[2 * j] > x1 ? p2[2 * j] : x1;
                y0 = p2[2 * j + 1] < y0 ? p2[2 * j + 1] : y0;
                y1 = p2[2 * j + 1] > y1 ? p2[2 * j + 1] : y1;
            }
            double ext = (x1 - x0) > (y1 - y0) ? (x1 - x0) : (y1 - y0);
            double cell = radius > ext / 1024.0 ? radius : ext / 1024.0;
            if (!(cell > 0.0))
                cell = 1.0;
            Py_ssize_t nx = (Py_ssize_t)((x1 - x0) / cell) + 1, ny = (Py_ssize_t)((y1 - y0) / cell) + 1;
            Py_ssize_t *start = calloc((size_t)(nx * ny + 1), sizeof(Py_ssize_t));
            Py_ssize_t *order = malloc(sizeof(Py_ssize_t) * (size_t)n2);
            Py_ssize_t *cellof = malloc(sizeof(Py_ssize_t) * (size_t)n2);
            Py_ssize_t *cand = malloc(sizeof(Py_ssize_t) * (size_t)n2);
            if (!start || !order || !cellof || !cand) {
                free(start);
                free(order);
                free(cellof);
                free(cand);
                PyErr_NoMemory();
                goto done;
            }
            Py_BEGIN_ALLOW_THREADS
            for (Py_ssize_t j = 0; j < n2; j++) { /* counting sort of the points by cell, j ascending in each */
                Py_ssize_t cx = (Py_ssize_t)((p2[2 * j] - x0) / cell), cy = (Py_ssize_t)((p2[2 * j + 1] - y0) / cell);
                cx = cx < nx ? cx : nx - 1;
                cy = cy < ny ? cy : ny - 1;
                cellof[j] = cy * nx + cx;
                start[cellof[j] + 1]++;
            }
            for (Py_ssize_t c = 0; c < nx * ny; c++)
                start[c + 1] += start[c];
            {
                Py_ssize_t *fill = malloc(sizeof(Py_ssize_t) * (size_t)(nx * ny));
                if (fill) {
                    for (Py_ssize_t c = 0; c < nx * ny; c++)
                        fill[c] = start[c];
                    for (Py_ssize_t j = 0; j < n2; j++)
                        order[fill[cellof[j]]++] = j;
                    free(fill);
                } else {
                    nx = -1; /* out of memory: reported below */
                }
            }
            double r2 = radius * radius;
            float fratio = (float)ratio;
            for (Py_ssize_t r = 0; nx > 0 && r < m; r++) {
                double u = uv[2 * r], v = uv[2 * r + 1], fu = (u - x0) / cell, fv = (v - y0) / cell;
                if (!(fu > -2.0 && fu < (double)nx + 1.0 && fv > -2.0 && fv < (double)ny + 1.0))
                    continue; /* more than a cell off the points: none within radius (and no overflow below) */
                Py_ssize_t cx = (Py_ssize_t)floor(fu), cy = (Py_ssize_t)floor(fv);
                Py_ssize_t nc = 0;
                const float *drow = d12 + rows[r] * n2;
                float best = 0.0f;
                Py_ssize_t bj = -1;
                for (Py_ssize_t gy = cy - 1; gy <= cy + 1; gy++) {
                    if (gy < 0 || gy >= ny)
                        continue;
                    for (Py_ssize_t gx = cx - 1; gx <= cx + 1; gx++) {
                        if (gx < 0 || gx >= nx)
                            continue;
                        for (Py_ssize_t q = start[gy * nx + gx]; q < start[gy * nx + gx + 1]; q++) {
                            Py_ssize_t j = order[q];
                            double dx = u - p2[2 * j], dy = v - p2[2 * j + 1];
                            if (dx * dx + dy * dy <= r2) {
                                cand[nc++] = j;
                                float d = drow[j];
                                if (bj < 0 || d < best || (d == best && j < bj)) {
                                    best = d;
                                    bj = j;
                                }
                            }
                        }
                    }
                }
                if (bj < 0)
                    continue;
                float second = INFINITY;
                double bx = p2[2 * bj], by = p2[2 * bj + 1];
                for (Py_ssize_t c = 0; c < nc; c++) {
                    Py_ssize_t j = cand[c];
                    double dx = p2[2 * j] - bx, dy = p2[2 * j + 1] - by;
                    if (sqrt(dx * dx + dy * dy) > min_sep && drow[j] < second)
                        second = drow[j];
                }
                float lim = fratio * second;
                if (best < lim) {
                    oi[k] = rows[r];
                    oj[k] = bj;
                    k++;
                }
            }
            Py_END_ALLOW_THREADS
            free(start);
            free(order);
            free(cellof);
            free(cand);
            if (nx < 0) {
                PyErr_NoMemory();
                goto done;
            }
        }
        ret = PyLong_FromSsize_t(k);
    }
done:
    PyBuffer_Release(&ub);
    PyBuffer_Release(&rb);
    PyBuffer_Release(&pb);
    PyBuffer_Release(&db);
    PyBuffer_Release(&oib);
    PyBuffer_Release(&ojb);
    return ret;
}

static PyMethodDef methods[] = {
    {"residuals", residuals, METH_VARARGS, "The tube fit's residuals for a batch of parameter vectors."},
    {"ring_residuals", ring_residuals, METH_VARARGS,
     "The residuals of the tube with one contraction ring for a batch of parameter vectors."},
    {"lm", lm, METH_VARARGS, "The tube fit's robust Levenberg-Marquardt loop (motion._lm_soft_l1) on either model."},
    {"guided_pairs", guided_pairs, METH_VARARGS, "Guided matching's candidate pairs under one motion hypothesis."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_tube_fit", NULL, -1, methods};

PyMODINIT_FUNC PyInit__tube_fit(void) { return PyModule_Create(&module); }
