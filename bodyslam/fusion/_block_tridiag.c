/* The marginal covariances of a block-tridiagonal information matrix (bodyslam.fusion.refine.marginal_covariances),
   compiled.

   The whole-exam solve states each pose's covariance: the diagonal 6x6 blocks of H^-1 for H with diagonal blocks
   D_k and blocks O_k at (k, k+1). numpy ran its two passes as ~10 small-array calls a frame (0.4 s of a
   10,000-frame exam's end); this is the same arithmetic written out: a forward pass of Schur complements
   S_k = D_k - O_{k-1}^T S_{k-1}^-1 O_{k-1}, each symmetrised and inverted through its Cholesky factor
   (S^-1 = L^-T L^-1; not positive definite -> the call returns False), then C_k = S_k^-1 + G_k C_{k+1} G_k^T with
   G_k = S_k^-1 O_k. Equal to the numpy version to ~1e-15 relative (sums in another order;
   tests/bodyslam/fusion/test_refine.py compares them).

   marginals(D, O, Sinv, C) -> bool
     D     float64 (n, 6, 6)       read
     O     float64 (n - 1, 6, 6)   read
     Sinv  float64 (n, 6, 6)       written (work: the forward pass's inverses)
     C     float64 (n, 6, 6)       written: the marginal covariances

   readings_share(O, Sinv, C, W, M) (session 65; bodyslam.fusion.refine.sandwich_share): the diagonal blocks of
   H^-1 W H^-1 for a block-diagonal W, from a marginals() call's Sinv and C. The cross blocks of H^-1 are
   C_(k,j) = A_k ... A_(j-1) C_j (j > k) with A_k = -Sinv_k O_k, so M_k = C_k U_k C_k + B_k, with a forward pass
   U_0 = 0, U_k = A_(k-1)^T (W_(k-1) + U_(k-1)) A_(k-1) (the frames before k) and a backward pass
   B_(n-1) = C W C, B_k = C_k W_k C_k + A_k B_(k+1) A_k^T (frame k and those after it).
     O, Sinv, C  as above, read
     W     float64 (n, 6, 6)       read
     M     float64 (n, 6, 6)       written
   All C-contiguous. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#define B 6

/* inv(S) of a symmetric positive-definite S (its symmetric part) through L L^T; 0 if not positive definite */
static int spd_inverse(const double *S, double *out) {
    double A[B * B], L[B * B] = {0}, Li[B * B] = {0};
    for (int i = 0; i < B; i++)
        for (int j = 0; j < B; j++)
            A[i * B + j] = 0.5 * (S[i * B + j] + S[j * B + i]);
    for (int j = 0; j < B; j++) {
        double d = A[j * B + j];
        for (int k = 0; k < j; k++)
            d -= L[j * B + k] * L[j * B + k];
        if (!(d > 0.0))
            return 0;
        double ljj = sqrt(d);
        L[j * B + j] = ljj;
        for (int i = j + 1; i < B; i++) {
            double s = A[i * B + j];
            for (int k = 0; k < j; k++)
                s -= L[i * B + k] * L[j * B + k];
            L[i * B + j] = s / ljj;
        }
    }
    for (int j = 0; j < B; j++) {  /* Li = L^-1, lower triangular: forward substitution per column */
        Li[j * B + j] = 1.0 / L[j * B + j];
        for (int i = j + 1; i < B; i++) {
            double s = 0.0;
            for (int k = j; k < i; k++)
                s -= L[i * B + k] * Li[k * B + j];
            Li[i * B + j] = s / L[i * B + i];
        }
    }
    for (int i = 0; i < B; i++)  /* S^-1 = Li^T Li */
        for (int j = 0; j < B; j++) {
            double s = 0.0;
            for (int k = 0; k < B; k++)
                s += Li[k * B + i] * Li[k * B + j];
            out[i * B + j] = s;
        }
    return 1;
}

static void mm(const double *X, const double *Y, double *Z, int tx, int ty) {  /* Z = op(X) op(Y), 6x6 */
    for (int i = 0; i < B; i++)
        for (int j = 0; j < B; j++) {
            double s = 0.0;
            for (int k = 0; k < B; k++)
                s += (tx ? X[k * B + i] : X[i * B + k]) * (ty ? Y[j * B + k] : Y[k * B + j]);
            Z[i * B + j] = s;
        }
}

static PyObject *marginals(PyObject *self, PyObject *args) {
    Py_buffer db, ob, sb, cb;
    if (!PyArg_ParseTuple(args, "y*y*w*w*", &db, &ob, &sb, &cb))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t blk = B * B * (Py_ssize_t)sizeof(double), n = db.len / blk;
    if (n < 1 || db.len != n * blk || ob.len != (n - 1) * blk || sb.len != db.len || cb.len != db.len) {
        PyErr_SetString(PyExc_ValueError, "marginals: D, Sinv and C (n, 6, 6), O (n - 1, 6, 6) float64 arrays");
        goto done;
    }
    {
        const double *D = (const double *)db.buf, *O = (const double *)ob.buf;
        double *Sinv = (double *)sb.buf, *C = (double *)cb.buf;
        int ok = 1;
        Py_BEGIN_ALLOW_THREADS
        double S[B * B], T[B * B], G[B * B];
        for (Py_ssize_t k = 0; k < n && ok; k++) {
            const double *Dk = D + k * B * B;
            if (k) {  /* S = D_k - O^T Sinv_{k-1} O */
                mm(O + (k - 1) * B * B, Sinv + (k - 1) * B * B, T, 1, 0);
                mm(T, O + (k - 1) * B * B, S, 0, 0);
                for (int i = 0; i < B * B; i++)
                    S[i] = Dk[i] - S[i];
            } else {
                for (int i = 0; i < B * B; i++)
                    S[i] = Dk[i];
            }
            ok = spd_inverse(S, Sinv + k * B * B);
        }
        if (ok) {
            for (int i = 0; i < B * B; i++)
                C[(n - 1) * B * B + i] = Sinv[(n - 1) * B * B + i];
            for (Py_ssize_t k = n - 2; k >= 0; k--) {  /* C_k = Sinv_k + G C_{k+1} G^T, G = Sinv_k O_k */
                mm(Sinv + k * B * B, O + k * B * B, G, 0, 0);
                mm(G, C + (k + 1) * B * B, T, 0, 0);
                mm(T, G, S, 0, 1);
                for (int i = 0; i < B * B; i++)
                    C[k * B * B + i] = Sinv[k * B * B + i] + S[i];
            }
        }
        Py_END_ALLOW_THREADS
        ret = PyBool_FromLong(ok);
    }
done:
    PyBuffer_Release(&db);
    PyBuffer_Release(&ob);
    PyBuffer_Release(&sb);
    PyBuffer_Release(&cb);
    return ret;
}

static PyObject *readings_share(PyObject *self, PyObject *args) {
    Py_buffer ob, sb, cb, wb, mb;
    if (!PyArg_ParseTuple(args, "y*y*y*y*w*", &ob, &sb, &cb, &wb, &mb))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t blk = B * B * (Py_ssize_t)sizeof(double), n = sb.len / blk;
    if (n < 1 || sb.len != n * blk || ob.len != (n - 1) * blk || cb.len != sb.len || wb.len != sb.len ||
        mb.len != sb.len) {
        PyErr_SetString(PyExc_ValueError, "readings_share: Sinv, C, W and M (n, 6, 6), O (n - 1, 6, 6) float64 arrays");
        goto done;
    }
    {
        const double *O = (const double *)ob.buf, *Sinv = (const double *)sb.buf, *C = (const double *)cb.buf;
        const double *W = (const double *)wb.buf;
        double *M = (double *)mb.buf;
        Py_BEGIN_ALLOW_THREADS
        double A[B * B], U[B * B] = {0}, T[B * B], V[B * B], Bk[B * B];
        for (Py_ssize_t k = 0; k < n; k++) {  /* forward: M_k = C_k U_k C_k */
            if (k) {  /* U_k = A^T (W_(k-1) + U_(k-1)) A, A = -Sinv_(k-1) O_(k-1) (the sign cancels) */
                mm(Sinv + (k - 1) * B * B, O + (k - 1) * B * B, A, 0, 0);
                for (int i = 0; i < B * B; i++)
                    V[i] = W[(k - 1) * B * B + i] + U[i];
                mm(A, V, T, 1, 0);
                mm(T, A, U, 0, 0);
            }
            mm(C + k * B * B, U, T, 0, 0);
            mm(T, C + k * B * B, M + k * B * B, 0, 0);
        }
        for (Py_ssize_t k = n - 1; k >= 0; k--) {  /* backward: B_k = C_k W_k C_k + A_k B_(k+1) A_k^T; M_k += B_k */
            mm(C + k * B * B, W + k * B * B, T, 0, 0);
            mm(T, C + k * B * B, V, 0, 0);
            if (k < n - 1) {
                mm(Sinv + k * B * B, O + k * B * B, A, 0, 0);
                mm(A, Bk, T, 0, 0);
                mm(T, A, U, 0, 1);
                for (int i = 0; i < B * B; i++)
                    V[i] += U[i];
            }
            for (int i = 0; i < B * B; i++) {
                Bk[i] = V[i];
                M[k * B * B + i] += V[i];
            }
        }
        Py_END_ALLOW_THREADS
        ret = Py_NewRef(Py_None);
    }
done:
    PyBuffer_Release(&ob);
    PyBuffer_Release(&sb);
    PyBuffer_Release(&cb);
    PyBuffer_Release(&wb);
    PyBuffer_Release(&mb);
    return ret;
}

static PyMethodDef methods[] = {
    {"marginals", marginals, METH_VARARGS, "Marginal covariances of a block-tridiagonal information matrix."},
    {"readings_share", readings_share, METH_VARARGS, "Diagonal blocks of H^-1 W H^-1 for a block-diagonal W."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_block_tridiag", NULL, -1, methods};

PyMODINIT_FUNC PyInit__block_tridiag(void) { return PyModule_Create(&module); }
