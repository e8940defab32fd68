/* The raw-RSS error-state EKF's frames for one candidate (bodyslam.fusion.ekf.ErrorStateEkf.run), compiled.

   A whole exam's filter runs predict + update once per frame for one candidate: ~60 numpy operations on arrays of
   3 to 32 numbers, whose per-call cost, not arithmetic, was the time (~0.4 ms a frame, 4 s of a 10,000-frame
   exam's serial end). This is the same arithmetic written out: the process model with the optional scale state
   (ErrorStateEkf.predict), the RSS update in its information form with the per-reading 99.9% gate, the
   divergence guard and the Woodbury step over the position block (ErrorStateEkf.update), Rodrigues with its series
   below 1e-4 rad (bodyslam/_rodrigues.h). It agrees with the numpy path to rounding (sums in another order:
   measured 5e-15 m, 2e-15 on covariances; tests/bodyslam/fusion/test_ekf.py runs both). Not covered (numpy
   runs them): several candidates at once, fix mode, the RSS bias states.

   run(state, steps, rss, sensors, normals, params, out, a, b, predict_first, n_scale, keep) -> None
     state    float64 (3 + 9 + D*D + n_scale + 4,)  read and written: p, R (row-major), P, [s], nll, streak,
                                                     n_rejected, n_updates; D = 6 + n_scale
     steps    float64 (n - 1, 15)   per step: translation applied (3), R_step (9), sigma_t, sigma_r, rho_scale
     rss      float64 (n, m)        readings (NaN: none)
     sensors, normals  float64 (m, 3)
     params   float64 (14,)         pt, d0, near depth, near (PL0, alpha, sigma), deep (PL0, alpha, sigma),
                                    max rejections, z gate, guard position sigma, guard angle sigma,
                                    scale variance (scale_sd_rel^2)
     out      float64 (b - a, W)    written, per frame: p (3), R (9), P[:6, :6] (36), nll; with keep also the
                                    prior p (3), R (9), P (D*D), the F into the frame (D*D, zero for a frame not
                                    predicted), the posterior P (D*D), the prior and posterior scale (n_scale each)
   Frames a .. b-1; frame a is predicted (from step a - 1) when predict_first. All C-contiguous. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "../_rodrigues.h"

#define MAXD 7

/* C (n x q) = A (n x k) B (k x q), row-major; C must not alias A or B */
static void matmul(const double *A, const double *B, double *C, int n, int k, int q) {
    for (int i = 0; i < n; i++)
        for (int j = 0; j < q; j++) {
            double s = 0.0;
            for (int l = 0; l < k; l++)
                s += A[i * k + l] * B[l * q + j];
            C[i * q + j] = s;
        }
}

typedef struct {
    double *p, *R, *P, *s, *nll, *streak, *n_rej, *n_upd;
    int D, ns;
} State;

/* ErrorStateEkf.predict into frame k; F (D x D) written */
static void predict(State *st, const double *step, double scale_var, double *F) {
    int D = st->D;
    const double *ts = step, *Rs = step + 3;
    double sig_t = step[12], sig_r = step[13], rho = step[14];
    double tsc[3] = {ts[0], ts[1], ts[2]};
    if (st->ns)
        for (int i = 0; i < 3; i++)
            tsc[i] = ts[i] * (1.0 + st->s[0]);
    double *R = st->R;
    memset(F, 0, sizeof(double) * D * D);
    for (int i = 0; i < D; i++)
        F[i * D + i] = 1.0;
    /* F[:3, 3:6] = -R [tsc]x */
    double K[9] = {0.0, -tsc[2], tsc[1], tsc[2], 0.0, -tsc[0], -tsc[1], tsc[0], 0.0}, M[9];
    matmul(R, K, M, 3, 3, 3);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            F[i * D + 3 + j] = -M[i * 3 + j];
            F[(3 + i) * D + 3 + j] = Rs[j * 3 + i];
        }
    double Q[MAXD] = {sig_t * sig_t, sig_t * sig_t, sig_t * sig_t, sig_r * sig_r, sig_r * sig_r, sig_r * sig_r, 0.0};
    if (st->ns) {
        F[6 * D + 6] = rho;
        Q[6] = (1.0 - rho * rho) * scale_var;
        for (int i = 0; i < 3; i++)
            F[i * D + 6] = R[i * 3] * ts[0] + R[i * 3 + 1] * ts[1] + R[i * 3 + 2] * ts[2];
        st->s[0] *= rho;
    }
    for (int i = 0; i < 3; i++)
        st->p[i] += R[i * 3] * tsc[0] + R[i * 3 + 1] * tsc[1] + R[i * 3 + 2] * tsc[2];
    double Rn[9], FP[MAXD * MAXD];
    matmul(R, Rs, Rn, 3, 3, 3);
    memcpy(R, Rn, sizeof Rn);
    matmul(F, st->P, FP, D, D, D);
    for (int i = 0; i < D; i++)
        for (int j = 0; j < D; j++) {
            double s = 0.0;
            for (int l = 0; l < D; l++)
                s += FP[i * D + l] * F[j * D + l];
            st->P[i * D + j] = s + (i == j ? Q[i] : 0.0);
        }
}

/* ErrorStateEkf.update with frame k's readings r (m,) in the information form (no bias states) */
static void update(State *st, const double *r, const double *sens, const double *nrm, Py_ssize_t m,
                   const double *prm, double *work) {
    int D = st->D;
    double pt = prm[0], d0 = prm[1], near_depth = prm[2];
    double max_rej = prm[9], zg2 = prm[10] * prm[10], grss = prm[11], gth = prm[12];
    double *H = work, *y = work + 3 * m, *s2 = work + 4 * m, *z2 = work + 5 * m;
    double *P = st->P, *p = st->p;
    Py_ssize_t mok = 0;
    for (Py_ssize_t j = 0; j < m; j++) {
        if (!isfinite(r[j]))
            continue;
        const double *sj = sens + 3 * j, *nj = nrm + 3 * j;
        double dx = sj[0] - p[0], dy = sj[1] - p[1], dz = sj[2] - p[2];
        double dd = dx * dx + dy * dy + dz * dz, d = sqrt(dd);
        double depth = dx * nj[0] + dy * nj[1] + dz * nj[2];
        if (depth < 0.0)  /* NaN stays NaN, as with np.maximum: then the deep model */
            depth = 0.0;
        const double *pl = depth < near_depth ? prm + 3 : prm + 6;
        double c = 10.0 * pl[1] / log(10.0);
        H[3 * mok] = c * dx / dd;
        H[3 * mok + 1] = c * dy / dd;
        H[3 * mok + 2] = c * dz / dd;
        y[mok] = r[j] - (pt - pl[0] - 10.0 * pl[1] * log10((d < 1e-4 ? 1e-4 : d) / d0));
        s2[mok] = pl[2] * pl[2];
        mok++;
    }
    if (mok < 1)
        return;
    double sum = 0.0;
    Py_ssize_t nkeep = 0;
    for (Py_ssize_t j = 0; j < mok; j++) {
        const double *h = H + 3 * j;
        double dS = s2[j];
        for (int a = 0; a < 3; a++) {
            double u = 0.0;
            for (int b = 0; b < 3; b++)
                u += h[b] * P[b * D + a];
            dS += u * h[a];
        }
        z2[j] = y[j] * y[j] / dS;
        sum += (z2[j] > zg2 ? zg2 : z2[j]) + log(dS);  /* NaN stays NaN, as with np.minimum */
        nkeep += z2[j] < zg2;
    }
    *st->nll += 0.5 * sum;
    *st->n_rej += (double)(mok - nkeep);
    int bad = (double)nkeep / (double)mok < 0.5;
    *st->streak = bad ? *st->streak + 1.0 : 0.0;
    int guard = bad && *st->streak >= max_rej;
    if (guard) {
        for (int i = 0; i < 3; i++) {
            P[i * D + i] += grss * grss;
            P[(3 + i) * D + 3 + i] += gth * gth;
        }
        *st->streak = 0.0;
        nkeep = mok;
    }
    if (nkeep < 1)
        return;  /* no reading passes the gate: the state stays, the counters above count it */
    double A[9] = {0}, g[3] = {0};
    for (Py_ssize_t j = 0; j < mok; j++) {
        if (!guard && !(z2[j] < zg2))
            continue;
        const double *h = H + 3 * j;
        double w = 1.0 / s2[j];
        for (int a = 0; a < 3; a++) {
            g[a] += h[a] * w * y[j];
            for (int b = 0; b < 3; b++)
                A[a * 3 + b] += h[a] * w * h[b];
        }
    }
    /* P' = P - PJ A (I + PJJ A)^-1 PJ^T, PJ = P[:, :3]: X = (I + PJJ A)^-1 P[:3, :] by Gaussian elimination */
    double M[9], X[3 * MAXD];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) {
            double s = a == b ? 1.0 : 0.0;
            for (int l = 0; l < 3; l++)
                s += P[a * D + l] * A[l * 3 + b];
            M[a * 3 + b] = s;
        }
    for (int a = 0; a < 3; a++)
        for (int j = 0; j < D; j++)
            X[a * D + j] = P[a * D + j];
    for (int c = 0; c < 3; c++) {  /* partial pivoting */
        int piv = c;
        for (int a = c + 1; a < 3; a++)
            if (fabs(M[a * 3 + c]) > fabs(M[piv * 3 + c]))
                piv = a;
        if (piv != c) {
            for (int b = 0; b < 3; b++) {
                double t = M[c * 3 + b]; M[c * 3 + b] = M[piv * 3 + b]; M[piv * 3 + b] = t;
            }
            for (int j = 0; j < D; j++) {
                double t = X[c * D + j]; X[c * D + j] = X[piv * D + j]; X[piv * D + j] = t;
            }
        }
        for (int a = c + 1; a < 3; a++) {
            double f = M[a * 3 + c] / M[c * 3 + c];
            for (int b = c; b < 3; b++)
                M[a * 3 + b] -= f * M[c * 3 + b];
            for (int j = 0; j < D; j++)
                X[a * D + j] -= f * X[c * D + j];
        }
    }
    for (int c = 2; c >= 0; c--) {
        for (int j = 0; j < D; j++) {
            double s = X[c * D + j];
            for (int b = c + 1; b < 3; b++)
                s -= M[c * 3 + b] * X[b * D + j];
            X[c * D + j] = s / M[c * 3 + c];
        }
    }
    double AX[3 * MAXD], Pn[MAXD * MAXD], dxs[MAXD];
    matmul(A, X, AX, 3, 3, D);
    for (int i = 0; i < D; i++)
        for (int j = 0; j < D; j++) {
            double s = 0.0;
            for (int l = 0; l < 3; l++)
                s += P[i * D + l] * AX[l * D + j];
            Pn[i * D + j] = P[i * D + j] - s;
        }
    for (int i = 0; i < D; i++)
        for (int j = i + 1; j < D; j++)
            Pn[i * D + j] = Pn[j * D + i] = 0.5 * (Pn[i * D + j] + Pn[j * D + i]);
    for (int i = 0; i < D; i++)
        dxs[i] = Pn[i * D] * g[0] + Pn[i * D + 1] * g[1] + Pn[i * D + 2] * g[2];
    double dR[9], Rn[9];
    rodrigues(dxs + 3, dR);
    matmul(st->R, dR, Rn, 3, 3, 3);
    memcpy(st->R, Rn, sizeof Rn);
    for (int i = 0; i < 3; i++)
        p[i] += dxs[i];
    if (st->ns)
        st->s[0] += dxs[6];
    memcpy(P, Pn, sizeof(double) * D * D);
    *st->n_upd += 1.0;
}

static PyObject *run(PyObject *self, PyObject *args) {
    Py_buffer sb, stb, rb, seb, nb, pb, ob;
    Py_ssize_t a, b;
    int predict_first, ns, keep;
    if (!PyArg_ParseTuple(args, "w*y*y*y*y*y*w*nniii", &sb, &stb, &rb, &seb, &nb, &pb, &ob, &a, &b, &predict_first,
                          &ns, &keep))
        return NULL;
    PyObject *ret = NULL;
    double *work = NULL;
    int D = 6 + ns;
    Py_ssize_t m = seb.len / (Py_ssize_t)(3 * sizeof(double));
    Py_ssize_t n = m ? rb.len / (Py_ssize_t)(m * sizeof(double)) : 0;
    Py_ssize_t W = 49 + (keep ? 12 + 3 * D * D + 2 * ns : 0);
    Py_ssize_t S = (Py_ssize_t)sizeof(double);
    if (ns < 0 || ns > 1 || m < 1 || sb.len != (12 + D * D + ns + 4) * S || seb.len != m * 3 * S || nb.len != seb.len
        || rb.len != n * m * S || stb.len != (n > 0 ? n - 1 : 0) * 15 * S || pb.len != 14 * S || a < 0 || b > n
        || b < a || (predict_first && a < 1) || ob.len != (b - a) * W * S) {
        PyErr_SetString(PyExc_ValueError, "run: state, steps (n - 1, 15), rss (n, m), sensors and normals (m, 3), "
                                          "params (14,) and out (b - a, W) float64 arrays of matching sizes");
        goto done;
    }
    work = PyMem_Malloc(sizeof(double) * 6 * (size_t)m);
    if (!work) {
        PyErr_NoMemory();
        goto done;
    }
    {
        double *sv = (double *)sb.buf;
        State st = {sv, sv + 3, sv + 12, sv + 12 + D * D, sv + 12 + D * D + ns, sv + 13 + D * D + ns,
                    sv + 14 + D * D + ns, sv + 15 + D * D + ns, D, ns};
        const double *steps = (const double *)stb.buf, *rss = (const double *)rb.buf, *prm = (const double *)pb.buf;
        const double *sens = (const double *)seb.buf, *nrm = (const double *)nb.buf;
        double *out = (double *)ob.buf;
        double F[MAXD * MAXD];
        for (Py_ssize_t k = a; k < b; k++) {
            double *o = out + (k - a) * W;
            memset(F, 0, sizeof F);
            if (k > a || predict_first)
                predict(&st, steps + 15 * (k - 1), prm[13], F);
            if (keep) {
                double *q = o + 49;
                memcpy(q, st.p, 3 * S);
                memcpy(q + 3, st.R, 9 * S);
                memcpy(q + 12, st.P, D * D * S);
                for (int i = 0; i < D * D; i++)
                    q[12 + D * D + i] = F[(i / D) * D + i % D];
                if (ns)
                    q[12 + 3 * D * D] = st.s[0];
            }
            update(&st, rss + m * k, sens, nrm, m, prm, work);
            memcpy(o, st.p, 3 * S);
            memcpy(o + 3, st.R, 9 * S);
            for (int i = 0; i < 6; i++)
                for (int j = 0; j < 6; j++)
                    o[12 + i * 6 + j] = st.P[i * D + j];
            o[48] = *st.nll;
            if (keep) {
                double *q = o + 49;
                memcpy(q + 12 + 2 * D * D, st.P, D * D * S);
                if (ns)
                    q[12 + 3 * D * D + 1] = st.s[0];
            }
        }
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    PyMem_Free(work);
    PyBuffer_Release(&sb);
    PyBuffer_Release(&stb);
    PyBuffer_Release(&rb);
    PyBuffer_Release(&seb);
    PyBuffer_Release(&nb);
    PyBuffer_Release(&pb);
    PyBuffer_Release(&ob);
    return ret;
}

static PyMethodDef methods[] = {
    {"run", run, METH_VARARGS, "The raw-RSS EKF's frames a .. b-1 for one candidate (module comment)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ekf_rss", NULL, -1, methods};

PyMODINIT_FUNC PyInit__ekf_rss(void) { return PyModule_Create(&module); }
