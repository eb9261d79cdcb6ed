/*
 * Inner loop of the likelihood: pixel sums of a batch of galaxy models.
 *
 * For each model m (coefficients of the quadratic form K^T C K times r^2)
 * and each Fourier mode j it evaluates the disk and bulge transforms from a
 * table uniform in u = sqrt(c^2 + rho^2) - c (see profiles.FastRadial), and
 * accumulates, without temporaries:
 *   L_f[t] = sum_j R_f(j) lin[t](j), L_g[t] likewise   (t = 0..5)
 *   ff = sum_j q(j) R_f^2, gg = sum_j q(j) R_g^2, fg = sum_j q(j) R_f R_g
 * for the modes in no fold group (q = the exposures' summed w |T|^2 / (N sigma^2)),
 * and for the fold groups (modes above Nyquist folding onto sampled modes,
 * merged over the exposures that share them, likelihood.JointModes) the
 * quadratic form R^T Re(H) R of each group, as sum_j (u_j . R)^2 over the
 * factors u_j of its block of Re H (as many as the block's rank).
 * This is the same arithmetic as likelihood.model_sums' numpy path, which
 * stays as the reference and the fallback; a test checks they agree.
 *
 * Modes are passed interleaved, 12 doubles each:
 *   [kx^2, 2 kx ky, ky^2, lin0..lin5, q, 0, 0]
 * the n_single modes in no group first (their loop has no branch), then the
 * groups' modes group after group, with each group's size, rank and factors
 * in three more buffers.
 * Only the buffer protocol is used, so no numpy headers are needed to build.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdint.h>
#include <limits.h>

#define NSTRIDE 12
#define NOUT 15

/* table rows are [value_f, slope_f, value_g, slope_g] in float32; the last row is zero */
/* Models are processed NB at a time: each mode's data is loaded once for the block, and the
 * per-model arithmetic (independent across the block) vectorises. On x86-64 Linux with GCC the
 * block loop is compiled for several instruction sets and the best one the CPU has is chosen at
 * run time (target_clones), so the build stays portable. Eight models fill one AVX-512 register
 * (8 % faster per galaxy than four, benchmarks/speed.py). */
#define NB 8
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define MULTIVERSION __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define MULTIVERSION
#endif

/* glibc's vector exp and log (libmvec, linked with libm): simple loops over arrays of them vectorise,
 * 8 at a time with AVX-512. Only where they exist (glibc on x86-64 with GCC); elsewhere the loops stay
 * scalar. They are accurate to a few units in the last place, as the scalar ones to one. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && defined(__GLIBC__)
double exp(double) __attribute__((simd("notinbranch")));
double log(double) __attribute__((simd("notinbranch")));
#endif

/* out[i] = exp(x[i] - shift) and out[i] = log(x[i]), vectorised where the CPU allows */
MULTIVERSION
static void vexp_shift(const double *x, double shift, double *out, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) out[i] = exp(x[i] - shift);
}

MULTIVERSION
static void vlog(const double *x, double *out, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) out[i] = log(x[i]);
}

/* release the buffers of a call (a NULL-terminated list) */
static void release_buffers(Py_buffer **b)
{
    for (; *b != NULL; b++) PyBuffer_Release(*b);
}
#define RELEASE(...) release_buffers((Py_buffer *[]){__VA_ARGS__, NULL})

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
    Py_ssize_t n_groups, const long long *gsz, const long long *grank, const double *fac, vnb *scratch,
    const float *T, double nmax, double c, double inv_du, double ratio2, int same, double *o)
{
    vnb a[3];
    for (int k = 0; k < NB; k++) { a[0][k] = a0p[k]; a[1][k] = a1p[k]; a[2][k] = a2p[k]; }
    const vnb zero = {0};
    vnb lf[6], lg[6];
    for (int t = 0; t < 6; t++) lf[t] = lg[t] = zero;
    vnb ff = zero, gg = zero, fg = zero;
    const double c2 = c * c;
    const double *p = M;
    for (Py_ssize_t j = 0; j < n_single; j++, p += NSTRIDE) {
        vnb rf, rg;
        eval_block(p, a, c, c2, inv_du, ratio2, same, T, nmax, &rf, &rg);
        for (int t = 0; t < 6; t++) { lf[t] += rf * p[3 + t]; lg[t] += rg * p[3 + t]; }
        vnb qf = rf * p[9];
        ff += qf * rf;
        fg += qf * rg;
        gg += rg * rg * p[9];
    }
    /* the fold groups: the transforms at the group's modes, then R^T Re(H) R = sum_j (u_j . R)^2 from the
       factors u_j of Re(H) (its eigenvectors times the root of their eigenvalues, as many as its rank) */
    const double *u = fac;
    for (Py_ssize_t g = 0; g < n_groups; g++) {
        const Py_ssize_t np_ = (Py_ssize_t)gsz[g], nr = (Py_ssize_t)grank[g];
        vnb *rfs = scratch, *rgs = scratch + np_;
        for (Py_ssize_t n = 0; n < np_; n++, p += NSTRIDE) {
            eval_block(p, a, c, c2, inv_du, ratio2, same, T, nmax, rfs + n, rgs + n);
            for (int t = 0; t < 6; t++) { lf[t] += rfs[n] * p[3 + t]; lg[t] += rgs[n] * p[3 + t]; }
        }
        for (Py_ssize_t j = 0; j < nr; j++, u += np_) {
            vnb sf = zero, sg = zero;
            for (Py_ssize_t n = 0; n < np_; n++) { sf += rfs[n] * u[n]; sg += rgs[n] * u[n]; }
            ff += sf * sf;
            gg += sg * sg;
            fg += sf * sg;
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
                       Py_ssize_t n_single, Py_ssize_t n_groups, const long long *gsz, const long long *grank,
                       const double *fac, vnb *scratch, const float *T, double nmax, double c, double inv_du, double ratio2, int same,
                       double *o)
{
    /* two copies of the loop, so that the common case (bulge and disk on one table row) has no branch */
    if (same)
        block_body(a0, a1, a2, M, n_single, n_groups, gsz, grank, fac, scratch, T, nmax, c, inv_du, ratio2, 1, o);
    else
        block_body(a0, a1, a2, M, n_single, n_groups, gsz, grank, fac, scratch, T, nmax, c, inv_du, ratio2, 0, o);
}

/* checks the fold groups' buffers (sizes and ranks, int64; factors, float64) against the modes, of which the
   first n_single are in no group; returns the largest group (-1: inconsistent) */
static Py_ssize_t check_groups(const Py_buffer *gszb, const Py_buffer *grkb, const Py_buffer *facb,
                               Py_ssize_t n_single, Py_ssize_t n_modes)
{
    const long long *gsz = (const long long *)gszb->buf, *grank = (const long long *)grkb->buf;
    Py_ssize_t n_groups = gszb->len / (Py_ssize_t)sizeof(long long);
    if (n_single > n_modes || grkb->len != gszb->len) return -1;
    Py_ssize_t tot = 0, totf = 0, mx = 0;
    for (Py_ssize_t g = 0; g < n_groups; g++) {
        if (gsz[g] < 1 || grank[g] < 0 || grank[g] > gsz[g]) return -1;
        tot += (Py_ssize_t)gsz[g];
        totf += (Py_ssize_t)(gsz[g] * grank[g]);
        if (gsz[g] > mx) mx = (Py_ssize_t)gsz[g];
    }
    return (tot == n_modes - n_single && totf == facb->len / (Py_ssize_t)sizeof(double)) ? mx : -1;
}

static vnb *alloc_scratch(Py_ssize_t max_group)
{
    void *ptr = NULL;
    size_t n = (size_t)(2 * (max_group > 0 ? max_group : 1)) * sizeof(vnb);
    if (posix_memalign(&ptr, 64, n) != 0) return NULL;
    return (vnb *)ptr;
}

static PyObject *model_sums(PyObject *self, PyObject *args)
{
    Py_buffer coef, modes, tab, gszb, grkb, facb, out;
    double c, inv_du, ratio2;
    Py_ssize_t n_single;
    if (!PyArg_ParseTuple(args, "y*y*y*dddny*y*y*w*", &coef, &modes, &tab, &c, &inv_du, &ratio2, &n_single, &gszb,
                          &grkb, &facb, &out))
        return NULL;
    Py_ssize_t n_models = coef.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_modes = modes.len / (NSTRIDE * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_tab = tab.len / (4 * (Py_ssize_t)sizeof(float));
    Py_ssize_t n_groups = gszb.len / (Py_ssize_t)sizeof(long long);
    const long long *GS = (const long long *)gszb.buf, *GR = (const long long *)grkb.buf;
    Py_ssize_t max_group = check_groups(&gszb, &grkb, &facb, n_single, n_modes);
    if (out.len < n_models * NOUT * (Py_ssize_t)sizeof(double) || max_group < 0) {
        RELEASE(&coef, &modes, &tab, &gszb, &grkb, &facb, &out);
        PyErr_SetString(PyExc_ValueError, "model_sums: inconsistent buffer sizes");
        return NULL;
    }
    vnb *scratch = alloc_scratch(max_group);
    if (scratch == NULL) {
        RELEASE(&coef, &modes, &tab, &gszb, &grkb, &facb, &out);
        return PyErr_NoMemory();
    }
    const double *C = (const double *)coef.buf;
    const double *M = (const double *)modes.buf;
    const float *T = (const float *)tab.buf;
    const double *U = (const double *)facb.buf;
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
        block_sums(a0, a1, a2, M, n_single, n_groups, GS, GR, U, scratch, T, nmax, c, inv_du, ratio2, same, ob);
        for (int k = 0; k < NB && m0 + k < n_models; k++)
            for (int t = 0; t < NOUT; t++) O[NOUT * (m0 + k) + t] = ob[NOUT * k + t];
    }
    Py_END_ALLOW_THREADS

    free(scratch);
    RELEASE(&coef, &modes, &tab, &gszb, &grkb, &facb, &out);
    Py_RETURN_NONE;
}

/*
 * The same sums with the modes alone on their sampled mode binned per ellipticity in kappa = K^T C K:
 * for a model of that ellipticity and any size r the transform depends on a mode only through
 * r^2 kappa, so each bin's summed weights (the six linear vectors and q) stand for its modes at the
 * bin's kappa, to second order in the bin's width. The bins are uniform in kappa within each octave,
 * nb per octave (kappa = 2^E (1 + i/nb)): their relative width is 1/nb to 1/(2 nb), and a mode's bin
 * and its cloud-in-cell weights come from the exponent and mantissa bits of kappa, without a log.
 * The bins of a set of ellipticities are made once (make_bins) and serve models of any size at them
 * (binned_sums): block_sums takes them as modes of their own (basis [kappa_b / c11, 0, 0], so that
 * the model's coefficients give r^2 kappa_b); the folded modes are summed exactly, as in model_sums.
 * The DC mode (K = 0) has its own bin at kappa = 0. Bins no mode reaches are left out.
 */
static inline void octave_bin(double k, int nb, long long *idx, double *frac)
{
    uint64_t bits;
    memcpy(&bits, &k, sizeof bits);
    long long e = (long long)((bits >> 52) & 0x7ff);
    uint64_t mb = (bits & 0xfffffffffffffULL) | 0x3ff0000000000000ULL;  /* mantissa as a double in [1, 2) */
    double m;
    memcpy(&m, &mb, sizeof m);
    double x = (m - 1.0) * nb;
    long long i = (long long)x;
    *idx = e * nb + i;
    *frac = x - (double)i;
}

static inline double octave_kappa(long long idx, int nb)
{
    long long e = idx / nb, i = idx % nb;
    return ldexp(1.0 + (double)i / nb, (int)(e - 1023));
}

/* pass 1 of the binning: each mode's bin and cloud-in-cell fraction (in two loops that vectorise);
   returns the lowest and highest bin; the DC mode (kappa = 0) gets the bin LLONG_MIN */
MULTIVERSION
static void bin_index(const float *B3, Py_ssize_t n_single, double a0, double a1, double a2, int nb,
                      long long *idx, double *frac, long long *lo_out, long long *hi_out)
{
    for (Py_ssize_t j = 0; j < n_single; j++) {
        const float *p = B3 + 4 * j;
        double k = a0 * p[0] + a1 * p[1] + a2 * p[2];
        int pos = k > 0;
        uint64_t bits;
        double kk = pos ? k : 1.0;
        memcpy(&bits, &kk, sizeof bits);
        long long e = (long long)((bits >> 52) & 0x7ff);
        uint64_t mb = (bits & 0xfffffffffffffULL) | 0x3ff0000000000000ULL;  /* mantissa, a double in [1, 2) */
        double m;
        memcpy(&m, &mb, sizeof m);
        double x = (m - 1.0) * nb;
        long long i = (long long)x;
        frac[j] = x - (double)i;
        idx[j] = pos ? e * nb + i : LLONG_MIN;
    }
    long long lo = LLONG_MAX, hi = LLONG_MIN;
    for (Py_ssize_t j = 0; j < n_single; j++) {
        long long i = idx[j];
        long long v = i == LLONG_MIN ? LLONG_MAX : i;
        lo = v < lo ? v : lo;
        hi = i > hi ? i : hi;
    }
    *lo_out = lo;
    *hi_out = hi;
}

/* pass 2: the modes' weights into rows of 8 (the six linear vectors, q, padding) */
MULTIVERSION
static void bin_scatter(const float *C8, Py_ssize_t n_single, const long long *idx, const double *frac,
                        long long lo, Py_ssize_t nbin, double *A, char *used)
{
    for (Py_ssize_t j = 0; j < n_single; j++) {
        const float *c = C8 + 8 * j;
        if (idx[j] == LLONG_MIN) {
            double *w0 = A + 8 * nbin;
            for (int t = 0; t < 8; t++) w0[t] += c[t];
            used[nbin] = 1;
            continue;
        }
        Py_ssize_t b = (Py_ssize_t)(idx[j] - lo);
        double f = frac[j], g = 1.0 - f;
        double *w0 = A + 8 * b;
        for (int t = 0; t < 8; t++) { w0[t] += g * c[t]; w0[8 + t] += f * c[t]; }
        used[b] = used[b + 1] = 1;
    }
}

/*
 * make_bins(shape, basis32, channels32, bins_per_octave) -> (rows, offsets): for each ellipticity
 * (its shape coefficients c11, c12, c22), the bins some mode reached, as kernel modes of 12 doubles
 * (basis [kappa_b / c11, 0, 0], the summed linear vectors and q), the DC bin last; rows of
 * ellipticity e are offsets[e] .. offsets[e + 1] (bytes of float64 and of int64).
 */
static PyObject *make_bins(PyObject *self, PyObject *args)
{
    Py_buffer shape, b3, c8;
    int nb;
    if (!PyArg_ParseTuple(args, "y*y*y*i", &shape, &b3, &c8, &nb)) return NULL;
    Py_ssize_t n_e = shape.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_single = b3.len / (4 * (Py_ssize_t)sizeof(float));
    if (c8.len != 8 * n_single * (Py_ssize_t)sizeof(float) || nb < 1 || nb > 4096) {
        RELEASE(&shape, &b3, &c8);
        PyErr_SetString(PyExc_ValueError, "make_bins: inconsistent buffers");
        return NULL;
    }
    const double *S = (const double *)shape.buf;
    Py_ssize_t ns = n_single > 0 ? n_single : 1;
    long long *idx = (long long *)malloc(ns * sizeof(long long));
    double *frac = (double *)malloc(ns * sizeof(double));
    long long *off = (long long *)malloc((n_e + 1) * sizeof(long long));
    double *A = NULL, *rows = NULL;
    char *used = NULL;
    Py_ssize_t capA = 0, capR = 0, nrows = 0;
    int nomem = (idx == NULL || frac == NULL || off == NULL);

    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t e = 0; !nomem && e < n_e; e++) {
        const double a0 = S[3 * e], a1 = S[3 * e + 1], a2 = S[3 * e + 2];
        long long lo, hi;
        bin_index((const float *)b3.buf, n_single, a0, a1, a2, nb, idx, frac, &lo, &hi);
        Py_ssize_t nbin = hi >= lo ? (Py_ssize_t)(hi - lo) + 2 : 0;   /* plus the upper neighbour of the last */
        if (nbin + 1 > capA) {
            free(A); free(used);
            capA = 2 * (nbin + 1);
            A = (double *)malloc(capA * 8 * sizeof(double));
            used = (char *)malloc(capA);
            if (A == NULL || used == NULL) { nomem = 1; break; }
        }
        memset(A, 0, (nbin + 1) * 8 * sizeof(double));
        memset(used, 0, nbin + 1);
        bin_scatter((const float *)c8.buf, n_single, idx, frac, lo, nbin, A, used);
        if (nrows + nbin + 1 > capR) {
            capR = 2 * (nrows + nbin + 1);
            double *r = (double *)realloc(rows, capR * NSTRIDE * sizeof(double));
            if (r == NULL) { nomem = 1; break; }
            rows = r;
        }
        off[e] = nrows;
        for (Py_ssize_t b = 0; b <= nbin; b++) {
            if (!used[b]) continue;
            double *w = rows + NSTRIDE * nrows;
            w[0] = b < nbin ? octave_kappa(lo + b, nb) / a0 : 0.0;
            w[1] = w[2] = 0.0;
            for (int t = 0; t < 7; t++) w[3 + t] = A[8 * b + t];
            w[10] = w[11] = 0.0;
            nrows++;
        }
    }
    off[n_e] = nrows;
    Py_END_ALLOW_THREADS

    PyObject *res = NULL;
    if (!nomem) {
        PyObject *r = PyBytes_FromStringAndSize((const char *)rows, nrows * NSTRIDE * sizeof(double));
        PyObject *o = PyBytes_FromStringAndSize((const char *)off, (n_e + 1) * sizeof(long long));
        if (r && o) res = PyTuple_Pack(2, r, o);
        Py_XDECREF(r);
        Py_XDECREF(o);
    }
    free(idx); free(frac); free(off); free(A); free(rows); free(used);
    RELEASE(&shape, &b3, &c8);
    if (nomem) return PyErr_NoMemory();
    return res;
}

/*
 * binned_sums(shape, r2, e_index, rows, offsets, modes, table, c, inv_du, ratio2, n_single, out): the
 * sums of models (r2 and the ellipticity e_index each, into shape and make_bins' rows and offsets),
 * from the bins of their ellipticity plus the folded modes (modes[n_single:]), summed exactly.
 */
static PyObject *binned_sums(PyObject *self, PyObject *args)
{
    Py_buffer shape, r2b, eidx, rowsb, offb, modes, tab, gszb, grkb, facb, out;
    double c, inv_du, ratio2;
    Py_ssize_t n_single;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*dddny*y*y*w*", &shape, &r2b, &eidx, &rowsb, &offb, &modes, &tab, &c,
                          &inv_du, &ratio2, &n_single, &gszb, &grkb, &facb, &out))
        return NULL;
    Py_ssize_t n_models = r2b.len / (Py_ssize_t)sizeof(double);
    Py_ssize_t n_e = shape.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_modes = modes.len / (NSTRIDE * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_rows = rowsb.len / (NSTRIDE * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_tab = tab.len / (4 * (Py_ssize_t)sizeof(float));
    Py_ssize_t n_groups = gszb.len / (Py_ssize_t)sizeof(long long);
    const long long *E = (const long long *)eidx.buf, *OFF = (const long long *)offb.buf;
    const long long *GS = (const long long *)gszb.buf, *GR = (const long long *)grkb.buf;
    Py_ssize_t max_group = check_groups(&gszb, &grkb, &facb, n_single, n_modes);
    int bad = out.len < n_models * NOUT * (Py_ssize_t)sizeof(double) || max_group < 0
              || eidx.len != n_models * (Py_ssize_t)sizeof(long long)
              || offb.len != (n_e + 1) * (Py_ssize_t)sizeof(long long) || OFF[n_e] != n_rows;
    for (Py_ssize_t m = 0; !bad && m < n_models; m++)
        bad = E[m] < 0 || E[m] >= n_e;
    for (Py_ssize_t e = 0; !bad && e < n_e; e++)
        bad = OFF[e] < 0 || OFF[e] > OFF[e + 1];
    if (bad) {
        RELEASE(&shape, &r2b, &eidx, &rowsb, &offb, &modes, &tab, &gszb, &grkb, &facb, &out);
        PyErr_SetString(PyExc_ValueError, "binned_sums: inconsistent buffers");
        return NULL;
    }
    vnb *scratch = alloc_scratch(max_group);
    if (scratch == NULL) {
        RELEASE(&shape, &r2b, &eidx, &rowsb, &offb, &modes, &tab, &gszb, &grkb, &facb, &out);
        return PyErr_NoMemory();
    }
    const double *S = (const double *)shape.buf;
    const double *R2 = (const double *)r2b.buf;
    const double *M = (const double *)modes.buf;
    const double *ROWS = (const double *)rowsb.buf;
    const float *T = (const float *)tab.buf;
    const double *U = (const double *)facb.buf;
    double *O = (double *)out.buf;
    const double nmax = (double)(n_tab - 1);
    const int same = (ratio2 == 1.0);

    Py_BEGIN_ALLOW_THREADS
    /* the bins, per run of models with one ellipticity */
    Py_ssize_t m0 = 0;
    while (m0 < n_models) {
        Py_ssize_t m1 = m0;
        while (m1 < n_models && E[m1] == E[m0]) m1++;
        const long long e = E[m0];
        const double a0 = S[3 * e], a1 = S[3 * e + 1], a2 = S[3 * e + 2];
        const double *W = ROWS + NSTRIDE * OFF[e];
        const Py_ssize_t nbins = (Py_ssize_t)(OFF[e + 1] - OFF[e]);
        for (Py_ssize_t b0 = m0; b0 < m1; b0 += NB) {
            double c0[NB], c1[NB], c2[NB], ob[NB * NOUT];
            for (int k = 0; k < NB; k++) {
                Py_ssize_t m = b0 + k < m1 ? b0 + k : m1 - 1;
                c0[k] = a0 * R2[m]; c1[k] = a1 * R2[m]; c2[k] = a2 * R2[m];
            }
            block_sums(c0, c1, c2, W, nbins, 0, GS, GR, U, scratch, T, nmax, c, inv_du, ratio2, same, ob);
            for (int k = 0; k < NB && b0 + k < m1; k++)
                for (int t = 0; t < NOUT; t++) O[NOUT * (b0 + k) + t] = ob[NOUT * k + t];
        }
        m0 = m1;
    }
    /* the fold groups, summed exactly, in full blocks whatever the models' ellipticities */
    if (n_groups > 0) {
        const double *MG = M + NSTRIDE * n_single;
        for (Py_ssize_t b0 = 0; b0 < n_models; b0 += NB) {
            double c0[NB], c1[NB], c2[NB], om[NB * NOUT];
            for (int k = 0; k < NB; k++) {
                Py_ssize_t m = b0 + k < n_models ? b0 + k : n_models - 1;
                const long long e = E[m];
                c0[k] = S[3 * e] * R2[m]; c1[k] = S[3 * e + 1] * R2[m]; c2[k] = S[3 * e + 2] * R2[m];
            }
            block_sums(c0, c1, c2, MG, 0, n_groups, GS, GR, U, scratch, T, nmax, c, inv_du, ratio2, same, om);
            for (int k = 0; k < NB && b0 + k < n_models; k++)
                for (int t = 0; t < NOUT; t++) O[NOUT * (b0 + k) + t] += om[NOUT * k + t];
        }
    }
    Py_END_ALLOW_THREADS

    free(scratch);
    RELEASE(&shape, &r2b, &eidx, &rowsb, &offb, &modes, &tab, &gszb, &grkb, &facb, &out);
    Py_RETURN_NONE;
}

/*
 * The marginalisation of each model over bulge fraction, position and flux (likelihood.py's
 * flux_position_marginal, which stays as the reference: a test checks they agree). erfcx and expi
 * are scipy.special's own (cython_special), whose C entry points the module is given once
 * (set_special); erf, exp and log are the C library's.
 */
typedef double (*special_fn)(double, int);
static special_fn sp_erfcx = NULL, sp_expi = NULL;
static const char *SPECIAL_SIG = "double (double, int __pyx_skip_dispatch)";
/* log Ei and its derivative e^x / (x Ei(x)) at x = ei_x0 + i ei_dx, from scipy's expi (likelihood.py):
   cubic Hermite interpolation between them is good to 1e-11, and 50 times faster than expi itself */
static double *ei_tab = NULL;
static Py_ssize_t ei_n = 0;
static double ei_x0 = 0.0, ei_dx = 1.0;

static PyObject *set_special(PyObject *self, PyObject *args)
{
    PyObject *c1, *c2;
    Py_buffer tab;
    double x0, dx;
    if (!PyArg_ParseTuple(args, "OOy*dd", &c1, &c2, &tab, &x0, &dx)) return NULL;
    if (!PyCapsule_IsValid(c1, SPECIAL_SIG) || !PyCapsule_IsValid(c2, SPECIAL_SIG) || !(dx > 0)
        || tab.len < 4 * (Py_ssize_t)sizeof(double) || tab.len % (2 * sizeof(double))) {
        PyBuffer_Release(&tab);
        PyErr_SetString(PyExc_ValueError, "set_special: capsules of signature 'double (double, int)' and a table needed");
        return NULL;
    }
    double *t = (double *)malloc(tab.len);
    if (t == NULL) { PyBuffer_Release(&tab); return PyErr_NoMemory(); }
    memcpy(t, tab.buf, tab.len);
    free(ei_tab);
    ei_tab = t;
    ei_n = tab.len / (2 * (Py_ssize_t)sizeof(double));
    ei_x0 = x0;
    ei_dx = dx;
    PyBuffer_Release(&tab);
    sp_erfcx = (special_fn)PyCapsule_GetPointer(c1, SPECIAL_SIG);
    sp_expi = (special_fn)PyCapsule_GetPointer(c2, SPECIAL_SIG);
    Py_RETURN_NONE;
}

#define LOG_2PI 1.8378770664093453
#define EI_SERIES_FROM 40.0

static double log_ei(double x)
{
    if (x < EI_SERIES_FROM) {
        double t = (x - ei_x0) / ei_dx;
        if (t >= 0 && t < (double)(ei_n - 1)) {
            Py_ssize_t i = (Py_ssize_t)t;
            double s = t - (double)i, s1 = 1.0 - s;
            const double *a = ei_tab + 2 * i;
            return (1 + 2 * s) * s1 * s1 * a[0] + s * s1 * s1 * ei_dx * a[1]
                   + s * s * (3 - 2 * s) * a[2] - s * s * s1 * ei_dx * a[3];
        }
        return log(sp_expi(x, 0));
    }
    /* asymptotic series, the same 13 terms k! / x^k as likelihood._log_ei */
    static const double fact[13] = {1.0, 1.0, 2.0, 6.0, 24.0, 120.0, 720.0, 5040.0, 40320.0, 362880.0,
                                    3628800.0, 39916800.0, 479001600.0};
    double inv = 1.0 / x, series = 0.0;
    for (int k = 12; k >= 0; k--) series = series * inv + fact[k];
    return x - log(x) + log(series);
}

static double log_erf_diff_c(double a, double b)
{
    if (b >= 0) {
        /* erfcx(a) <= erfcx(b): below e^-745 relative the second term cannot change the double */
        double d = b * b - a * a;
        return -b * b + log(sp_erfcx(b, 0) - (d > -745.0 ? sp_erfcx(a, 0) * exp(d) : 0.0));
    }
    if (a <= 0) {
        double al = -b, bl = -a;
        return -bl * bl + log(sp_erfcx(bl, 0) - sp_erfcx(al, 0) * exp(bl * bl - al * al));
    }
    return log(erf(a) - erf(b));
}

typedef struct {
    double sb2, b0, log_zb, tcrit, log_ei_tcrit, mu_min, max_step, slope, halfwidth;
    int bounded;
} MargPar;

/* log P_disk and <B> at (hf, hg), and log P_disk at h = 0 (the pedestal), which shares theta */
static void disk_logp_c(double S, double ff, double gg, double fg, double hf, double hg, const MargPar *P,
                        double *logp, double *meanb, double *logp0)
{
    double two_theta2 = S * S * (ff + gg - 2 * fg) + 1.0 / P->sb2;
    double theta = sqrt(0.5 * two_theta2), log_theta = log(theta);
    for (int zero = 0; zero < 2; zero++) {
        double h_f = zero ? 0.0 : hf, h_g = zero ? 0.0 : hg;
        double r0 = S * (h_f - h_g) + S * S * (fg - ff) - P->b0 / P->sb2;
        double a = theta + r0 / (2 * theta), b = r0 / (2 * theta);
        double lediff = log_erf_diff_c(a, b);
        double v = (S * h_f - 0.5 * S * S * ff - 0.5 * P->b0 * P->b0 / P->sb2 + r0 * r0 / (4 * theta * theta)
                    + log(sqrt(M_PI) / 2) - log_theta + lediff - P->log_zb);
        if (zero) {
            *logp0 = v;
        } else {
            *logp = v;
            double mu = -r0 / (2 * theta * theta);
            double num = exp(-b * b - lediff) - exp(-a * a - lediff);
            double m = mu + num / (theta * sqrt(M_PI));
            if (m < 0) m = 0;
            if (m > 1) m = 1;
            *meanb = m;
        }
    }
}

/* likelihood._position_integral for one element: returns the log integral, and corr */
static double position_c(double lp_ref, double lp0, double g1, double g2, const double *H, const MargPar *P,
                         double *corr_out)
{
    double h11 = -H[0], h12 = -H[1], h22 = -H[2];
    double logdet, gqg, step;
    int ok;
    if (P->bounded) {
        double half_tr = 0.5 * (h11 + h22);
        double rad = sqrt(0.25 * (h11 - h22) * (h11 - h22) + h12 * h12);
        double lam1 = fmax(half_tr + rad, P->mu_min), lam2 = fmax(half_tr - rad, P->mu_min);
        if (isnan(half_tr + rad)) lam1 = NAN;     /* np.maximum propagates NaN */
        if (isnan(half_tr - rad)) lam2 = NAN;
        double gg = g1 * g1 + g2 * g2;
        double gmg = h11 * g1 * g1 + 2 * h12 * g1 * g2 + h22 * g2 * g2;
        double p1sq = rad > 1e-9 * fabs(half_tr) ? (gmg - (half_tr - rad) * gg) / (2 * rad) : gg;
        p1sq = p1sq < 0 ? 0 : (p1sq > gg ? gg : p1sq);
        double p2sq = gg - p1sq;
        ok = isfinite(lam1) && isfinite(lam2);
        logdet = log(lam1 * lam2);
        gqg = p1sq / lam1 + p2sq / lam2;
        step = sqrt(p1sq / (lam1 * lam1) + p2sq / (lam2 * lam2));
    } else {
        double det = h11 * h22 - h12 * h12;
        ok = (h11 > 0) && (det > 0);
        logdet = ok ? log(det) : 0.0;
        gqg = (g1 * g1 * h22 - 2 * g1 * g2 * h12 + g2 * g2 * h11) / det;
        step = 0.0;
    }
    double t = step > P->max_step ? P->max_step / (step > 0 ? step : 1.0) : 1.0;
    double corr = (t - 0.5 * t * t) * gqg;
    corr = ok ? (corr > 0 ? corr : (isnan(corr) ? NAN : 0.0)) : 0.0;
    *corr_out = corr;
    if (!ok) return -INFINITY;
    double A = lp_ref + corr - lp0;
    double lei;
    if (A > P->tcrit) {
        double la = log_ei(A);
        /* log1p(-e^-d) ~ -e^-d is below half a unit in the last place of la once d > 37 and |la| >= 1:
           the sum is la itself */
        lei = (la - P->log_ei_tcrit > 37.0 && fabs(la) >= 1.0) ? la : la + log1p(-exp(P->log_ei_tcrit - la));
    } else {
        lei = -INFINITY;
    }
    return lp0 + LOG_2PI - 0.5 * logdet + log(A > 0 ? A : 1.0) + lei;
}

#define MAXF 64

static PyObject *marginal(PyObject *self, PyObject *args)
{
    Py_buffer sums, ub, ufb, spl, itp, par, out;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*w*", &sums, &ub, &ufb, &spl, &itp, &par, &out)) return NULL;
    Py_ssize_t n = sums.len / (15 * (Py_ssize_t)sizeof(double));
    Py_ssize_t nf = ub.len / (Py_ssize_t)sizeof(double), nfine = ufb.len / (Py_ssize_t)sizeof(double);
    int bad = sp_erfcx == NULL || nf < 2 || nf > MAXF || nfine < 2 || nfine > 4 * MAXF
              || spl.len != nf * nfine * (Py_ssize_t)sizeof(double) || itp.len != spl.len
              || par.len != 10 * (Py_ssize_t)sizeof(double) || out.len < 9 * n * (Py_ssize_t)sizeof(double);
    if (bad) {
        RELEASE(&sums, &ub, &ufb, &spl, &itp, &par, &out);
        PyErr_SetString(PyExc_ValueError, sp_erfcx == NULL ? "marginal: set_special first"
                                                           : "marginal: inconsistent buffers");
        return NULL;
    }
    const double *X = (const double *)sums.buf, *u = (const double *)ub.buf, *uf = (const double *)ufb.buf;
    const double *SPL = (const double *)spl.buf, *ITP = (const double *)itp.buf, *pp = (const double *)par.buf;
    double *O = (double *)out.buf;
    MargPar P = {pp[0], pp[1], pp[2], pp[3], 0.0, pp[4], pp[5], pp[6], pp[7], pp[8] != 0.0};
    Py_BEGIN_ALLOW_THREADS
    P.log_ei_tcrit = log_ei(P.tcrit);
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *x = X + 15 * i;
        /* kernel layout: hf, grad_f (2), hess_f (3), hg, grad_g (2), hess_g (3), ff, gg, fg */
        const double ff = x[12], gg = x[13], fg = x[14];
        double *o = O + 9 * i;   /* logl_d, logl_b, flux_d, flux_b, meanb_d, chi2_d, chi2_b, snr_d, snr_b */
        for (int pop = 0; pop < 2; pop++) {
            const double *L = x + 6 * pop;   /* h, grad, hess of this population */
            double h = L[0], hh = pop == 0 ? ff : gg;
            int good = (hh > 0) && (h > 0);
            double hh_s = good ? hh : 1.0, s_ml = good ? h / hh_s : 1.0, sig = 1.0 / sqrt(hh_s);
            double lo = fmax(s_ml - P.halfwidth * sig, 0.02 * s_ml), hi = s_ml + P.halfwidth * sig;
            double lp[MAXF], mb[MAXF];
            double Sk[MAXF], logS[MAXF];
            for (Py_ssize_t k = 0; k < nf; k++) Sk[k] = lo + (hi - lo) * u[k];
            vlog(Sk, logS, nf);
            for (Py_ssize_t k = 0; k < nf; k++) {
                double S = Sk[k], logp, logp0, meanb, g[2], H[3], corr;
                if (pop == 0) {
                    disk_logp_c(S, ff, gg, fg, x[0], x[6], &P, &logp, &meanb, &logp0);
                    for (int t = 0; t < 2; t++) g[t] = S * ((1 - meanb) * x[1 + t] + meanb * x[7 + t]);
                    for (int t = 0; t < 3; t++) H[t] = S * ((1 - meanb) * x[3 + t] + meanb * x[9 + t]);
                } else {
                    logp = S * x[6] - 0.5 * S * S * gg;
                    logp0 = -0.5 * S * S * gg;
                    for (int t = 0; t < 2; t++) g[t] = S * x[7 + t];
                    for (int t = 0; t < 3; t++) H[t] = S * x[9 + t];
                    meanb = 1.0;
                }
                double v = position_c(logp, logp0, g[0], g[1], H, &P, &corr) - P.slope * logS[k];
                lp[k] = good ? v : -INFINITY;
                mb[k] = meanb;
            }
            /* the cubic spline of log P over the flux nodes, integrated on the fine grid (_spline_logint) */
            double rowmax = -INFINITY;
            for (Py_ssize_t k = 0; k < nf; k++) if (isfinite(lp[k]) && lp[k] > rowmax) rowmax = lp[k];
            int good_row = isfinite(rowmax);
            double floor_ = good_row ? rowmax - 40.0 : 0.0;
            double lv[MAXF];
            for (Py_ssize_t k = 0; k < nf; k++) lv[k] = isfinite(lp[k]) ? fmax(lp[k], floor_) : floor_;
            double vf[4 * MAXF], m = -INFINITY;
            for (Py_ssize_t q = 0; q < nfine; q++) {
                double acc = 0.0;
                for (Py_ssize_t k = 0; k < nf; k++) acc += lv[k] * SPL[k * nfine + q];
                vf[q] = acc;
                if (acc > m) m = acc;
            }
            double integral = 0.0, wsum = 0.0, ws = 0.0, wb = 0.0, wprev = 0.0, wv[4 * MAXF];
            vexp_shift(vf, m, wv, nfine);
            for (Py_ssize_t q = 0; q < nfine; q++) {
                double w = wv[q];
                if (q > 0) integral += 0.5 * (w + wprev) * (uf[q] - uf[q - 1]);
                wprev = w;
                wsum += w;
                ws += w * (lo + (hi - lo) * uf[q]);
                if (pop == 0) {
                    double bf = 0.0;
                    for (Py_ssize_t k = 0; k < nf; k++) bf += mb[k] * ITP[k * nfine + q];
                    wb += w * bf;
                } else {
                    wb += w;
                }
            }
            if (!(wsum > 0)) wsum = 1.0;
            double logint = good_row ? m + log(integral) : -INFINITY;
            logint += log(hi - lo);
            /* best-fit chi^2 of the single-component model at its best flux and position */
            double gpos[2] = {L[1] * s_ml, L[2] * s_ml}, Hpos[3] = {L[3] * s_ml, L[4] * s_ml, L[5] * s_ml}, cml;
            position_c(0.0, -1.0, gpos[0], gpos[1], Hpos, &P, &cml);
            double chi2 = good ? -(h * h / hh_s) - 2 * cml : 0.0;
            o[pop] = good ? logint : -INFINITY;
            o[2 + pop] = ws / wsum;
            if (pop == 0) o[4] = wb / wsum;
            o[5 + pop] = chi2;
            o[7 + pop] = good ? h / sqrt(hh_s) : 0.0;
        }
    }
    Py_END_ALLOW_THREADS
    RELEASE(&sums, &ub, &ufb, &spl, &itp, &par, &out);
    Py_RETURN_NONE;
}

/*
 * size_marginal(ld, lb, fd, fb, bd, logprior, lsegprior, spline, interp, xf, u, rf, l0, logmix, out): the size
 * integral of sampling.EllipticityLikelihood._size_marginal (which stays as the reference: a test checks they
 * agree). Per ellipticity e and population (disk, bulge): log L at the n_r nodes (ld, lb; floored 40 below
 * their maximum), splined onto the fine ln r grid xf (spline: n_r x n_f), plus the log prior there
 * (logprior: n_e x n_f); from r = 0 to the first node, log L linear in r^2 between the point source (l0)
 * and the first node, on u in [0, 1] (lsegprior: n_e x n_u); trapezoid sums; posterior means of r and of
 * the flux and B (fd, fb, bd linearly interpolated from the nodes, interp: n_r x n_f); the populations
 * mixed by logmix (log(1 - f_B), log f_B). out (5 x n_e): log L disk, log L bulge, mean r, mean B, mean flux.
 */
#define MAXN 512
static PyObject *size_marginal(PyObject *self, PyObject *args)
{
    Py_buffer b[15];
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*y*y*y*y*y*w*", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6],
                          &b[7], &b[8], &b[9], &b[10], &b[11], &b[12], &b[13], &b[14]))
        return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    Py_ssize_t nf = b[9].len / D, nu = b[10].len / D, nr = nf > 0 ? b[7].len / D / nf : 0;
    Py_ssize_t ne = nr > 0 ? b[0].len / D / nr : 0;
    int bad = nf < 2 || nu < 2 || nr < 2 || nf > MAXN || nu > MAXN || nr > MAXN
              || b[8].len != nr * nf * D || b[7].len != nr * nf * D || b[12].len != 2 * D || b[13].len != 2 * D
              || b[14].len < 5 * ne * D || b[5].len != ne * nf * D || b[11].len != ne * nf * D
              || b[6].len != ne * nu * D;
    for (int i = 1; i < 5 && !bad; i++) bad = b[i].len != ne * nr * D;
    if (bad) {
        RELEASE(&b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7], &b[8], &b[9], &b[10], &b[11], &b[12],
                &b[13], &b[14]);
        PyErr_SetString(PyExc_ValueError, "size_marginal: inconsistent buffers");
        return NULL;
    }
    const double *LD = b[0].buf, *LB = b[1].buf, *FD = b[2].buf, *FB = b[3].buf, *BD = b[4].buf;
    const double *LP = b[5].buf, *LS = b[6].buf, *SPL = b[7].buf, *ITP = b[8].buf, *XF = b[9].buf, *U = b[10].buf;
    const double *RF = b[11].buf, *L0 = b[12].buf, *LM = b[13].buf;
    double *O = b[14].buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t e = 0; e < ne; e++) {
        const double *rf = RF + e * nf;
        double lm[2], mr[2], mf[2], mb = 0.0;
        for (int pop = 0; pop < 2; pop++) {
            const double *L = (pop == 0 ? LD : LB) + e * nr, *F = (pop == 0 ? FD : FB) + e * nr;
            double rowmax = -INFINITY, lv[MAXN], vf[MAXN], w[MAXN];
            for (Py_ssize_t n = 0; n < nr; n++) if (isfinite(L[n]) && L[n] > rowmax) rowmax = L[n];
            int good = isfinite(rowmax);
            double floor_ = good ? rowmax - 40.0 : 0.0;
            for (Py_ssize_t n = 0; n < nr; n++) lv[n] = isfinite(L[n]) ? (L[n] > floor_ ? L[n] : floor_) : floor_;
            double m = -INFINITY;
            for (Py_ssize_t q = 0; q < nf; q++) {
                double acc = 0.0;
                for (Py_ssize_t n = 0; n < nr; n++) acc += lv[n] * SPL[n * nf + q];
                vf[q] = acc + LP[e * nf + q];
                if (vf[q] > m) m = vf[q];
            }
            double l0 = isfinite(L0[pop]) ? L0[pop] : -INFINITY, lseg[MAXN];
            for (Py_ssize_t j = 0; j < nu; j++) {
                lseg[j] = (isfinite(l0) ? (1 - U[j]) * (l0 > -1e300 ? l0 : -1e300) + U[j] * lv[0]
                                        : lv[0] - 1e3 * (1 - U[j])) + LS[e * nu + j];
                if (lseg[j] > m) m = lseg[j];
            }
            double integ = 0.0, seg = 0.0, wsum = 0.0, wr = 0.0, wf = 0.0, wb = 0.0;
            double es[MAXN];
            vexp_shift(vf, m, w, nf);
            vexp_shift(lseg, m, es, nu);
            for (Py_ssize_t q = 0; q < nf; q++) {
                if (q > 0) integ += (XF[q] - XF[q - 1]) * (w[q] + w[q - 1]) * 0.5;
                wsum += w[q];
                wr += w[q] * rf[q];
                double fi = 0.0, bi = 0.0;
                for (Py_ssize_t n = 0; n < nr; n++) fi += F[n] * ITP[n * nf + q];
                wf += w[q] * fi;
                if (pop == 0) {
                    for (Py_ssize_t n = 0; n < nr; n++) bi += BD[e * nr + n] * ITP[n * nf + q];
                    wb += w[q] * bi;
                }
            }
            for (Py_ssize_t j = 1; j < nu; j++) seg += (U[j] - U[j - 1]) * (es[j] + es[j - 1]) * 0.5;
            integ += seg * 0.5 * rf[0] * rf[0];
            lm[pop] = good ? m + log(integ) : -INFINITY;
            if (!(wsum > 1e-300)) wsum = 1e-300;
            mr[pop] = wr / wsum;
            mf[pop] = wf / wsum;
            if (pop == 0) mb = wb / wsum;
        }
        double la = LM[0] + lm[0], lbb = LM[1] + lm[1];
        double mx = la > lbb ? la : lbb;
        if (!isfinite(mx)) mx = 0.0;
        double pa = exp(la - mx), pb = exp(lbb - mx), tot = pa + pb;
        if (!(tot > 1e-300)) tot = 1e-300;
        O[e] = lm[0];
        O[ne + e] = lm[1];
        O[2 * ne + e] = (pa * mr[0] + pb * mr[1]) / tot;
        O[3 * ne + e] = (pa * mb + pb * 1.0) / tot;
        O[4 * ne + e] = (pa * mf[0] + pb * mf[1]) / tot;
    }
    Py_END_ALLOW_THREADS
    RELEASE(&b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7], &b[8], &b[9], &b[10], &b[11], &b[12], &b[13],
            &b[14]);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"model_sums", model_sums, METH_VARARGS,
     "model_sums(coef, modes, table, c, inv_du, ratio2, n_single, group_sizes, group_ranks, group_factors, out)"},
    {"set_special", set_special, METH_VARARGS, "set_special(erfcx_capsule, expi_capsule)"},
    {"marginal", marginal, METH_VARARGS, "marginal(sums, u, u_fine, spline, interp, params, out)"},
    {"size_marginal", size_marginal, METH_VARARGS,
     "size_marginal(ld, lb, fd, fb, bd, logprior, lsegprior, spline, interp, xf, u, rf, l0, logmix, out)"},
    {"make_bins", make_bins, METH_VARARGS, "make_bins(shape, basis32, channels32, bins_per_octave) -> (rows, offsets)"},
    {"binned_sums", binned_sums, METH_VARARGS,
     "binned_sums(shape, r2, e_index, rows, offsets, modes, table, c, inv_du, ratio2, n_single, group_sizes, "
     "group_ranks, group_factors, out)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "Compiled inner loop of the shearfit likelihood.", -1, methods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
