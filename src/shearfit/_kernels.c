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

/* table rows are [value_f, slope_f, value_g, slope_g] in float32 */
static inline double lookup(const float *tab, int which, double u, double nmax)
{
    if (u >= nmax) return 0.0;
    long i = (long)u;
    double f = u - (double)i;
    const float *row = tab + 4 * i + 2 * which;
    return (double)row[0] + f * (double)row[1];
}

typedef struct { double lf[6], lg[6]; } Acc;

/* disk and bulge transforms of one mode for the model with quadratic-form coefficients a0..a2 */
static inline void eval_mode(const double *p, double a0, double a1, double a2, double c, double c2,
                             double inv_du, double ratio2, int same, const float *T, double nmax,
                             double *rf, double *rg)
{
    double rho2 = a0 * p[0] + a1 * p[1] + a2 * p[2];
    rho2 = rho2 < 0 ? 0 : rho2;
    double u = (sqrt(c2 + rho2) - c) * inv_du;
    *rf = lookup(T, 0, u, nmax);
    *rg = same ? lookup(T, 1, u, nmax) : lookup(T, 1, (sqrt(c2 + rho2 * ratio2) - c) * inv_du, nmax);
}

/* the six linear sums (cross-correlation, its gradient and Hessian) of both components */
static inline void accumulate(Acc *acc, const double *p, double rf, double rg)
{
    for (int t = 0; t < 6; t++) {
        acc->lf[t] += rf * p[3 + t];
        acc->lg[t] += rg * p[3 + t];
    }
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
    const double c2 = c * c;
    const int same = (ratio2 == 1.0);

    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t m = 0; m < n_models; m++) {
        const double a0 = C[3 * m], a1 = C[3 * m + 1], a2 = C[3 * m + 2];
        Acc acc = {0};
        double ff = 0, gg = 0, fg = 0;
        double mfr = 0, mfi = 0, mgr = 0, mgi = 0;
        const double *p = M;
        Py_ssize_t j = 0;
        double rf, rg;
        for (; j < n_single; j++, p += NSTRIDE) {
            eval_mode(p, a0, a1, a2, c, c2, inv_du, ratio2, same, T, nmax, &rf, &rg);
            accumulate(&acc, p, rf, rg);
            double qf = p[9] * rf;
            ff += qf * rf;
            fg += qf * rg;
            gg += p[9] * rg * rg;
        }
        for (; j < n_modes; j++, p += NSTRIDE) {
            eval_mode(p, a0, a1, a2, c, c2, inv_du, ratio2, same, T, nmax, &rf, &rg);
            accumulate(&acc, p, rf, rg);
            mfr += p[9] * rf; mfi += p[10] * rf;
            mgr += p[9] * rg; mgi += p[10] * rg;
            if (p[11] != 0.0) {
                ff += mfr * mfr + mfi * mfi;
                gg += mgr * mgr + mgi * mgi;
                fg += mfr * mgr + mfi * mgi;
                mfr = mfi = mgr = mgi = 0.0;
            }
        }
        double *o = O + NOUT * m;
        for (int t = 0; t < 6; t++) { o[t] = acc.lf[t]; o[6 + t] = acc.lg[t]; }
        o[12] = ff; o[13] = gg; o[14] = fg;
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
