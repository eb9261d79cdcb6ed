/*
 * Inner loop of the likelihood: pixel sums of a batch of galaxy models.
 *
 * For each model m (coefficients of the quadratic form K^T C K times r^2)
 * and each Fourier mode j it evaluates the disk and bulge transforms from a
 * table uniform in u = sqrt(c^2 + rho^2) - c (see profiles.FastRadial), and
 * accumulates, without temporaries:
 *   L_f[t] = sum_j R_f(j) lin[t](j), L_g[t] likewise   (t = 0..5)
 *   ff = sum_j q(j) R_f^2, gg = sum_j q(j) R_g^2, fg = sum_j q(j) R_f R_g
 * This is the same arithmetic as likelihood.model_sums' numpy path, which
 * stays as the reference and the fallback; a test checks they agree.
 *
 * and the Parseval sums through the fold onto the sampled grid: modes that
 * fold onto the same sampled mode are contiguous, each carries its complex
 * transfer T (scaled by sqrt(w / (N sigma^2))) and a flag marking the last
 * of its group; per group M = sum T R, and ff += |M_f|^2, fg += Re(M_f M_g*).
 * Modes are passed interleaved, 12 doubles each:
 *   [kx^2, 2 kx ky, ky^2, lin0..lin5, Re T, Im T, last-of-group]
 * The first n_single modes are alone on their sampled mode: for them
 * |M|^2 = |T|^2 R^2, so they carry q = |T|^2 in place of Re T and the loop
 * over them has no branch.
 * Only the buffer protocol is used, so no numpy headers are needed to build.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#define NSTRIDE 12
#define NOUT 15

/* table rows are [value_f, slope_f, value_g, slope_g] in float32; the last row is zero */
/* Models are processed NB at a time: each mode's data is loaded once for the block, and the
 * per-model arithmetic (independent across the block) vectorises. On x86-64 Linux with GCC the
 * block loop is compiled for several instruction sets and the best one the CPU has is chosen at
 * run time (target_clones), so the build stays portable. */
#define NB 4
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define MULTIVERSION __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define MULTIVERSION
#endif

typedef double vnb __attribute__((vector_size(NB * sizeof(double))));

/* transforms of the NB models at one mode: u clamped to the last table row, which is zero */
static inline __attribute__((always_inline)) void eval_block(
    const double *p, const vnb *a, double c, double c2, double inv_du, double ratio2, int same,
    const float *T, double nmax, vnb *rf, vnb *rg)
{
    /* rho2 >= 0 up to rounding, far below c2 */
    vnb rho2 = a[0] * p[0] + a[1] * p[1] + a[2] * p[2];
    vnb s, sg, u, ug;
    for (int k = 0; k < NB; k++) s[k] = sqrt(c2 + rho2[k]);
    u = (s - c) * inv_du;
    if (same) {
        ug = u;
    } else {
        for (int k = 0; k < NB; k++) sg[k] = sqrt(c2 + rho2[k] * ratio2);
        ug = (sg - c) * inv_du;
    }
    vnb vf, sf, vg, slg, fi, fig;
    for (int k = 0; k < NB; k++) {
        double uk = u[k] < nmax ? u[k] : nmax, ugk = ug[k] < nmax ? ug[k] : nmax;
        long i = (long)uk, ig = (long)ugk;
        const float *row = T + 4 * i, *rowg = T + 4 * ig;
        vf[k] = row[0]; sf[k] = row[1]; vg[k] = rowg[2]; slg[k] = rowg[3];
        fi[k] = uk - (double)i; fig[k] = ugk - (double)ig;
    }
    *rf = vf + fi * sf;
    *rg = vg + fig * slg;
}

static inline __attribute__((always_inline)) void block_body(
    const double *a0p, const double *a1p, const double *a2p, const double *M, Py_ssize_t n_single,
    Py_ssize_t n_modes, const float *T, double nmax, double c, double inv_du, double ratio2, int same,
    double *o)
{
    vnb a[3];
    for (int k = 0; k < NB; k++) { a[0][k] = a0p[k]; a[1][k] = a1p[k]; a[2][k] = a2p[k]; }
    const vnb zero = {0};
    vnb lf[6], lg[6];
    for (int t = 0; t < 6; t++) lf[t] = lg[t] = zero;
    vnb ff = zero, gg = zero, fg = zero, mfr = zero, mfi = zero, mgr = zero, mgi = zero;
    const double c2 = c * c;
    const double *p = M;
    Py_ssize_t j = 0;
    for (; j < n_single; j++, p += NSTRIDE) {
        vnb rf, rg;
        eval_block(p, a, c, c2, inv_du, ratio2, same, T, nmax, &rf, &rg);
        for (int t = 0; t < 6; t++) { lf[t] += rf * p[3 + t]; lg[t] += rg * p[3 + t]; }
        vnb qf = rf * p[9];
        ff += qf * rf;
        fg += qf * rg;
        gg += rg * rg * p[9];
    }
    for (; j < n_modes; j++, p += NSTRIDE) {
        vnb rf, rg;
        eval_block(p, a, c, c2, inv_du, ratio2, same, T, nmax, &rf, &rg);
        for (int t = 0; t < 6; t++) { lf[t] += rf * p[3 + t]; lg[t] += rg * p[3 + t]; }
        mfr += rf * p[9]; mfi += rf * p[10];
        mgr += rg * p[9]; mgi += rg * p[10];
        if (p[11] != 0.0) {
            ff += mfr * mfr + mfi * mfi;
            gg += mgr * mgr + mgi * mgi;
            fg += mfr * mgr + mfi * mgi;
            mfr = mfi = mgr = mgi = zero;
        }
    }
    for (int k = 0; k < NB; k++) {
        double *ok = o + NOUT * k;
        for (int t = 0; t < 6; t++) { ok[t] = lf[t][k]; ok[6 + t] = lg[t][k]; }
        ok[12] = ff[k]; ok[13] = gg[k]; ok[14] = fg[k];
    }
}

MULTIVERSION
static void block_sums(const double *a0, const double *a1, const double *a2, const double *M,
                       Py_ssize_t n_single, Py_ssize_t n_modes, const float *T, double nmax, double c,
                       double inv_du, double ratio2, int same, double *o)
{
    /* two copies of the loop, so that the common case (bulge and disk on one table row) has no branch */
    if (same)
        block_body(a0, a1, a2, M, n_single, n_modes, T, nmax, c, inv_du, ratio2, 1, o);
    else
        block_body(a0, a1, a2, M, n_single, n_modes, T, nmax, c, inv_du, ratio2, 0, o);
}

static PyObject *model_sums(PyObject *self, PyObject *args)
{
    Py_buffer coef, modes, tab, out;
    double c, inv_du, ratio2;
    Py_ssize_t n_single;
    if (!PyArg_ParseTuple(args, "y*y*y*dddnw*", &coef, &modes, &tab, &c, &inv_du, &ratio2, &n_single, &out))
        return NULL;
    Py_ssize_t n_models = coef.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_modes = modes.len / (NSTRIDE * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_tab = tab.len / (4 * (Py_ssize_t)sizeof(float));
    if (out.len < n_models * NOUT * (Py_ssize_t)sizeof(double) || n_single > n_modes) {
        PyBuffer_Release(&coef); PyBuffer_Release(&modes); PyBuffer_Release(&tab); PyBuffer_Release(&out);
        PyErr_SetString(PyExc_ValueError, "model_sums: inconsistent buffer sizes");
        return NULL;
    }
    const double *C = (const double *)coef.buf;
    const double *M = (const double *)modes.buf;
    const float *T = (const float *)tab.buf;
    double *O = (double *)out.buf;
    const double nmax = (double)(n_tab - 1);
    const int same = (ratio2 == 1.0);

    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t m0 = 0; m0 < n_models; m0 += NB) {
        double a0[NB], a1[NB], a2[NB], ob[NB * NOUT];
        for (int k = 0; k < NB; k++) {
            /* a short last block repeats its last model; the copies are not written out */
            Py_ssize_t m = m0 + k < n_models ? m0 + k : n_models - 1;
            a0[k] = C[3 * m]; a1[k] = C[3 * m + 1]; a2[k] = C[3 * m + 2];
        }
        block_sums(a0, a1, a2, M, n_single, n_modes, T, nmax, c, inv_du, ratio2, same, ob);
        for (int k = 0; k < NB && m0 + k < n_models; k++)
            for (int t = 0; t < NOUT; t++) O[NOUT * (m0 + k) + t] = ob[NOUT * k + t];
    }
    Py_END_ALLOW_THREADS

    PyBuffer_Release(&coef); PyBuffer_Release(&modes); PyBuffer_Release(&tab); PyBuffer_Release(&out);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"model_sums", model_sums, METH_VARARGS,
     "model_sums(coef, modes, table, c, inv_du, ratio2, n_single, out)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "Compiled inner loop of the shearfit likelihood.", -1, methods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
