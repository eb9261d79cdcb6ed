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
#include <float.h>

#define NSTRIDE 12
#define NOUT 15

/* table rows are [value_f, slope_f, value_g, slope_g] in float32; the last row is zero */
/* Models are processed NB at a time: each mode's data is loaded once for the block, and the
 * per-model arithmetic (independent across the block) vectorises (the module is built for several
 * instruction-set levels, see below). Eight models fill one AVX-512 register
 * (8 % faster per galaxy than four, benchmarks/speed.py). */
#define NB 8
/* The module is compiled once per instruction-set level (setup.py: _kernels for the compiler's baseline,
 * _kernels_v3 with -march=x86-64-v3 (AVX2, FMA), _kernels_v4 with -march=x86-64-v4 (AVX-512)), each file
 * whole, so that every loop is vectorised for its level; shearfit.engine.kernel imports the best one the CPU
 * runs, or the one SHEARFIT_ISA names. No run-time dispatch inside the module (no ifunc: musl and clang build
 * it too). KERNEL_MODULE names the module, KERNEL_LEVEL its level. */
#ifndef KERNEL_MODULE
#define KERNEL_MODULE _kernels
#endif
#ifndef KERNEL_LEVEL
#define KERNEL_LEVEL "baseline"
#endif
#define K_CAT_(a, b) a##b
#define K_CAT(a, b) K_CAT_(a, b)
#define K_STR_(a) #a
#define K_STR(a) K_STR_(a)

/* glibc's vector exp and log (libmvec, linked with libm): simple loops over arrays of them vectorise,
 * 8 at a time with AVX-512. Only where they exist (glibc on x86-64 with GCC); elsewhere the loops stay
 * scalar. They are accurate to a few units in the last place, as the scalar ones to one. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && defined(__GLIBC__)
double exp(double) __attribute__((simd("notinbranch")));
double log(double) __attribute__((simd("notinbranch")));
double sin(double) __attribute__((simd("notinbranch")));
double cos(double) __attribute__((simd("notinbranch")));
#if __GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 35)
double log2(double) __attribute__((simd("notinbranch")));
double erfc(double) __attribute__((simd("notinbranch")));
#endif
#endif

/* out[i] = exp(x[i] - shift) and out[i] = log(x[i]), vectorised where the CPU allows */
static void vexp_shift(const double *x, double shift, double *out, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) out[i] = exp(x[i] - shift);
}

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

/* the table rows of the NB models (four floats each: value and slope of the disk, of the bulge) as four
   vectors across the models: eight 16-byte loads and a transpose in registers, where a gather of each
   float into its lane took a load and an insert per float (NB = 8 only) */
typedef float v4f __attribute__((vector_size(16), aligned(4)));
typedef float v8f __attribute__((vector_size(32)));
typedef float v16f __attribute__((vector_size(64)));
static inline __attribute__((always_inline)) void rows_t(const float *const *row, vnb *c0, vnb *c1, vnb *c2,
                                                         vnb *c3)
{
#if NB == 8 && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
    v4f r[8];
    for (int k = 0; k < 8; k++) r[k] = *(const v4f *)row[k];
    v8f a01 = __builtin_shufflevector(r[0], r[1], 0, 1, 2, 3, 4, 5, 6, 7);
    v8f a23 = __builtin_shufflevector(r[2], r[3], 0, 1, 2, 3, 4, 5, 6, 7);
    v8f a45 = __builtin_shufflevector(r[4], r[5], 0, 1, 2, 3, 4, 5, 6, 7);
    v8f a67 = __builtin_shufflevector(r[6], r[7], 0, 1, 2, 3, 4, 5, 6, 7);
    v16f A = __builtin_shufflevector(a01, a23, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    v16f B = __builtin_shufflevector(a45, a67, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    *c0 = __builtin_convertvector(__builtin_shufflevector(A, B, 0, 4, 8, 12, 16, 20, 24, 28), vnb);
    *c1 = __builtin_convertvector(__builtin_shufflevector(A, B, 1, 5, 9, 13, 17, 21, 25, 29), vnb);
    *c2 = __builtin_convertvector(__builtin_shufflevector(A, B, 2, 6, 10, 14, 18, 22, 26, 30), vnb);
    *c3 = __builtin_convertvector(__builtin_shufflevector(A, B, 3, 7, 11, 15, 19, 23, 27, 31), vnb);
#else
    for (int k = 0; k < NB; k++) {
        (*c0)[k] = row[k][0]; (*c1)[k] = row[k][1]; (*c2)[k] = row[k][2]; (*c3)[k] = row[k][3];
    }
#endif
}

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
    const float *row[NB], *rowg[NB];
    vnb fi, fig;
    for (int k = 0; k < NB; k++) {
        double uk = u[k] < nmax ? u[k] : nmax;
        long i = (long)uk;
        row[k] = T + 4 * i;
        fi[k] = uk - (double)i;
    }
    vnb vf, sf, vg, slg, x0, x1;
    rows_t(row, &vf, &sf, &vg, &slg);
    if (same) {
        fig = fi;
    } else {
        for (int k = 0; k < NB; k++) sg[k] = sqrt(c2 + rho2[k] * ratio2);
        ug = (sg - c) * inv_du;
        for (int k = 0; k < NB; k++) {
            double ugk = ug[k] < nmax ? ug[k] : nmax;
            long ig = (long)ugk;
            rowg[k] = T + 4 * ig;
            fig[k] = ugk - (double)ig;
        }
        rows_t(rowg, &x0, &x1, &vg, &slg);
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
 * r^2 kappa, so the bins' summed weights (the six linear vectors and q) stand for their modes at the
 * bins' kappa. The bins are uniform in log kappa, nb per octave (kappa_b = 2^(b/nb)); each mode is
 * shared among the four bins around it with the weights of cubic Lagrange interpolation in log kappa,
 * so the sums are right to fourth order in the bins' width (16 per octave: 7e-6 of the largest sum,
 * where 64 bins per octave of the earlier linear sharing gave the same).
 * The bins of a set of ellipticities are made once (make_bins) and serve models of any size at them
 * (binned_sums). Since the bins are uniform in log kappa, a model of size r meets the transforms at
 * log2(rho^2) = log2(r^2) + b / nb: points equally spaced on one table uniform in log2(rho^2)
 * (profiles.FastRadial.log_table, P = nb M points per octave), all at one fraction of its step. Its
 * bins' transforms are then a linear interpolation between two contiguous rows of that table laid out
 * by phase (row s holds points s, s + M, s + 2M, ...): no square root and no gather per bin. The DC
 * mode (K = 0) has its own bin, at the transform's value at 0. The modes of the fold groups are binned
 * too (their linear vectors, and the diagonal of Re H as their q); each group's cross terms
 * 2 Re H_ab R_a R_b take R_a and R_b from the bins' transforms by the same cubic interpolation (model_sums
 * sums them exactly, which cost 3 to 7 times the binned sums where an object had a hundred groups).
 */
/* log2 of x > 0 (normal) to 2e-11: the exponent, and log2 of the mantissa m in [sqrt(1/2), sqrt(2)) by the series
   2/ln2 atanh(s), s = (m - 1)/(m + 1), |s| < 0.172, to s^11. Integer work in 64-bit shifts, ands and ors only
   (the exponent becomes a double by the 2^52 trick), so that a loop of these vectorises with AVX2 too, which
   converts no 64-bit integers to doubles */
static inline __attribute__((always_inline)) double fast_log2(double x)
{
    uint64_t u;
    memcpy(&u, &x, sizeof u);
    /* m > sqrt(2) (the double 0x3FF6A09E667F3BCD) where the mantissa's bits exceed 0x6A09E667F3BCD; then m / 2
       is the exponent 1022 and the exponent one more, all in integer operations (float selects made GCC
       compute both arms of what follows, see bin_index_f32) */
    const uint64_t mant = u & 0x000FFFFFFFFFFFFFULL;
    const uint64_t big = mant > 0x0006A09E667F3BCDULL;
    uint64_t eu = ((u >> 52) + big) | 0x4330000000000000ULL;      /* 2^52 + the biased exponent (+ 1) */
    uint64_t mu = mant | (0x3FF0000000000000ULL - (big << 52));
    double ed, m;
    memcpy(&ed, &eu, sizeof ed);
    memcpy(&m, &mu, sizeof m);
    const double e = ed - 4503599627371519.0;   /* 2^52 + 1023 */
    const double s = (m - 1.0) / (m + 1.0), s2 = s * s;
    double t = (1.0 / 11.0) * s2 + 1.0 / 9.0;
    t = t * s2 + 1.0 / 7.0;
    t = t * s2 + 1.0 / 5.0;
    t = t * s2 + 1.0 / 3.0;
    t = t * s2 + 1.0;
    return e + 2.8853900817779268 * s * t;   /* 2 / ln 2 */
}

/* pass 1 of the binning: each mode's position x = bins_per_octave log2(K^T C K) on the bins' axis, then its
   lowest bin i = floor(x) - 1 and the weights of its four bins i .. i + 3: cubic Lagrange interpolation at x
   between them (w4: four arrays of n_single), so that a function cubic in log K^T C K over four bins is summed
   exactly. The basis comes as three arrays of doubles (P: kx^2, then 2 kx ky, then ky^2) and the bins are int32,
   so that the loops vectorise (AVX2 converts doubles to int32 only).
   Returns the lowest and highest bin; the DC mode (K = 0) gets the bin INT_MIN */
typedef int v8i __attribute__((vector_size(8 * sizeof(int)), aligned(sizeof(int))));

/* the lowest and highest of the bins idx[0 .. n - 1], the DC mode's INT_MIN left out of the lowest (INT_MAX,
   INT_MIN where none), eight at a time in vectors of int32 (vectorised as written: a scalar loop of these
   selects was not, and cost a quarter of the binning) */
static void bin_range(const int *restrict idx, Py_ssize_t n, int *lo_out, int *hi_out)
{
    v8i vlo, vhi, vmin, vmax;
    for (int t = 0; t < 8; t++) {
        vlo[t] = vmax[t] = INT_MAX;
        vhi[t] = vmin[t] = INT_MIN;
    }
    Py_ssize_t j = 0;
    for (; j + 8 <= n; j += 8) {
        v8i v;
        memcpy(&v, idx + j, sizeof v);
        const v8i dc = v == vmin;
        const v8i vv = (dc & vmax) | (~dc & v);
        const v8i m = vv < vlo, mh = v > vhi;
        vlo = (m & vv) | (~m & vlo);
        vhi = (mh & v) | (~mh & vhi);
    }
    int lo = INT_MAX, hi = INT_MIN;
    for (int t = 0; t < 8; t++) {
        lo = vlo[t] < lo ? vlo[t] : lo;
        hi = vhi[t] > hi ? vhi[t] : hi;
    }
    for (; j < n; j++) {
        const int i = idx[j], v = i == INT_MIN ? INT_MAX : i;
        lo = v < lo ? v : lo;
        hi = i > hi ? i : hi;
    }
    *lo_out = lo;
    *hi_out = hi;
}

/* bin_index's loops, with weights of type WT: double for the pairs of binned_sums, float for make_bins' sums
   (float32) where AVX2 is not there to take the logarithm in float32 too (bin_index_f32). xs: n_single doubles */
#define BIN_INDEX_DOUBLE(WT)                                                                                  \
    const double *restrict P0 = P, *restrict P1 = P + n_single, *restrict P2 = P + 2 * n_single;            \
    for (Py_ssize_t j = 0; j < n_single; j++) {                                                              \
        double k = a0 * P0[j] + a1 * P1[j] + a2 * P2[j];                                                    \
        double lg = fast_log2(k > 1e-300 ? k : 1.0) * nb;                                                    \
        xs[j] = k > 1e-300 ? lg : INFINITY;   /* +inf: the DC mode */                                       \
    }                                                                                                        \
    /* the weights and bins: a loop of selects that vectorises (a floating-point min/max in it would not) */ \
    for (Py_ssize_t j = 0; j < n_single; j++) {                                                              \
        int dc = !(xs[j] < INFINITY);                                                                        \
        double x = dc ? 0.0 : xs[j];                                                                         \
        double f = floor(x), t = x - f;                                                                      \
        double tp = t + 1.0, tm = t - 1.0, tm2 = t - 2.0;                                                    \
        w4[j] = (WT)(-t * tm * tm2 / 6.0);                                                                   \
        w4[n_single + j] = (WT)(tp * tm * tm2 / 2.0);                                                        \
        w4[2 * n_single + j] = (WT)(-tp * t * tm2 / 2.0);                                                    \
        w4[3 * n_single + j] = (WT)(tp * t * tm / 6.0);                                                      \
        int i = (int)f - 1;                                                                                  \
        idx[j] = dc ? INT_MIN : i;                                                                           \
    }                                                                                                        \
    int lo, hi;                                                                                              \
    bin_range(idx, n_single, &lo, &hi);                                                                      \
    *lo_out = lo != INT_MAX ? (long long)lo : LLONG_MAX;                                                     \
    *hi_out = hi != INT_MIN ? (long long)hi + 3 : LLONG_MIN;

static void bin_index(const double *restrict P, Py_ssize_t n_single, double a0, double a1, double a2, int nb,
                      double *restrict xs, int *restrict idx, double *restrict w4, long long *lo_out,
                      long long *hi_out)
{
    BIN_INDEX_DOUBLE(double)
}

/* bin_index for make_bins, whose sums are float32: K^T C K in doubles, then its logarithm and the weights in
   float32, eight modes a vector with AVX2. The position x = nb log2(K^T C K) is split into nb e (e the
   exponent, an integer: exact) and f = nb log2(m), m the mantissa in [sqrt(1/2), sqrt(2)), |f| <= nb / 2,
   whose floor and fraction float32 holds to 1e-6 of a bin (K^T C K to 5e-8 relative), below the float32
   rounding of the modes' weights themselves (6e-8) and far below the binning's own error. kf: scratch of
   n_single floats */
#if defined(__AVX2__)
static void bin_index_f32(const double *restrict P, Py_ssize_t n_single, double a0, double a1, double a2, int nb,
                          void *restrict scratch, int *restrict idx, float *restrict w4, long long *lo_out,
                          long long *hi_out)
{
    float *restrict kf = (float *)scratch;
    const double *restrict P0 = P, *restrict P1 = P + n_single, *restrict P2 = P + 2 * n_single;
    for (Py_ssize_t j = 0; j < n_single; j++) {
        double k = a0 * P0[j] + a1 * P1[j] + a2 * P2[j];
        kf[j] = k > 1e-300 ? (float)k : -1.0f;   /* -1: the DC mode */
    }
    const float nbf = (float)nb, c = (float)(2.0 / M_LN2);
    for (Py_ssize_t j = 0; j < n_single; j++) {
        const float k = kf[j];
        const int dc = !(k > 0.0f);
        uint32_t u;
        memcpy(&u, &k, sizeof u);
        u = dc ? 0x3F800000u : u;   /* the DC mode: 1 */
        /* the mantissa m in [sqrt(1/2), sqrt(2)) and its exponent, in integer operations: m > sqrt(2) (the
           float 0x3FB504F3) where its bits exceed 0x3504F3, and then m / 2 is the exponent 126. Written as
           float selects (m = big ? m / 2 : m), GCC made both arms of everything after them and blended the
           results: twice the work */
        const uint32_t mant = u & 0x007FFFFFu;
        const uint32_t big = mant > 0x003504F3u;
        const int32_t e = (int32_t)(u >> 23) - 127 + (int32_t)big;
        const uint32_t mu = mant | (0x3F800000u - (big << 23));
        float m;
        memcpy(&m, &mu, sizeof m);
        const float s = (m - 1.0f) / (m + 1.0f), s2 = s * s;
        float p = (1.0f / 9.0f) * s2 + 1.0f / 7.0f;
        p = p * s2 + 1.0f / 5.0f;
        p = p * s2 + 1.0f / 3.0f;
        p = p * s2 + 1.0f;
        const float f = nbf * (c * s * p);
        const float fl = floorf(f), t = f - fl;
        const float tp = t + 1.0f, tm = t - 1.0f, tm2 = t - 2.0f;
        w4[j] = -t * tm * tm2 * (1.0f / 6.0f);
        w4[n_single + j] = tp * tm * tm2 * 0.5f;
        w4[2 * n_single + j] = -tp * t * tm2 * 0.5f;
        w4[3 * n_single + j] = tp * t * tm * (1.0f / 6.0f);
        const int i = nb * (int)e + (int)fl - 1;
        idx[j] = dc ? INT_MIN : i;
    }
    int lo, hi;
    bin_range(idx, n_single, &lo, &hi);
    *lo_out = lo != INT_MAX ? (long long)lo : LLONG_MAX;
    *hi_out = hi != INT_MIN ? (long long)hi + 3 : LLONG_MIN;
}
#else
/* without AVX2 (the portable build: SSE2 has no vector floor or float-to-int32 rounding for these loops) the
   float32 logarithm would run one mode at a time: bin_index's doubles, the weights stored as float32 */
static void bin_index_f32(const double *restrict P, Py_ssize_t n_single, double a0, double a1, double a2, int nb,
                          void *restrict scratch, int *restrict idx, float *restrict w4, long long *lo_out,
                          long long *hi_out)
{
    double *restrict xs = (double *)scratch;
    BIN_INDEX_DOUBLE(float)
}
#endif

/* pass 2: the modes' weights into rows of 8 floats (the six linear vectors, q, padding), a row a vector; the
   DC mode's into row nbin. Each mode's four rows are updated directly, without branches: the bins of one
   ellipticity fit in the first-level cache (an earlier version summed runs of modes with the same bins in
   registers first; its unpredictable branch cost more than the updates). The rows are summed in float32
   (one AVX2 vector a row, no conversion of the float32 weights): rounding within 1e-6 of the largest bin
   (tests/test_measure.py), within what benchmarks/speed.py --check bounds for the estimates.
   The modes come ordered by |K|, so consecutive modes mostly update the same four rows, and each update waited
   for the previous one's store: mode j goes to copy j % NACC of the rows (NACC copies of nbin + 1 rows, stride
   apart), and the copies are added at the end. The binning took 9 % less time on 47 calls of seven-exposure
   objects (AMD EPYC Zen 4, AVX2); the sums differ from one copy's by float32 rounding (1e-7 of the largest) */
typedef double v8u __attribute__((vector_size(8 * sizeof(double)), aligned(sizeof(double))));
typedef float v8fu __attribute__((vector_size(8 * sizeof(float)), aligned(sizeof(float))));

#define NACC 4

static inline void scatter_mode(const float *C8, Py_ssize_t n_single, const int *idx, const float *w4,
                                long long lo, Py_ssize_t nbin, float *A, Py_ssize_t j)
{
    const v8fu cv = *(const v8fu *)(C8 + 8 * j);
    const int i = idx[j];
    if (i == INT_MIN) {            /* the DC mode: one per object at most */
        *(v8f *)(A + 8 * nbin) += cv;
        return;
    }
    v8f *row = (v8f *)(A + 8 * (Py_ssize_t)(i - lo));
    row[0] += w4[j] * cv;
    row[1] += w4[n_single + j] * cv;
    row[2] += w4[2 * n_single + j] * cv;
    row[3] += w4[3 * n_single + j] * cv;
}

/* A: NACC copies of nbin + 1 rows, the first zero (or holding a polar grid's rows, polar_fill), the others zeroed
   here over their first nrows rows, which the modes reach (nbin + 1: every row, the DC mode's too); the sum is
   left in the first */
static void bin_scatter(const float *C8, Py_ssize_t n_single, const int *idx, const float *w4, long long lo,
                        Py_ssize_t nbin, Py_ssize_t nrows, float *A)
{
    const Py_ssize_t stride = 8 * (nbin + 1);
    for (int c = 1; c < NACC; c++) memset(A + c * stride, 0, nrows * 8 * sizeof(float));
    Py_ssize_t j = 0;
    for (; j + NACC <= n_single; j += NACC)
        for (int c = 0; c < NACC; c++) scatter_mode(C8, n_single, idx, w4, lo, nbin, A + c * stride, j + c);
    for (; j < n_single; j++) scatter_mode(C8, n_single, idx, w4, lo, nbin, A, j);
    for (int c = 1; c < NACC; c++) {
        v8f *dst = (v8f *)A;
        const v8f *src = (const v8f *)(A + c * stride);
        for (Py_ssize_t r = 0; r < nrows; r++) dst[r] += src[r];
    }
}

#define NCH 7      /* a bin's weights: the six linear vectors and q */
#define BPAD 8     /* bins per ellipticity padded to a multiple of this (one vector), with zero weights */

/*
 * The polar grid (issue 27): the modes spread once per object onto a grid uniform in u = nb log2 |K|^2 (a node
 * every POLAR_HU bins) and in psi = 2 phi (phi the direction of K; npsi nodes over 2 pi, periodic), by
 * Lagrange interpolation of six points in u and in psi. A model's K^T C K is |K|^2 A(psi), so a
 * node of the grid lies at u + nb log2 A(psi) on the bins' axis: every node of one psi column is moved by the
 * same amount, and the column is shared among the bins by the cubic sharing of make_bins with weights common to
 * the column. The modes' sums (any function of log K^T C K smooth on the nodes' scale) are then right to sixth
 * order in the nodes' spacing in u and in psi (and to the bins' fourth), and each ellipticity costs the grid's nodes (a few
 * thousand, whatever the number of exposures) instead of every mode, with no per-node position or weight.
 * The grid cannot follow a model of high |e|, whose A(psi) varies over an angle of order its axis ratio q:
 * make_bins bins such ellipticities mode by mode.
 */
#define POLAR_HU 2
#define POLAR_TU 6       /* points of the interpolation in u (nodes -2 .. 3 around a mode) */
#define POLAR_TPSI 6     /* and in psi */
#define POLAR_MARGIN 3   /* empty node rows below and above the modes' (the cubic sharing reaches one beyond) */

/* the weights of Lagrange interpolation at y in [0, 1) over the nodes -2 .. 3 */
static inline void lagrange6(double y, double *w)
{
    const double ym2 = y + 2.0, ym1 = y + 1.0, y1 = y - 1.0, y2 = y - 2.0, y3 = y - 3.0;
    w[0] = -ym1 * y * y1 * y2 * y3 / 120.0;
    w[1] = ym2 * y * y1 * y2 * y3 / 24.0;
    w[2] = -ym2 * ym1 * y1 * y2 * y3 / 12.0;
    w[3] = ym2 * ym1 * y * y2 * y3 / 12.0;
    w[4] = -ym2 * ym1 * y * y1 * y3 / 24.0;
    w[5] = ym2 * ym1 * y * y1 * y2 / 120.0;
}

/*
 * polar_grid(basis32, channels32, bins_per_octave, npsi[, versions[, node_modes]]) -> (u0, n_u, grid, dc, rows,
 * direct): the modes (basis32 and channels32 as make_bins') spread onto the grid; u0 the first node row's u (an
 * integer), grid float32 (versions, npsi, n_u, 8), dc float64 (versions, 8): the weights of the DC mode (K = 0),
 * which the grid leaves out, rows int32 (npsi, 2): each column's first and last row that a mode reached (first >
 * last: none), direct int32: the modes left off the grid, which make_bins bins one by one.
 * The modes are densest at high |K| (their number per octave of |K|^2 doubles from one octave to the next), while
 * every row of the grid costs npsi nodes: the lowest rows held some 25 modes for 80 nodes. node_modes (0: none)
 * is what binning one mode costs in nodes of the grid (likelihood.POLAR_MODE_NS / POLAR_NODE_NS); the modes of
 * the lowest rows are left off the grid, as many rows as save most by that cost.
 */
static PyObject *polar_grid(PyObject *self, PyObject *args)
{
    Py_buffer b3, c8;
    int nb, npsi, nv = 1;
    double node_modes = 0.0;
    if (!PyArg_ParseTuple(args, "y*y*ii|id", &b3, &c8, &nb, &npsi, &nv, &node_modes)) return NULL;
    const Py_ssize_t n = b3.len / (4 * (Py_ssize_t)sizeof(float));
    if (nv < 1 || c8.len != (Py_ssize_t)nv * 8 * n * (Py_ssize_t)sizeof(float) || nb < 1 || nb > 4096 ||
        npsi < POLAR_TPSI || npsi > 4096) {
        RELEASE(&b3, &c8);
        PyErr_SetString(PyExc_ValueError, "polar_grid: inconsistent buffers");
        return NULL;
    }
    const float *B = (const float *)b3.buf;
    const float *C = (const float *)c8.buf;
    Py_ssize_t ns = n > 0 ? n : 1;
    double *u = (double *)malloc(ns * sizeof(double)), *ps = (double *)malloc(ns * sizeof(double));
    double *dc = (double *)calloc(8 * (Py_ssize_t)nv, sizeof(double));
    int *rows = (int *)malloc(2 * (Py_ssize_t)npsi * sizeof(int));
    int *direct = (int *)malloc(ns * sizeof(int)), *rowof = (int *)malloc(ns * sizeof(int));
    Py_ssize_t *cum = NULL;
    Py_ssize_t nd = 0;
    float *G = NULL;
    int nomem = u == NULL || ps == NULL || dc == NULL || rows == NULL || direct == NULL || rowof == NULL;
    double umin = INFINITY, umax = -INFINITY;
    long long u0 = 0, n_u = 2 * POLAR_MARGIN + 4;
    Py_ssize_t colsz = 0, vsz = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; !nomem && j < n; j++) {
        const double a = B[4 * j], b = B[4 * j + 1], c = B[4 * j + 2], k2 = a + c;
        if (!(k2 > 0.0)) { u[j] = NAN; continue; }   /* the DC mode */
        u[j] = nb * log2(k2);
        ps[j] = atan2(b, a - c);   /* 2 phi: K^T C K = |K|^2 (mean + half (c2 cos psi + s2 sin psi)) */
        umin = u[j] < umin ? u[j] : umin;
        umax = u[j] > umax ? u[j] : umax;
    }
    /* the modes of the lowest rows (rows of POLAR_HU bins from the lowest mode) left off the grid: the number of
       rows r that saves most, npsi r nodes against node_modes nodes for each of their modes */
    if (!nomem && umin <= umax && node_modes > 0.0) {
        const Py_ssize_t nr = (Py_ssize_t)floor((umax - umin) / POLAR_HU) + 1;
        cum = (Py_ssize_t *)calloc(nr + 1, sizeof(Py_ssize_t));
        nomem = cum == NULL;
        for (Py_ssize_t j = 0; !nomem && j < n; j++) {
            if (u[j] != u[j]) continue;
            Py_ssize_t r = (Py_ssize_t)floor((u[j] - umin) / POLAR_HU);
            r = r < 0 ? 0 : (r >= nr ? nr - 1 : r);
            rowof[j] = (int)r;
            cum[r + 1]++;
        }
        double best = 0.0;
        Py_ssize_t rbest = 0;
        for (Py_ssize_t r = 1; !nomem && r <= nr; r++) cum[r] += cum[r - 1];
        for (Py_ssize_t r = 1; !nomem && r < nr; r++) {   /* (the grid keeps the top row's modes) */
            const double saving = (double)npsi * (double)r - node_modes * (double)cum[r];
            if (saving > best) {
                best = saving;
                rbest = r;
            }
        }
        if (!nomem && rbest > 0) {
            double gmin = INFINITY;
            for (Py_ssize_t j = 0; j < n; j++) {
                if (u[j] != u[j]) continue;
                if (rowof[j] < rbest) direct[nd++] = (int)j;
                else gmin = u[j] < gmin ? u[j] : gmin;
            }
            umin = gmin;
        }
    }
    if (!nomem && umin <= umax) {
        u0 = (long long)floor(umin) - POLAR_HU * (POLAR_MARGIN + 2);
        n_u = (long long)floor((umax - (double)u0) / POLAR_HU) + POLAR_MARGIN + 5;
    }
    colsz = 8 * (Py_ssize_t)n_u;
    vsz = colsz * npsi;
    if (!nomem) {
        G = (float *)calloc((size_t)(vsz * nv), sizeof(float));
        nomem = G == NULL;
    }
    for (int t = 0; t < npsi; t++) { rows[2 * t] = INT_MAX; rows[2 * t + 1] = INT_MIN; }
    for (Py_ssize_t j = 0, d = 0; !nomem && j < n; j++) {
        if (u[j] != u[j]) {
            for (int v = 0; v < nv; v++)
                for (int t = 0; t < 8; t++) dc[8 * v + t] += C[((Py_ssize_t)v * n + j) * 8 + t];
            continue;
        }
        if (d < nd && direct[d] == j) {   /* left off the grid */
            d++;
            continue;
        }
        const double tu = (u[j] - (double)u0) / POLAR_HU, fu = floor(tu);
        double wd[POLAR_TU], wp[POLAR_TPSI];
        lagrange6(tu - fu, wd);
        float wu[POLAR_TU];
        for (int r = 0; r < POLAR_TU; r++) wu[r] = (float)wd[r];
        const int iu = (int)fu - 2;
        const double tp = ps[j] / (2.0 * M_PI) * npsi;
        const double fp = floor(tp);
        lagrange6(tp - fp, wp);
        int col = ((int)fp - 2) % npsi;
        col = col < 0 ? col + npsi : col;
        for (int a = 0; a < POLAR_TPSI; a++, col = col + 1 == npsi ? 0 : col + 1) {
            rows[2 * col] = iu < rows[2 * col] ? iu : rows[2 * col];
            rows[2 * col + 1] = iu + POLAR_TU - 1 > rows[2 * col + 1] ? iu + POLAR_TU - 1 : rows[2 * col + 1];
            const float wa = (float)wp[a];
            for (int v = 0; v < nv; v++) {
                const v8fu cv = *(const v8fu *)(C + ((Py_ssize_t)v * n + j) * 8) * wa;
                v8fu *g = (v8fu *)(G + v * vsz + col * colsz + 8 * (Py_ssize_t)iu);
                for (int r = 0; r < POLAR_TU; r++) g[r] += wu[r] * cv;
            }
        }
    }
    Py_END_ALLOW_THREADS
    PyObject *res = NULL;
    if (!nomem) {
        PyObject *g = PyBytes_FromStringAndSize((const char *)G, vsz * nv * (Py_ssize_t)sizeof(float));
        PyObject *d = PyBytes_FromStringAndSize((const char *)dc, 8 * (Py_ssize_t)nv * sizeof(double));
        PyObject *r = PyBytes_FromStringAndSize((const char *)rows, 2 * (Py_ssize_t)npsi * sizeof(int));
        PyObject *o = PyBytes_FromStringAndSize((const char *)direct, nd * (Py_ssize_t)sizeof(int));
        if (g && d && r && o) res = Py_BuildValue("LLOOOO", u0, n_u, g, d, r, o);
        Py_XDECREF(g);
        Py_XDECREF(d);
        Py_XDECREF(r);
        Py_XDECREF(o);
    }
    free(u); free(ps); free(dc); free(rows); free(G); free(direct); free(rowof); free(cum);
    RELEASE(&b3, &c8);
    if (nomem) return PyErr_NoMemory();
    return res;
}

/* one ellipticity's placement of the polar grid's columns: per column its base (the bin of node row 0's
   floor) and four weights; returns the lowest and highest bin reached (LLONG_MAX, LLONG_MIN: none) */
static void polar_place(double a0, double a1, double a2, int nb, long long u0, int npsi, const int *rows,
                        const double *cs, long long *base, float *w4, long long *lo_out, long long *hi_out)
{
    long long lo = LLONG_MAX, hi = LLONG_MIN;
    const double mean = 0.5 * (a0 + a2), hc = 0.5 * (a0 - a2);
    for (int j = 0; j < npsi; j++) {
        const double A = mean + hc * cs[2 * j] + a1 * cs[2 * j + 1];   /* cos, sin of psi_j = 2 pi j / npsi */
        const double s = nb * fast_log2(A), fs = floor(s), t = s - fs;
        const double tp = t + 1.0, tm = t - 1.0, tm2 = t - 2.0;
        w4[4 * j] = (float)(-t * tm * tm2 / 6.0);
        w4[4 * j + 1] = (float)(tp * tm * tm2 / 2.0);
        w4[4 * j + 2] = (float)(-tp * t * tm2 / 2.0);
        w4[4 * j + 3] = (float)(tp * t * tm / 6.0);
        base[j] = u0 + (long long)fs;
        if (rows[2 * j] > rows[2 * j + 1]) continue;
        const long long a = base[j] + POLAR_HU * (long long)(rows[2 * j] - 1);
        const long long b = base[j] + POLAR_HU * (long long)(rows[2 * j + 1] + 1) + 1;
        lo = a < lo ? a : lo;
        hi = b > hi ? b : hi;
    }
    *lo_out = lo;
    *hi_out = hi;
}

/* the polar grid of one version (G: npsi columns of n_u rows of 8 floats) into the rows A (nbin + 1, zero; the
   DC mode's weights into row nbin). Node m of a column sits at bin base + 2 m (+ the column's fraction) and
   shares itself among bins base + 2m - 1 .. base + 2m + 2 (weights w0 .. w3), so bin base + 2m takes w1 G[m] +
   w3 G[m - 1] and bin base + 2m + 1 takes w2 G[m] + w0 G[m + 1]: two rows written per node, none twice in a
   row */
static void polar_fill(const float *G, long long n_u, int npsi, const int *rows, const long long *base,
                       const float *w4, const double *dcw, long long lo, Py_ssize_t nbin, float *A)
{
    const Py_ssize_t colsz = 8 * (Py_ssize_t)n_u;
    for (int j = 0; j < npsi; j++) {
        if (rows[2 * j] > rows[2 * j + 1]) continue;
        const v8f *g = (const v8f *)(G + j * colsz);
        const float w0 = w4[4 * j], w1 = w4[4 * j + 1], w2 = w4[4 * j + 2], w3 = w4[4 * j + 3];
        const long long mlo = rows[2 * j] - 1, mhi = rows[2 * j + 1] + 1;
        v8f *out = (v8f *)(A + 8 * (Py_ssize_t)(base[j] + POLAR_HU * mlo - lo));
        for (long long m = mlo; m <= mhi; m++, out += 2) {
            const v8f gm = g[m], gl = g[m - 1], gh = g[m + 1];
            out[0] += w1 * gm + w3 * gl;
            out[1] += w2 * gm + w0 * gh;
        }
    }
    for (int t = 0; t < 8; t++) A[8 * nbin + t] += (float)dcw[t];
}

/* the rows of 8 floats (bins 0 .. nbin - 1; A 64-byte aligned) as NCH columns of npad doubles, zero from nbin:
   eight bins at a time, each channel's eight values gathered from the eight rows in registers (a loop per
   channel over the rows read each row seven times, one float at a time) */
typedef double v8du __attribute__((vector_size(8 * sizeof(double)), aligned(sizeof(double))));
static void rows_to_columns(const float *A, Py_ssize_t nbin, Py_ssize_t npad, double *blk)
{
    Py_ssize_t b = 0;
    for (; b + 8 <= nbin; b += 8) {
        const v8f *r = (const v8f *)(A + 8 * b);
        const v8f r0 = r[0], r1 = r[1], r2 = r[2], r3 = r[3], r4 = r[4], r5 = r[5], r6 = r[6], r7 = r[7];
        for (int t = 0; t < NCH; t++) {
            const v8f c = {r0[t], r1[t], r2[t], r3[t], r4[t], r5[t], r6[t], r7[t]};
            *(v8du *)(blk + t * npad + b) = __builtin_convertvector(c, v8du);
        }
    }
    for (int t = 0; t < NCH; t++) {
        double *ch = blk + t * npad;
        for (Py_ssize_t k = b; k < nbin; k++) ch[k] = A[8 * k + t];
        for (Py_ssize_t k = nbin; k < npad; k++) ch[k] = 0.0;
    }
}

/*
 * make_bins(shape, basis32, channels32, bins_per_octave[, versions]) -> (lo, offsets, columns, dc): for
 * each ellipticity e (its shape coefficients c11, c12, c22), its bins lo[e] .. lo[e] + n - 1 (kappa_b =
 * 2^(b / nb)), every bin from the lowest to the highest a mode reached, padded with empty bins to a
 * multiple of BPAD: n = offsets[e + 1] - offsets[e]. Their weights are in columns, channel after channel
 * (NCH channels of n doubles from NCH offsets[e]); the DC bin's weights in dc[8 e .. 8 e + 6].
 * With versions = V > 1, channels32 holds V sets of the modes' weights one after the other (versions of one
 * object on the same modes: metacal's), and every output has an entry per ellipticity and version, e V + v
 * (the ellipticity's bin positions and weights found once, then each version's weights scattered with
 * them: the same numbers as V calls). Every output is bytes (int64 and float64).
 */
static PyObject *make_bins(PyObject *self, PyObject *args)
{
    Py_buffer shape, b3, c8, pg = {0}, pdc = {0}, prw = {0}, pdir = {0}, outb = {0};
    int nb, nv = 1, npsi = 0;
    long long pu0 = 0, pnu = 0;
    double q2min = 2.0;   /* the polar grid for ellipticities whose q^2 is at least this (2: none) */
    PyObject *polar_obj = Py_None, *out_obj = Py_None;
    if (!PyArg_ParseTuple(args, "y*y*y*i|iOO", &shape, &b3, &c8, &nb, &nv, &polar_obj, &out_obj)) return NULL;
    /* (the polar tuple's buffers parsed by a call of their own: PyArg_ParseTuple sizes its list of buffers to
       release by the format's top-level items, which a nested tuple of them overruns) */
    if (polar_obj != Py_None && !PyArg_ParseTuple(polar_obj, "LLy*y*y*y*id", &pu0, &pnu, &pg, &pdc, &prw, &pdir,
                                                  &npsi, &q2min)) {
        RELEASE(&shape, &b3, &c8);
        return NULL;
    }
    /* out: where the columns are written while they fit (a float64 buffer the caller keeps and passes again, whose
       memory is already mapped: fresh memory for them, its pages faulted in at every call, cost a quarter of the
       binning); the columns returned are then None, the first NCH offsets[-1] doubles of out */
    if (out_obj != Py_None && PyObject_GetBuffer(out_obj, &outb, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) != 0) {
        RELEASE(&shape, &b3, &c8, &pg, &pdc, &prw, &pdir);
        return NULL;
    }
    Py_ssize_t n_e = shape.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t n_single = b3.len / (4 * (Py_ssize_t)sizeof(float));
    const int polar = npsi > 0;
    if (nv < 1 || c8.len != (Py_ssize_t)nv * 8 * n_single * (Py_ssize_t)sizeof(float) || nb < 1 || nb > 4096 ||
        (polar && (pnu < 2 * POLAR_MARGIN + 4 || pg.len != (Py_ssize_t)nv * npsi * pnu * 8 * (Py_ssize_t)sizeof(float)
                   || pdc.len != (Py_ssize_t)nv * 8 * (Py_ssize_t)sizeof(double)
                   || prw.len != 2 * (Py_ssize_t)npsi * (Py_ssize_t)sizeof(int)
                   || pdir.len % (Py_ssize_t)sizeof(int) != 0))) {
        RELEASE(&shape, &b3, &c8, &pg, &pdc, &prw, &pdir, &outb);
        PyErr_SetString(PyExc_ValueError, "make_bins: inconsistent buffers");
        return NULL;
    }
    const double *S = (const double *)shape.buf;
    /* the modes the polar grid leaves off (polar_grid's direct), binned one by one */
    const Py_ssize_t nd = polar ? pdir.len / (Py_ssize_t)sizeof(int) : 0;
    const int *DIR = (const int *)pdir.buf;
    for (Py_ssize_t d = 0; d < nd; d++)
        if (DIR[d] < 0 || DIR[d] >= n_single) {
            RELEASE(&shape, &b3, &c8, &pg, &pdc, &prw, &pdir, &outb);
            PyErr_SetString(PyExc_ValueError, "make_bins: the polar grid's direct modes are not the modes'");
            return NULL;
        }
    Py_ssize_t ns = n_single > 0 ? n_single : 1;
    int *idx = (int *)malloc(ns * sizeof(int));
    double *Pd = (double *)malloc(3 * (nd > 0 ? nd : 1) * sizeof(double));
    float *Cd = (float *)malloc(8 * nv * (nd > 0 ? nd : 1) * sizeof(float));
    for (Py_ssize_t d = 0; Pd != NULL && Cd != NULL && d < nd; d++) {
        for (int t = 0; t < 3; t++) Pd[t * nd + d] = ((const float *)b3.buf)[4 * (Py_ssize_t)DIR[d] + t];
        for (int v = 0; v < nv; v++)
            memcpy(Cd + 8 * ((Py_ssize_t)v * nd + d), (const float *)c8.buf + 8 * ((Py_ssize_t)v * n_single + DIR[d]),
                   8 * sizeof(float));
    }
    long long *pbase = (long long *)malloc((npsi > 0 ? npsi : 1) * sizeof(long long));
    float *pw4 = (float *)malloc(4 * (npsi > 0 ? npsi : 1) * sizeof(float));
    double *pcs = (double *)malloc(2 * (npsi > 0 ? npsi : 1) * sizeof(double));
    /* the grid on 64-byte boundaries (likelihood.polar_grid keeps it so), else copied there: a bytes object's
       data lie 16 bytes off, and half its rows' loads then straddled two cache lines */
    float *pga = NULL, *pgown = NULL;
    if (polar) {
        if (((uintptr_t)pg.buf & 63) == 0)
            pga = (float *)pg.buf;
        else {
            void *pa = NULL;
            pga = pgown = posix_memalign(&pa, 64, pg.len > 0 ? pg.len : 64) == 0 ? (float *)pa : NULL;
            if (pga != NULL) memcpy(pga, pg.buf, pg.len);
        }
    }
    for (int j = 0; pcs != NULL && j < npsi; j++) {
        pcs[2 * j] = cos(2.0 * M_PI * j / npsi);
        pcs[2 * j + 1] = sin(2.0 * M_PI * j / npsi);
    }
    double *frac = (double *)malloc(ns * sizeof(double));   /* scratch: each mode's K^T C K or position */
    float *w4 = (float *)malloc(4 * ns * sizeof(float));      /* its four weights */
    const Py_ssize_t n_out = n_e * nv;   /* entries: ellipticity e, version v at e nv + v */
    long long *off = (long long *)malloc((n_out + 1) * sizeof(long long));
    long long *los = (long long *)malloc((n_out > 0 ? n_out : 1) * sizeof(long long));
    double *dc = (double *)calloc(8 * (n_out > 0 ? n_out : 1), sizeof(double));
    float *A = NULL;
    double *cols = NULL;
    Py_ssize_t capA = 0, capC = 0, ncol = 0;
    int nomem = (idx == NULL || Pd == NULL || Cd == NULL || frac == NULL || w4 == NULL || off == NULL || los == NULL || dc == NULL ||
                 pbase == NULL || pw4 == NULL || pcs == NULL || (polar && pga == NULL));
    int own_cols = 0;   /* cols is memory of their own (malloc), not colobj's */

    /* the columns are written straight into the bytes returned, sized from above and shrunk at the end (a
       copy of them was a few per cent of the binning): per ellipticity, its bins span at most nb log2 of the shape
       matrix's eigenvalues' ratio times the modes' |K|^2 range, plus the cubic sharing's 3 and rounding's
       margin. Where that bound cannot be made (no modes, a shape matrix not positive definite), or proves too
       small, the columns grow in memory of their own and are copied */
    PyObject *colobj = NULL;
    {
        double k2min = INFINITY, k2max = 0.0;
        for (Py_ssize_t j = 0; j < n_single; j++) {
            const float *q = (const float *)b3.buf + 4 * j;
            const double k2 = (double)q[0] + (double)q[2];
            k2min = k2 > 0.0 && k2 < k2min ? k2 : k2min;
            k2max = k2 > k2max ? k2 : k2max;
        }
        double total = 0.0;
        int bounded = !nomem && k2max > 0.0 && isfinite(k2max);
        for (Py_ssize_t e = 0; bounded && e < n_e; e++) {
            const double a0 = S[3 * e], a1 = S[3 * e + 1], a2 = S[3 * e + 2];
            const double hm = 0.5 * (a0 + a2), hd = sqrt(0.25 * (a0 - a2) * (a0 - a2) + a1 * a1);
            /* (the polar grid's columns reach a few node rows beyond the modes) */
            const double span = nb * (log2((hm + hd) * k2max) - log2((hm - hd) * k2min)) +
                                (polar ? 2 * POLAR_HU * (POLAR_MARGIN + 3) : 0);
            bounded = hm - hd > 0.0 && isfinite(span) && span < 1e6;
            total += (double)((((Py_ssize_t)ceil(span) + 8 + BPAD - 1) / BPAD) * BPAD) * nv;
        }
        if (outb.buf != NULL) {   /* the caller's memory */
            cols = (double *)outb.buf;
            capC = outb.len / (Py_ssize_t)sizeof(double);
        } else if (bounded && NCH * total * sizeof(double) < 1e9) {
            colobj = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)(NCH * total) * (Py_ssize_t)sizeof(double));
            if (colobj == NULL) PyErr_Clear();   /* then the columns' own memory */
            else {
                cols = (double *)PyBytes_AS_STRING(colobj);
                capC = NCH * (Py_ssize_t)total;
            }
        }
    }

    /* the modes' basis as three arrays of doubles, for loops that vectorise */
    double *P = (double *)malloc(3 * ns * sizeof(double));
    nomem |= P == NULL;
    int have_P = 0;   /* made at the first ellipticity binned mode by mode (none where the polar grid takes all) */
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t e = 0; !nomem && e < n_e; e++) {
        const double a0 = S[3 * e], a1 = S[3 * e + 1], a2 = S[3 * e + 2];
        long long lo, hi;
        const double hm = 0.5 * (a0 + a2), hd = sqrt(0.25 * (a0 - a2) * (a0 - a2) + a1 * a1);
        /* q^2: the ratio of the shape matrix's eigenvalues */
        const int use_polar = polar && hm - hd >= q2min * (hm + hd);
        long long dlo = LLONG_MAX, dhi = LLONG_MIN;
        if (use_polar) {
            polar_place(a0, a1, a2, nb, pu0, npsi, (const int *)prw.buf, pcs, pbase, pw4, &lo, &hi);
            if (nd > 0) {
                bin_index_f32(Pd, nd, a0, a1, a2, nb, frac, idx, w4, &dlo, &dhi);
                lo = dlo < lo ? dlo : lo;
                hi = dhi > hi ? dhi : hi;
            }
        } else {
            if (!have_P) {
                for (Py_ssize_t j = 0; j < n_single; j++)
                    for (int t = 0; t < 3; t++) P[t * n_single + j] = ((const float *)b3.buf)[4 * j + t];
                have_P = 1;
            }
            bin_index_f32(P, n_single, a0, a1, a2, nb, frac, idx, w4, &lo, &hi);
        }
        Py_ssize_t nbin = hi >= lo ? (Py_ssize_t)(hi - lo) + 1 : 0;
        Py_ssize_t npad = (nbin + BPAD - 1) / BPAD * BPAD;
        if (NACC * (nbin + 1) > capA) {
            free(A);
            capA = 2 * NACC * (nbin + 1);
            /* rows of 8 doubles on 64-byte boundaries: each row's update is one aligned vector */
            void *pa = NULL;
            A = posix_memalign(&pa, 64, capA * 8 * sizeof(float)) == 0 ? (float *)pa : NULL;
            if (A == NULL) { nomem = 1; break; }
        }
        for (int v = 0; v < nv; v++) {
            const Py_ssize_t ev = e * nv + v;
            memset(A, 0, (nbin + 1) * 8 * sizeof(float));
            if (use_polar) {
                polar_fill(pga + (Py_ssize_t)v * npsi * pnu * 8, pnu, npsi, (const int *)prw.buf,
                           pbase, pw4, (const double *)pdc.buf + 8 * v, lo, nbin, A);
                if (dhi >= dlo)   /* the modes left off the grid, into its rows */
                    bin_scatter(Cd + 8 * (Py_ssize_t)v * nd, nd, idx, w4, lo, nbin, (Py_ssize_t)(dhi - lo) + 1, A);
            } else
                bin_scatter((const float *)c8.buf + (Py_ssize_t)v * 8 * n_single, n_single, idx, w4, lo, nbin,
                            nbin + 1, A);
            if (NCH * (ncol + npad) > capC) {
                capC = 2 * NCH * (ncol + npad);
                double *r;
                if (!own_cols && cols != NULL) {   /* the bound or out fell short: memory of their own from here on */
                    r = (double *)malloc(capC * sizeof(double));
                    if (r != NULL) memcpy(r, cols, NCH * ncol * sizeof(double));
                } else
                    r = (double *)realloc(cols, capC * sizeof(double));
                if (r == NULL) { nomem = 1; break; }
                cols = r;
                own_cols = 1;
            }
            off[ev] = ncol;
            los[ev] = nbin > 0 ? lo : 0;
            double *blk = cols + NCH * ncol;
            rows_to_columns(A, nbin, npad, blk);
            for (int t = 0; t < NCH; t++) dc[8 * ev + t] = A[8 * nbin + t];
            ncol += npad;
        }
    }
    off[n_out] = ncol;
    Py_END_ALLOW_THREADS

    PyObject *res = NULL;
    if (!nomem) {
        PyObject *l = PyBytes_FromStringAndSize((const char *)los, n_out * sizeof(long long));
        PyObject *o = PyBytes_FromStringAndSize((const char *)off, (n_out + 1) * sizeof(long long));
        PyObject *c;
        if (!own_cols && outb.buf != NULL) {
            c = Py_None;   /* in out */
            Py_INCREF(c);
        } else if (!own_cols && colobj != NULL) {
            c = colobj;   /* the reference passes to the result */
            colobj = NULL;
            if (_PyBytes_Resize(&c, NCH * ncol * (Py_ssize_t)sizeof(double)) != 0) c = NULL;
        } else
            c = PyBytes_FromStringAndSize((const char *)cols, NCH * ncol * sizeof(double));
        PyObject *d = PyBytes_FromStringAndSize((const char *)dc, 8 * n_out * sizeof(double));
        if (l && o && c && d) res = PyTuple_Pack(4, l, o, c, d);
        Py_XDECREF(l);
        Py_XDECREF(o);
        Py_XDECREF(c);
        Py_XDECREF(d);
    }
    free(P); free(Pd); free(Cd); free(idx); free(frac); free(w4); free(off); free(los); free(dc); free(A); free(pbase); free(pw4); free(pcs); free(pgown);
    if (own_cols) free(cols);
    Py_XDECREF(colobj);
    RELEASE(&shape, &b3, &c8, &pg, &pdc, &prw, &pdir, &outb);
    if (nomem) return PyErr_NoMemory();
    return res;
}

/* the transform at the n (padded: npad) bins of a model whose bin 0 lies at position pos of the log table
   (G2: rows of J points, row s holding the table's points s, s + M, s + 2M, ...; M + 1 rows): bins below
   the table get low (the transform at its start, where it is flat), bins beyond it 0; pos = -inf (r = 0)
   gives every bin zero_val, the transform at rho = 0, and a NaN (r NaN) NaN */
/* where a model whose bin 0 lies at position pos of the log table reads it (G2 as log_table_row's): rows A and
   B (bin b interpolated as A[b] + f (B[b] - A[b])), the bins within the table blo .. bhi - 1 of n; 0, or -1 for
   pos = -inf (r = 0) or NaN, which read no row */
static inline __attribute__((always_inline)) int table_rows(const double *G2, Py_ssize_t M, Py_ssize_t J, double pos,
                                                            Py_ssize_t n, const double **A, const double **B,
                                                            double *f, Py_ssize_t *blo_out, Py_ssize_t *bhi_out)
{
    if (!(pos > -1e15)) return -1;
    if (pos > 1e15) pos = 1e15;
    const double fl = floor(pos);
    *f = pos - fl;
    const long long i0 = (long long)fl;
    long long s = i0 % (long long)M;
    if (s < 0) s += M;
    const long long j0 = (i0 - s) / (long long)M;
    long long blo = -j0, bhi = (long long)J - j0;
    blo = blo < 0 ? 0 : (blo > n ? n : blo);
    bhi = bhi < blo ? blo : (bhi > n ? n : bhi);
    *A = G2 + s * J + j0;
    *B = G2 + (s + 1) * J + j0;
    *blo_out = (Py_ssize_t)blo;
    *bhi_out = (Py_ssize_t)bhi;
    return 0;
}

/* the transform at the n (padded: npad) bins of a model whose bin 0 lies at position pos of the log table
   (G2: rows of J points, row s holding the table's points s, s + M, s + 2M, ...; M + 1 rows): bins below
   the table get low (the transform at its start, where it is flat), bins beyond it 0; pos = -inf (r = 0)
   gives every bin zero_val, the transform at rho = 0, and a NaN (r NaN) NaN */
static inline __attribute__((always_inline)) void log_table_row(
    const double *G2, Py_ssize_t M, Py_ssize_t J, double pos, Py_ssize_t n, Py_ssize_t npad, double low,
    double zero_val, double *restrict R)
{
    const double *A, *B;
    double f;
    Py_ssize_t blo, bhi;
    if (table_rows(G2, M, J, pos, n, &A, &B, &f, &blo, &bhi) != 0) {
        const double v = pos != pos ? pos : zero_val;
        for (Py_ssize_t b = 0; b < n; b++) R[b] = v;
        for (Py_ssize_t b = n; b < npad; b++) R[b] = 0.0;
        return;
    }
    for (Py_ssize_t b = 0; b < blo; b++) R[b] = low;
    for (Py_ssize_t b = blo; b < bhi; b++) R[b] = A[b] + f * (B[b] - A[b]);
    for (Py_ssize_t b = bhi; b < npad; b++) R[b] = 0.0;
}

/* the sums of one model from its ellipticity's bins (W: NCH channels of npad), transforms rf, rg there, and
   the DC bin (dcw, at the transforms' values at 0, r0f and r0g): the output row o of NOUT, as block_body's.
   The fifteen sums in one pass would spill AVX2's 16 vector registers to memory at every step, so they run in two
   passes (the disk's six linear sums, ff and fg; then the bulge's and gg) of four-double accumulators: at most nine
   live vectors each. (With AVX-512, these two passes with the transforms interpolated in them ran x1.03 faster
   than one pass of eight-double accumulators over the transforms written out, session 80: the AVX-512 build runs
   them too.)
   sums_core's ROWS = 1 takes the transforms from the log tables' rows instead (table_rows': rf, bf with the
   fraction tf; rg, bg with tg), interpolated in the loop as log_table_row interpolates them, where every bin lies
   within both tables: the same numbers, without writing the transforms out and reading them back (which took a
   quarter of the binned sums' time) */
#define TRANSFORM(V, X, Y, T, K) do {                                                                          \
        V = *(const VT *)((X) + (K));                                                                        \
        if (ROWS) V = V + (T) * (*(const VT *)((Y) + (K)) - V);                                             \
    } while (0)
typedef double v4u __attribute__((vector_size(4 * sizeof(double)), aligned(sizeof(double))));
#define VT v4u

static inline double hsum4(v4u v)
{
    return (v[0] + v[2]) + (v[1] + v[3]);
}

static inline __attribute__((always_inline)) void sums_core(
    const int ROWS, const int LIN, const double *restrict W, Py_ssize_t npad, const double *restrict rf,
    const double *restrict bf, double tf, const double *restrict rg, const double *restrict bg, double tg,
    const double *dcw, double r0f, double r0g, double *o)
{
    const v4u zero = {0};
    v4u l[6], a = zero, b = zero;
    const double *Q = W + 6 * npad;
    /* pass 1: the disk's linear sums, ff and fg (LIN: the linear sums alone) */
    for (int t = 0; t < 6; t++) l[t] = zero;
    for (Py_ssize_t k = 0; k < npad; k += 4) {
        v4u vf;
        TRANSFORM(vf, rf, bf, tf, k);
        for (int t = 0; t < 6; t++) l[t] += vf * *(const v4u *)(W + t * npad + k);
        if (!LIN) {
            v4u vg;
            TRANSFORM(vg, rg, bg, tg, k);
            v4u qf = *(const v4u *)(Q + k) * vf;
            a += qf * vf;
            b += qf * vg;
        }
    }
    for (int t = 0; t < 6; t++) o[t] = hsum4(l[t]) + r0f * dcw[t];
    if (!LIN) {
        o[12] = hsum4(a) + dcw[6] * r0f * r0f;
        o[14] = hsum4(b) + dcw[6] * r0f * r0g;
    }
    /* pass 2: the bulge's linear sums and gg */
    for (int t = 0; t < 6; t++) l[t] = zero;
    a = zero;
    for (Py_ssize_t k = 0; k < npad; k += 4) {
        v4u vg;
        TRANSFORM(vg, rg, bg, tg, k);
        for (int t = 0; t < 6; t++) l[t] += vg * *(const v4u *)(W + t * npad + k);
        if (!LIN) a += *(const v4u *)(Q + k) * vg * vg;
    }
    for (int t = 0; t < 6; t++) o[6 + t] = hsum4(l[t]) + r0g * dcw[t];
    if (!LIN) o[13] = hsum4(a) + dcw[6] * r0g * r0g;
}
#undef TRANSFORM
#undef VT

#if defined(__AVX2__)
#define ROWS_IN_SUMS 1
#else
#define ROWS_IN_SUMS 0
#endif

/* sums_core from the bins' transforms written out (rf, rg) or from the tables' rows; LIN: the linear sums alone (o[12 ..
   14] left as they are: a version whose quadratic sums are another's, size_nodes_versions) */
static inline __attribute__((always_inline)) void sums_from_bins(
    const int LIN, const double *restrict W, Py_ssize_t npad, const double *restrict rf, const double *restrict rg,
    const double *dcw, double r0f, double r0g, double *o)
{
    sums_core(0, LIN, W, npad, rf, NULL, 0.0, rg, NULL, 0.0, dcw, r0f, r0g, o);
}

static inline __attribute__((always_inline)) void sums_from_rows(
    const int LIN, const double *restrict W, Py_ssize_t npad, const double *restrict af, const double *restrict bf,
    double tf, const double *restrict ag, const double *restrict bg, double tg, const double *dcw, double r0f,
    double r0g, double *o)
{
    sums_core(1, LIN, W, npad, af, bf, tf, ag, bg, tg, dcw, r0f, r0g, o);
}

/*
 * binned_sums(shape, r2, e_index, lo, offsets, columns, dc, bins_per_octave, log_f, log_g, M, J, start, per_octave,
 *             low_f, low_g, zero_f, zero_g, ratio2, pair_basis, pair_a, pair_b, pair_h, pair_tol, out):
 * the sums of models (r2 and the ellipticity e_index each, into shape and make_bins' outputs), from the bins of
 * their ellipticity on the log tables of the disk and bulge (log_f, log_g: M + 1 rows of J; point i of a table
 * at log2(rho^2) = start + i / per_octave). The bulge's rho^2 is ratio2 times the disk's.
 * The fold groups' cross terms: pairs (pair_a, pair_b: int64 into the pair modes, whose basis rows, as
 * make_bins', are pair_basis; pair_h: float64, the pair's 2 Re H_ab) add h R_a R_b to ff and gg and
 * h (R_a^f R_b^g + R_a^g R_b^f) / 2 to fg, with each mode's transforms interpolated from the bins' as the
 * binning shares it (bin_index, once per run of models with one ellipticity, in O(pair modes) memory). Their
 * modes' own terms (the linear vectors and the diagonal of Re H) are in the bins. pair_tol > 0: a model's pair
 * terms are left out where a bound on each of them (from its transforms at the pair modes' bins) is within
 * pair_tol (FitConfig.pair_chi2_tolerance over S^2: likelihood.join_exposures); 0 keeps them in every model.
 */
/* binned_sums' fold pairs of nk (<= PLB) models of one ellipticity: sum_k h_k R_a R_b over the pairs, added to
   each model's ff, gg and fg (O: rows of NOUT), each pair mode's transforms R interpolated from its four bins (PI:
   the first, PW: four arrays of weights; columns l of RFT, RGT: model kept[l]'s bins, rows of PLB) where its pair
   needs them (a mode of several pairs, once for each). The same arithmetic, in the same order, as one model at a
   time, the models in vectors of PLB (the unused columns hold earlier models' values, computed and left): no
   gathers, and no pass over the modes apart from the pairs' */
#define PLB 8
static inline __attribute__((always_inline)) void pair_mode(Py_ssize_t g, Py_ssize_t n_g, const int *restrict PI,
                                                             const double *restrict PW, const double *restrict RFT,
                                                             const double *restrict RGT, double *restrict pf,
                                                             double *restrict pg)
{
    const double *f = RFT + (Py_ssize_t)PI[g] * PLB, *r = RGT + (Py_ssize_t)PI[g] * PLB;
    const double w0 = PW[g], w1 = PW[n_g + g], w2 = PW[2 * n_g + g], w3 = PW[3 * n_g + g];
    for (int l = 0; l < PLB; l++) {
        pf[l] = w0 * f[l] + w1 * f[PLB + l] + w2 * f[2 * PLB + l] + w3 * f[3 * PLB + l];
        pg[l] = w0 * r[l] + w1 * r[PLB + l] + w2 * r[2 * PLB + l] + w3 * r[3 * PLB + l];
    }
}

static void pair_block(int nk, const Py_ssize_t *kept, Py_ssize_t n_g, Py_ssize_t n_pairs, const int *restrict PI,
                       const double *restrict PW, const long long *restrict PA, const long long *restrict PB,
                       const double *restrict PH, const double *restrict RFT, const double *restrict RGT, double *O)
{
    if (nk <= 0) return;
    double ff[PLB], gg[PLB], fg[PLB];
    for (int l = 0; l < PLB; l++) ff[l] = gg[l] = fg[l] = 0.0;
    for (Py_ssize_t k = 0; k < n_pairs; k++) {
        double fa[PLB], fb[PLB], ga[PLB], gb[PLB];
        pair_mode(PA[k], n_g, PI, PW, RFT, RGT, fa, ga);
        pair_mode(PB[k], n_g, PI, PW, RFT, RGT, fb, gb);
        const double h = PH[k];
        for (int l = 0; l < PLB; l++) {
            ff[l] += h * fa[l] * fb[l];
            gg[l] += h * ga[l] * gb[l];
            fg[l] += 0.5 * h * (fa[l] * gb[l] + ga[l] * fb[l]);
        }
    }
    for (int l = 0; l < nk; l++) {
        double *o = O + NOUT * kept[l];
        o[12] += ff[l];
        o[13] += gg[l];
        o[14] += fg[l];
    }
}

/* what binned_sums needs besides the models: an object's bins at a set of ellipticities (make_bins'), the log
   tables and the fold groups' pairs; checked once (bins_check) */
typedef struct {
    const double *S, *COLS, *DC, *GF, *GG, *PH;
    const long long *OFF, *LO, *PA, *PB;
    const float *PBS;
    Py_ssize_t n_e, n_cols, n_pairs, n_g, M, J, maxpad;
    double start, per_oct, low_f, low_g, zero_f, zero_g, ratio2, pair_tol;
    int nb;
} BinsCtx;

/* the buffers of a BinsCtx (shape, lo, offsets, columns, dc, log_f, log_g, pair_basis, pair_a, pair_b, pair_h),
   checked against each other: 0, or -1 with a ValueError set */
static int bins_check(BinsCtx *c, const Py_buffer *shape, const Py_buffer *lob, const Py_buffer *offb,
                      const Py_buffer *colb, const Py_buffer *dcb, const Py_buffer *gfb, const Py_buffer *ggb,
                      const Py_buffer *pbsb, const Py_buffer *pab, const Py_buffer *pbb, const Py_buffer *phb)
{
    c->n_e = shape->len / (3 * (Py_ssize_t)sizeof(double));
    c->n_cols = colb->len / (NCH * (Py_ssize_t)sizeof(double));
    c->n_pairs = phb->len / (Py_ssize_t)sizeof(double);
    c->n_g = pbsb->len / (4 * (Py_ssize_t)sizeof(float));
    c->S = (const double *)shape->buf;
    c->OFF = (const long long *)offb->buf;
    c->LO = (const long long *)lob->buf;
    c->PA = (const long long *)pab->buf;
    c->PB = (const long long *)pbb->buf;
    c->COLS = (const double *)colb->buf;
    c->DC = (const double *)dcb->buf;
    c->GF = (const double *)gfb->buf;
    c->GG = (const double *)ggb->buf;
    c->PH = (const double *)phb->buf;
    c->PBS = (const float *)pbsb->buf;
    const Py_ssize_t n_e = c->n_e;
    int bad = c->nb < 1 || c->M < 1 || c->J < 1
              || lob->len != n_e * (Py_ssize_t)sizeof(long long) || dcb->len != 8 * n_e * (Py_ssize_t)sizeof(double)
              || gfb->len != (c->M + 1) * c->J * (Py_ssize_t)sizeof(double) || ggb->len != gfb->len
              || offb->len != (n_e + 1) * (Py_ssize_t)sizeof(long long) || c->OFF[n_e] != c->n_cols
              || c->per_oct != (double)(c->nb * c->M) || pbsb->len != 4 * c->n_g * (Py_ssize_t)sizeof(float)
              || pab->len != c->n_pairs * (Py_ssize_t)sizeof(long long) || pbb->len != pab->len;
    for (Py_ssize_t e = 0; !bad && e < n_e; e++)
        bad = c->OFF[e] < 0 || c->OFF[e] > c->OFF[e + 1] || (c->OFF[e + 1] - c->OFF[e]) % BPAD != 0;
    for (Py_ssize_t k = 0; !bad && k < c->n_pairs; k++)
        bad = c->PA[k] < 0 || c->PA[k] >= c->n_g || c->PB[k] < 0 || c->PB[k] >= c->n_g;
    c->maxpad = 0;
    for (Py_ssize_t e = 0; !bad && e < n_e; e++)
        if (c->OFF[e + 1] - c->OFF[e] > c->maxpad) c->maxpad = (Py_ssize_t)(c->OFF[e + 1] - c->OFF[e]);
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "binned_sums: inconsistent buffers");
        return -1;
    }
    return 0;
}

/* the sums of n_models models (R2: r^2, E: the ellipticity of each, checked within the context's) into O (rows of
   NOUT); 0, or -1 where memory ran out. Runs without the GIL. */
static inline __attribute__((always_inline)) int binned_sums_impl(const BinsCtx *c, Py_ssize_t n_models,
                                                                  const long long *E, const double *R2, double *O,
                                                                  const int LIN)
{
    /* LIN: the linear sums alone (sums_from_rows'), no fold pairs */
    const Py_ssize_t n_pairs = LIN ? 0 : c->n_pairs, n_g = c->n_g, maxpad = c->maxpad, M = c->M, J = c->J;
    const long long *OFF = c->OFF, *LO = c->LO, *PA = c->PA, *PB = c->PB;
    const int nb = c->nb;
    double pair_tol = c->pair_tol;
    void *rbuf = NULL, *tbuf = NULL;
    const Py_ssize_t ng1 = n_g > 0 ? n_g : 1;
    /* the pair terms of up to PLB models of one ellipticity at a time: their bins' transforms (rows of PLB, the
       bins and the four entries after them), so that the interpolation and the pairs' products run over the models
       in vectors (pair_block) */
    const Py_ssize_t trows = maxpad + BPAD + 4;
    if (n_pairs > 0 && posix_memalign(&tbuf, 64, 2 * trows * PLB * sizeof(double)) != 0) return -1;
    double *RFT = NULL, *RGT = NULL;
    if (tbuf != NULL) {
        RFT = (double *)tbuf;
        RGT = RFT + trows * PLB;
        memset(tbuf, 0, 2 * trows * PLB * sizeof(double));
    }
    Py_ssize_t kept[PLB];
    int nk = 0;
    /* the bins' transforms; per pair mode its transforms, basis (3 arrays), position, bin and weights */
    if (posix_memalign(&rbuf, 64, (2 * (maxpad + BPAD) + 10 * ng1) * sizeof(double) + ng1 * sizeof(int)) != 0) {
        free(tbuf);
        return -1;
    }
    double *RF = (double *)rbuf, *RG = RF + maxpad + BPAD, *PF = RG + maxpad + BPAD, *PG = PF + ng1;
    double *PB3 = PG + ng1, *PX = PB3 + 3 * ng1, *PW = PX + ng1;
    int *PI = (int *)(PW + 4 * ng1);
    for (Py_ssize_t g = 0; g < n_g; g++)
        for (int t = 0; t < 3; t++) PB3[t * n_g + g] = c->PBS[4 * g + t];
    const double *S = c->S, *COLS = c->COLS, *DC = c->DC, *GF = c->GF, *GG = c->GG, *PH = c->PH;
    const double start = c->start, per_oct = c->per_oct, low_f = c->low_f, low_g = c->low_g;
    const double zero_f = c->zero_f, zero_g = c->zero_g;
    const int same = (c->ratio2 == 1.0);
    const double shift_g = same ? 0.0 : log2(c->ratio2) * per_oct;

    long long cur_e = -1;
    Py_ssize_t lo_b = 0, hi_b = -1;
    double c_zero = 0.0;
    /* per pair mode, half the |h| of its pairs (CG), and per bin their sum (CB: see pair_tol below) */
    double *CG = NULL, *CB = NULL;
    if (pair_tol > 0 && n_pairs > 0) {
        CG = (double *)calloc(ng1 + maxpad + BPAD, sizeof(double));
        if (CG == NULL) pair_tol = 0.0;   /* no memory for the bound: every model keeps its pairs */
        else {
            CB = CG + ng1;
            for (Py_ssize_t k = 0; k < n_pairs; k++) {
                CG[PA[k]] += 0.5 * fabs(PH[k]);
                CG[PB[k]] += 0.5 * fabs(PH[k]);
            }
        }
    }
    for (Py_ssize_t m = 0; m < n_models; m++) {
        const long long e = E[m];
        const Py_ssize_t npad = (Py_ssize_t)(OFF[e + 1] - OFF[e]);
        const double *W = COLS + NCH * OFF[e];
        /* the position of bin 0 (kappa = 2^(lo / nb)) on the tables; r = 0 gives -inf */
        const double pos = (log2(R2[m]) - start) * per_oct + (double)LO[e] * (double)M;
        double *o = O + NOUT * m;
        const double *AF, *BF, *AG, *BG;
        double tf, tg;
        Py_ssize_t flo, fhi, glo, ghi;
        /* every bin within both tables (the usual case): the sums interpolate the tables' rows themselves, and the
           fold pairs below, if any, take their bins' transforms from RF, RG made over the bins they read only. (Not
           in the portable build: SSE2's sixteen registers of two doubles spill in the passes' loops as it is, and
           the interpolation in them made it slower) */
        const int rows = ROWS_IN_SUMS && table_rows(GF, M, J, pos, npad, &AF, &BF, &tf, &flo, &fhi) == 0
                         && table_rows(GG, M, J, pos + shift_g, npad, &AG, &BG, &tg, &glo, &ghi) == 0
                         && flo == 0 && fhi == npad && glo == 0 && ghi == npad;
        if (rows)
            sums_from_rows(LIN, W, npad, AF, BF, tf, AG, BG, tg, DC + 8 * e, zero_f, zero_g, o);
        else {
            log_table_row(GF, M, J, pos, npad, npad, low_f, zero_f, RF);
            log_table_row(GG, M, J, pos + shift_g, npad, npad, low_g, zero_g, RG);
            sums_from_bins(LIN, W, npad, RF, RG, DC + 8 * e, zero_f, zero_g, o);
        }
        if (n_pairs > 0) {
            if (e != cur_e) {   /* the pair modes' bins at this ellipticity, as make_bins placed them */
                pair_block(nk, kept, n_g, n_pairs, PI, PW, PA, PB, PH, RFT, RGT, O);
                nk = 0;
                long long plo, phi;
                bin_index(PB3, n_g, S[3 * e], S[3 * e + 1], S[3 * e + 2], nb, PX, PI, PW, &plo, &phi);
                cur_e = e;
                /* each pair mode's first bin (within the bins), in place of its bin in PI, or -1 for the
                   transform at 0 (the DC mode, or too few bins); the bins they reach, lo_b .. hi_b, and with
                   pair_tol per bin the sum of CG over the modes whose first bin it is (CB), that of the modes at
                   0 in c_zero */
                lo_b = PY_SSIZE_T_MAX;
                hi_b = -1;
                c_zero = 0.0;
                for (Py_ssize_t g = 0; g < n_g; g++) {
                    if (PI[g] == INT_MIN || npad < 4) {
                        PI[g] = -1;
                        if (CG != NULL) c_zero += CG[g];
                        continue;
                    }
                    long long i0 = (long long)PI[g] - LO[e];
                    i0 = i0 < 0 ? 0 : (i0 > npad - 4 ? npad - 4 : i0);   /* within the bins (rounding only) */
                    PI[g] = (int)i0;
                    lo_b = (Py_ssize_t)i0 < lo_b ? (Py_ssize_t)i0 : lo_b;
                    hi_b = (Py_ssize_t)i0 > hi_b ? (Py_ssize_t)i0 : hi_b;
                }
                if (pair_tol > 0 && hi_b >= lo_b) {
                    for (Py_ssize_t b = lo_b; b <= hi_b; b++) CB[b] = 0.0;
                    for (Py_ssize_t g = 0; g < n_g; g++)
                        if (PI[g] >= 0) CB[PI[g]] += CG[g];
                }
                /* the DC mode's weights are those of position 0, (0, 1, 0, 0): it reads its transform at 0 from
                   four entries after the bins (npad + 1), so that the interpolation below has no branch */
                if (npad >= 4)
                    for (Py_ssize_t g = 0; g < n_g; g++) PI[g] = PI[g] < 0 ? (int)npad : PI[g];
            }
            if (rows)   /* the transforms of the bins the pairs read, as log_table_row makes them */
                for (Py_ssize_t b = lo_b; b <= hi_b + 3; b++) {
                    RF[b] = AF[b] + tf * (BF[b] - AF[b]);
                    RG[b] = AG[b] + tg * (BG[b] - AG[b]);
                }
            if (pair_tol > 0) {
                /* |h R_a R_b| <= |h| (A_a^2 + A_b^2) / 2 for A a mode's largest |R^f|, |R^g|, and A <= 1.25 times
                   the largest over its four bins (the cubic weights' absolute sum is at most 1.25): so the
                   pairs' ff, gg and fg are each within sum_g CG_g 1.5625 max^2 (CG_g: half the |h| of the
                   pairs of mode g), summed per first bin. Skipped where that is within pair_tol */
                const double z = fabs(zero_f) > fabs(zero_g) ? fabs(zero_f) : fabs(zero_g);
                double bound = c_zero * z * z;
                for (Py_ssize_t b = lo_b; b <= hi_b && 1.5625 * bound <= pair_tol; b++) {
                    /* (the terms are >= 0, so a partial sum past pair_tol decides as the whole one: stop there) */
                    if (CB[b] == 0.0) continue;
                    double a = 0.0;
                    for (int t = 0; t < 4; t++) {
                        const double v = fabs(RF[b + t]) > fabs(RG[b + t]) ? fabs(RF[b + t]) : fabs(RG[b + t]);
                        a = v > a ? v : a;
                    }
                    bound += CB[b] * a * a;
                }
                if (1.5625 * bound <= pair_tol) continue;
            }
            if (npad >= 4) {
                /* the model's bins' transforms into the block's column nk, and its pair terms with the block's:
                   only the bins the pair modes read (their first bins lo_b .. hi_b and the three after, and the
                   four entries at npad for those at 0; the fold groups' modes are aliases near the highest |K|) */
                for (int t = 0; t < 4; t++) {
                    RFT[(npad + t) * PLB + nk] = t == 1 ? zero_f : 0.0;
                    RGT[(npad + t) * PLB + nk] = t == 1 ? zero_g : 0.0;
                }
                for (Py_ssize_t b = lo_b; b <= hi_b + 3; b++) {
                    RFT[b * PLB + nk] = RF[b];
                    RGT[b * PLB + nk] = RG[b];
                }
                kept[nk++] = m;
                if (nk == PLB) {
                    pair_block(nk, kept, n_g, n_pairs, PI, PW, PA, PB, PH, RFT, RGT, O);
                    nk = 0;
                }
                continue;
            }
            for (Py_ssize_t g = 0; g < n_g; g++) {
                PF[g] = zero_f;
                PG[g] = zero_g;
            }
            double ff = 0.0, gg = 0.0, fg = 0.0;
            for (Py_ssize_t k = 0; k < n_pairs; k++) {
                const double fa = PF[PA[k]], fb = PF[PB[k]], ga = PG[PA[k]], gb = PG[PB[k]], h = PH[k];
                ff += h * fa * fb;
                gg += h * ga * gb;
                fg += 0.5 * h * (fa * gb + ga * fb);
            }
            o[12] += ff;
            o[13] += gg;
            o[14] += fg;
        }
    }
    if (n_pairs > 0) pair_block(nk, kept, n_g, n_pairs, PI, PW, PA, PB, PH, RFT, RGT, O);

    free(rbuf);
    free(tbuf);
    free(CG);
    return 0;
}

static __attribute__((noinline)) int binned_sums_run(const BinsCtx *c, Py_ssize_t n_models, const long long *E,
                                                     const double *R2, double *O)
{
    return binned_sums_impl(c, n_models, E, R2, O, 0);
}

/* binned_sums_run's linear sums alone (each row's o[12 .. 14] left as it is) */
static __attribute__((noinline)) int binned_lin_run(const BinsCtx *c, Py_ssize_t n_models, const long long *E,
                                                    const double *R2, double *O)
{
    return binned_sums_impl(c, n_models, E, R2, O, 1);
}

static PyObject *binned_sums(PyObject *self, PyObject *args)
{
    Py_buffer shape, r2b, eidx, lob, offb, colb, dcb, gfb, ggb, pbsb, pab, pbb, phb, out;
    BinsCtx c;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*iy*y*nndddddddy*y*y*y*dw*", &shape, &r2b, &eidx, &lob, &offb,
                          &colb, &dcb, &c.nb, &gfb, &ggb, &c.M, &c.J, &c.start, &c.per_oct, &c.low_f, &c.low_g,
                          &c.zero_f, &c.zero_g, &c.ratio2, &pbsb, &pab, &pbb, &phb, &c.pair_tol, &out))
        return NULL;
#define BS_RELEASE RELEASE(&shape, &r2b, &eidx, &lob, &offb, &colb, &dcb, &gfb, &ggb, &pbsb, &pab, &pbb, &phb, &out)
    if (bins_check(&c, &shape, &lob, &offb, &colb, &dcb, &gfb, &ggb, &pbsb, &pab, &pbb, &phb) != 0) {
        BS_RELEASE;
        return NULL;
    }
    Py_ssize_t n_models = r2b.len / (Py_ssize_t)sizeof(double);
    const long long *E = (const long long *)eidx.buf;
    int bad = out.len < n_models * NOUT * (Py_ssize_t)sizeof(double)
              || eidx.len != n_models * (Py_ssize_t)sizeof(long long);
    for (Py_ssize_t m = 0; !bad && m < n_models; m++)
        bad = E[m] < 0 || E[m] >= c.n_e;
    if (bad) {
        BS_RELEASE;
        PyErr_SetString(PyExc_ValueError, "binned_sums: inconsistent buffers");
        return NULL;
    }
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = binned_sums_run(&c, n_models, E, (const double *)r2b.buf, (double *)out.buf);
    Py_END_ALLOW_THREADS
    BS_RELEASE;
#undef BS_RELEASE
    if (rc != 0) return PyErr_NoMemory();
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

typedef struct {
    double sb2, b0, log_zb, tcrit, log_ei_tcrit, mu_min, max_step, slope, halfwidth;
    int bounded;
} MargPar;

/* The marginalisation runs in stages over arrays of (model, flux node) elements, so that the exponentials
 * and logarithms of each stage vectorise (libmvec, see vexp_shift); only erfcx, erf and the exponential
 * integral's table are evaluated one element at a time. MB_L elements per batch. */
#define MB_L 256

/* the position integral's geometry for one element (likelihood._position_integral): the determinant's
   argument dl (whose log is log det), the second-order correction corr, and whether the curvature is usable */
static inline __attribute__((always_inline)) void position_geometry(
    double g1, double g2, double H0, double H1, double H2, const MargPar *P, double *dl, double *corr_out, int *ok_out)
{
    double h11 = -H0, h12 = -H1, h22 = -H2;
    double gqg, step;
    int ok;
    if (P->bounded) {
        double half_tr = 0.5 * (h11 + h22);
        double rad = sqrt(0.25 * (h11 - h22) * (h11 - h22) + h12 * h12);
        double v1 = half_tr + rad, v2 = half_tr - rad;
        /* np.maximum: NaN propagates */
        double lam1 = v1 != v1 ? v1 : (v1 > P->mu_min ? v1 : P->mu_min);
        double lam2 = v2 != v2 ? v2 : (v2 > P->mu_min ? v2 : P->mu_min);
        double gg = g1 * g1 + g2 * g2;
        double gmg = h11 * g1 * g1 + 2 * h12 * g1 * g2 + h22 * g2 * g2;
        double p1sq = rad > 1e-9 * fabs(half_tr) ? (gmg - (half_tr - rad) * gg) / (2 * rad) : gg;
        p1sq = p1sq < 0 ? 0 : (p1sq > gg ? gg : p1sq);
        double p2sq = gg - p1sq;
        ok = isfinite(lam1) && isfinite(lam2);
        *dl = lam1 * lam2;
        gqg = p1sq / lam1 + p2sq / lam2;
        step = sqrt(p1sq / (lam1 * lam1) + p2sq / (lam2 * lam2));
    } else {
        double det = h11 * h22 - h12 * h12;
        ok = (h11 > 0) && (det > 0);
        *dl = ok ? det : 1.0;
        gqg = (g1 * g1 * h22 - 2 * g1 * g2 * h12 + g2 * g2 * h11) / det;
        step = 0.0;
    }
    double t = step > P->max_step ? P->max_step / (step > 0 ? step : 1.0) : 1.0;
    double corr = (t - 0.5 * t * t) * gqg;
    corr = ok ? (corr > 0 ? corr : (corr != corr ? corr : 0.0)) : 0.0;
    *corr_out = corr;
    *ok_out = ok;
}

static const double EI_FACT[13] = {1.0, 1.0, 2.0, 6.0, 24.0, 120.0, 720.0, 5040.0, 40320.0, 362880.0,
                                   3628800.0, 39916800.0, 479001600.0};   /* k!, the series' coefficients */

/* log Ei(x) for x > tcrit, in two parts: returns 1 and the series sum k! / x^k (likelihood._log_ei's 13
   terms) where log Ei = x - log x + log(series), else 0 and log Ei itself in *la */
static int log_ei_part(double x, double *la, double *series)
{
    if (x < EI_SERIES_FROM) {
        double t = (x - ei_x0) / ei_dx;
        if (t >= 0 && t < (double)(ei_n - 1)) {
            Py_ssize_t i = (Py_ssize_t)t;
            double s = t - (double)i, s1 = 1.0 - s;
            const double *a = ei_tab + 2 * i;
            *la = (1 + 2 * s) * s1 * s1 * a[0] + s * s1 * s1 * ei_dx * a[1]
                  + s * s * (3 - 2 * s) * a[2] - s * s * s1 * ei_dx * a[3];
        } else {
            *la = log(sp_expi(x, 0));
        }
        return 0;
    }
    double inv = 1.0 / x, s = 0.0;
    for (int k = 12; k >= 0; k--) s = s * inv + EI_FACT[k];
    *series = s;
    return 1;
}

static double log_ei(double x)
{
    double la = 0.0, series = 1.0;
    return log_ei_part(x, &la, &series) ? x - log(x) + log(series) : la;
}

/* the position integral (likelihood._position_integral) of n elements: val = log integral, -inf where the
   curvature is unusable; w: scratch of 7 x MB_L */
static void position_vec(Py_ssize_t n, const double *restrict lpr, const double *restrict lp0,
                         const double *restrict g1, const double *restrict g2, const double *restrict H0,
                         const double *restrict H1, const double *restrict H2, const MargPar *P,
                         double *restrict val, double *restrict w)
{
    double *dl = w, *A = w + MB_L, *okf = w + 2 * MB_L, *ld = w + 3 * MB_L, *lA = w + 4 * MB_L;
    double *la = w + 5 * MB_L, *ser = w + 6 * MB_L;
    const double tcrit = P->tcrit, lt = P->log_ei_tcrit;
    if (P->bounded) {
        /* position_geometry's bounded branch written out with selects only, so that the loop vectorises (its
           divisions and square roots, one element at a time, were a large part of the marginalisation): the
           same operations, the same numbers */
        const double mu_min = P->mu_min, max_step = P->max_step;
        for (Py_ssize_t e = 0; e < n; e++) {
            const double h11 = -H0[e], h12 = -H1[e], h22 = -H2[e], a1 = g1[e], a2 = g2[e];
            const double half_tr = 0.5 * (h11 + h22);
            const double rad = sqrt(0.25 * (h11 - h22) * (h11 - h22) + h12 * h12);
            const double v1 = half_tr + rad, v2 = half_tr - rad;
            const double lam1 = v1 != v1 ? v1 : (v1 > mu_min ? v1 : mu_min);
            const double lam2 = v2 != v2 ? v2 : (v2 > mu_min ? v2 : mu_min);
            const double gg = a1 * a1 + a2 * a2;
            const double gmg = h11 * a1 * a1 + 2 * h12 * a1 * a2 + h22 * a2 * a2;
            const double p1 = (gmg - (half_tr - rad) * gg) / (2 * rad);
            double p1sq = rad > 1e-9 * fabs(half_tr) ? p1 : gg;
            p1sq = p1sq < 0 ? 0 : (p1sq > gg ? gg : p1sq);
            const double p2sq = gg - p1sq;
            const int ok = fabs(lam1) < INFINITY && fabs(lam2) < INFINITY;   /* isfinite */
            const double gqg = p1sq / lam1 + p2sq / lam2;
            const double step = sqrt(p1sq / (lam1 * lam1) + p2sq / (lam2 * lam2));
            const double t = step > max_step ? max_step / (step > 0 ? step : 1.0) : 1.0;
            double corr = (t - 0.5 * t * t) * gqg;
            corr = ok ? (corr > 0 ? corr : (corr != corr ? corr : 0.0)) : 0.0;
            dl[e] = lam1 * lam2;
            A[e] = lpr[e] + corr - lp0[e];
            okf[e] = ok ? 1.0 : 0.0;
        }
    } else {
        for (Py_ssize_t e = 0; e < n; e++) {
            double corr, d;
            int ok;
            position_geometry(g1[e], g2[e], H0[e], H1[e], H2[e], P, &d, &corr, &ok);
            dl[e] = d;
            A[e] = lpr[e] + corr - lp0[e];
            okf[e] = ok;
        }
    }
    for (Py_ssize_t e = 0; e < n; e++) {
        ld[e] = log(dl[e]);
        lA[e] = log(A[e] > 0 ? A[e] : 1.0);
    }
    /* log Ei as log_ei_part: the series (most elements) in a loop that vectorises, then the table (or scipy's
       expi) one at a time below its start; the series' logarithms vectorised below */
    for (Py_ssize_t e = 0; e < n; e++) {
        const int series = A[e] > tcrit && A[e] >= EI_SERIES_FROM;
        const double inv = 1.0 / (series ? A[e] : EI_SERIES_FROM);
        double s = 0.0;
        for (int k = 12; k >= 0; k--) s = s * inv + EI_FACT[k];
        la[e] = lt + 1.0;
        ser[e] = series ? s : 1.0;
    }
    for (Py_ssize_t e = 0; e < n; e++)
        if (A[e] > tcrit && A[e] < EI_SERIES_FROM) {
            double s = 1.0, l = lt + 1.0;
            log_ei_part(A[e], &l, &s);
            la[e] = l;
            ser[e] = -1.0;   /* -1: la is l */
        }
    for (Py_ssize_t e = 0; e < n; e++) {
        double ls = log(ser[e] > 0 ? ser[e] : 1.0);
        double l = ser[e] > 0 ? A[e] - lA[e] + ls : la[e];
        la[e] = A[e] > tcrit ? l : lt + 1.0;
    }
    for (Py_ssize_t e = 0; e < n; e++) {
        /* log1p(-e^-d) ~ -e^-d is below half a unit in the last place of la once d > 37 and |la| >= 1 */
        double l = la[e];
        double lei = (l - lt > 37.0 && fabs(l) >= 1.0) ? l : l + log1p(-exp(lt - l));
        lei = A[e] > tcrit ? lei : -INFINITY;
        val[e] = okf[e] != 0 ? lp0[e] + LOG_2PI - 0.5 * ld[e] + lA[e] + lei : -INFINITY;
    }
}

/* log(erf(a) - erf(b)) for a > b (likelihood.log_erf_diff) of n pairs, without cancellation in the tails.
   erf(a) - erf(b) = erfc(u) - erfc(v) with u = b, v = a, or, in the lower tail (a <= 0), u = -a, v = -b:
   u < v and u is never in the lower tail, so erfc(u) is accurate and the difference cancels no more than
   the erf form (a - b >= 1/(sqrt(2) sigma_B) here). Both erfc in a loop that vectorises (glibc's vector
   erfc where it exists); where erfc(u) would underflow (u >= ERFC_SAFE), e^-u^2 comes out and scipy's
   erfcx is used, one element at a time: -u^2 + log(erfcx(u) - erfcx(v) e^(u^2 - v^2)).
   w: scratch of 4 x MB_L */
#define ERFC_SAFE 25.0
static void log_erf_diff_vec(Py_ssize_t n, const double *restrict a, const double *restrict b,
                             double *restrict out, double *restrict w)
{
    double *p = w, *us = w + MB_L, *vs = w + 2 * MB_L;
    int far = 0;
    for (Py_ssize_t e = 0; e < n; e++) {
        double ae = a[e], be = b[e];
        int lower = ae <= 0 && be < 0;
        double u = lower ? -ae : be, v = lower ? -be : ae;
        double uc = u < ERFC_SAFE ? u : 0.0;   /* the far ones are redone below */
        p[e] = erfc(uc) - erfc(uc < u ? uc : v);
        us[e] = u;
        vs[e] = v;
        far |= !(u < ERFC_SAFE);
    }
    for (Py_ssize_t e = 0; e < n; e++) out[e] = log(p[e]);
    if (!far) return;
    for (Py_ssize_t e = 0; e < n; e++) {
        double u = us[e], v = vs[e];
        if (u < ERFC_SAFE) continue;
        double d = u * u - v * v;
        double q = d > -745.0 ? sp_erfcx(v, 0) * exp(d) : 0.0;
        out[e] = -u * u + log(sp_erfcx(u, 0) - q);
    }
}

/* the disk population (bulge fraction marginalised analytically, likelihood._disk_logp) of n elements:
   log P at (hf, hg) and at h = 0 (the pedestal, which shares theta), <B>, and the position's gradient and
   Hessian mixed by <B> (g: 5 x MB_L). x: each element's model sums (15, see marginal); w: scratch of
   14 x MB_L */
static void disk_vec(Py_ssize_t n, const double *restrict S, const double *const *restrict x, const MargPar *P,
                     double *restrict lp, double *restrict lp0, double *restrict mb, double *restrict g,
                     double *restrict w)
{
    double *th = w, *lth = w + MB_L, *r0 = w + 2 * MB_L, *ab = w + 4 * MB_L, *led = w + 8 * MB_L;
    double *scratch = w + 10 * MB_L;
    const double inv_sb2 = 1.0 / P->sb2, b0s = P->b0 / P->sb2;
    for (Py_ssize_t e = 0; e < n; e++) {
        const double *xe = x[e];
        double s = S[e], ff = xe[12], gg = xe[13], fg = xe[14];
        double t = sqrt(0.5 * (s * s * (ff + gg - 2 * fg) + inv_sb2));
        double rn = s * (xe[0] - xe[6]) + s * s * (fg - ff) - b0s, rz = s * s * (fg - ff) - b0s;
        th[e] = t;
        r0[e] = rn;
        r0[MB_L + e] = rz;
        ab[e] = t + rn / (2 * t);              /* a and b at (hf, hg), then at h = 0 */
        ab[MB_L + e] = rn / (2 * t);
        ab[2 * MB_L + e] = t + rz / (2 * t);
        ab[3 * MB_L + e] = rz / (2 * t);
    }
    for (Py_ssize_t e = 0; e < n; e++) lth[e] = log(th[e]);
    log_erf_diff_vec(n, ab, ab + MB_L, led, scratch);
    log_erf_diff_vec(n, ab + 2 * MB_L, ab + 3 * MB_L, led + MB_L, scratch);
    const double c0 = -0.5 * P->b0 * P->b0 / P->sb2, c1 = log(sqrt(M_PI) / 2);
    for (Py_ssize_t e = 0; e < n; e++) {
        const double *xe = x[e];
        double s = S[e], t = th[e], rn = r0[e], rz = r0[MB_L + e];
        double a = ab[e], b = ab[MB_L + e], le = led[e];
        lp[e] = s * xe[0] - 0.5 * s * s * xe[12] + c0 + rn * rn / (4 * t * t) + c1 - lth[e] + le - P->log_zb;
        lp0[e] = -0.5 * s * s * xe[12] + c0 + rz * rz / (4 * t * t) + c1 - lth[e] + led[MB_L + e] - P->log_zb;
        double mu = -rn / (2 * t * t);
        double num = exp(-b * b - le) - exp(-a * a - le);
        double m = mu + num / (t * sqrt(M_PI));
        m = m < 0 ? 0 : (m > 1 ? 1 : m);
        mb[e] = m;
        for (int c = 0; c < 2; c++) g[c * MB_L + e] = s * ((1 - m) * xe[1 + c] + m * xe[7 + c]);
        for (int c = 0; c < 3; c++) g[(2 + c) * MB_L + e] = s * ((1 - m) * xe[3 + c] + m * xe[9 + c]);
    }
}

/* the bulge population (B = 1): log P at hg and at h = 0, and the position's gradient and Hessian */
static void bulge_vec(Py_ssize_t n, const double *restrict S, const double *const *restrict x,
                      double *restrict lp, double *restrict lp0, double *restrict g)
{
    for (Py_ssize_t e = 0; e < n; e++) {
        const double *xe = x[e];
        double s = S[e];
        lp[e] = s * xe[6] - 0.5 * s * s * xe[13];
        lp0[e] = -0.5 * s * s * xe[13];
        for (int c = 0; c < 2; c++) g[c * MB_L + e] = s * xe[7 + c];
        for (int c = 0; c < 3; c++) g[(2 + c) * MB_L + e] = s * xe[9 + c];
    }
}

#define MAXF 64

/* out[q] = sum_k v[k] M[k, q] (M: nk x nq), summed over k in order as the scalar loop did; four q at a time in
   registers (a pass over out per k, as written before, was a large part of the marginalisation) */
typedef double v4du __attribute__((vector_size(4 * sizeof(double)), aligned(sizeof(double))));
static void spline_rows(const double *restrict v, const double *restrict M, Py_ssize_t nk, Py_ssize_t nq,
                        double *restrict out)
{
    Py_ssize_t q = 0;
    for (; q + 4 <= nq; q += 4) {
        v4du acc = {0.0, 0.0, 0.0, 0.0};
        for (Py_ssize_t k = 0; k < nk; k++) acc += v[k] * *(const v4du *)(M + k * nq + q);
        *(v4du *)(out + q) = acc;
    }
    for (; q < nq; q++) {
        double acc = 0.0;
        for (Py_ssize_t k = 0; k < nk; k++) acc += v[k] * M[k * nq + q];
        out[q] = acc;
    }
}

/* what marginal needs besides the models' sums: the flux nodes u (nf), the fine grid uf (nfine), the spline and
   interpolation matrices between them and the parameters (marg_check) */
typedef struct {
    const double *u, *uf, *SPL, *ITP;
    Py_ssize_t nf, nfine;
    MargPar P;
} MargCtx;

/* the buffers of a MargCtx (u, u_fine, spline, interp, params): 0, or -1 with a ValueError set */
static int marg_check(MargCtx *c, const Py_buffer *ub, const Py_buffer *ufb, const Py_buffer *spl,
                      const Py_buffer *itp, const Py_buffer *par)
{
    c->nf = ub->len / (Py_ssize_t)sizeof(double);
    c->nfine = ufb->len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t nf = c->nf, nfine = c->nfine;
    if (sp_erfcx == NULL || nf < 2 || nf > MAXF || nfine < 2 || nfine > 4 * MAXF
        || spl->len != nf * nfine * (Py_ssize_t)sizeof(double) || itp->len != spl->len
        || par->len != 10 * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, sp_erfcx == NULL ? "marginal: set_special first"
                                                           : "marginal: inconsistent buffers");
        return -1;
    }
    const double *pp = (const double *)par->buf;
    MargPar P = {pp[0], pp[1], pp[2], pp[3], 0.0, pp[4], pp[5], pp[6], pp[7], pp[8] != 0.0};
    c->P = P;
    c->u = (const double *)ub->buf;
    c->uf = (const double *)ufb->buf;
    c->SPL = (const double *)spl->buf;
    c->ITP = (const double *)itp->buf;
    return 0;
}

/* the marginalisation of n models (X: their sums, rows of 15) into O (rows of 9: logl_d, logl_b, flux_d, flux_b,
   meanb_d, chi2_d, chi2_b, snr_d, snr_b); 0, or -1 where memory ran out. Runs without the GIL. */
/* m = v[0], then m = v[q] > m ? v[q] : m for q = 1 .. n - 1 (NaN after v[0] left out; v[0] NaN: NaN): the same value
   from four lanes that start at v[0] and take every fourth, then joined by the same rule (the serial chain of
   maxima, 4 cycles each, was a tenth of the marginalisation) */
static inline double max_from_first(const double *v, Py_ssize_t n)
{
    double m4[4] = {v[0], v[0], v[0], v[0]};
    Py_ssize_t q = 1;
    for (; q + 4 <= n; q += 4)
        for (int l = 0; l < 4; l++) m4[l] = v[q + l] > m4[l] ? v[q + l] : m4[l];
    double m = m4[0];
    for (int l = 1; l < 4; l++) m = m4[l] > m ? m4[l] : m;
    for (; q < n; q++) m = v[q] > m ? v[q] : m;
    return m;
}

/* the best-fit chi^2 and SNR of population pop's single-component model at its best flux and position (x: the
   model's sums, rows of 15; o: its row of marginal_run's 9, entries 5 + pop and 7 + pop); one function, so that
   marginal_run's and best_fit_rows' numbers are the same */
static __attribute__((noinline)) void best_fit_one(const double *x, int pop, const MargPar *P, double *o)
{
    const double *L = x + 6 * pop;
    const double h = L[0], hh = x[12 + pop];
    const int good = (hh > 0) && (h > 0);
    const double hh_s = good ? hh : 1.0, s_ml = good ? h / hh_s : 1.0;
    double dl, cml;
    int ok;
    position_geometry(L[1] * s_ml, L[2] * s_ml, L[3] * s_ml, L[4] * s_ml, L[5] * s_ml, P, &dl, &cml, &ok);
    o[5 + pop] = good ? -(h * h / hh_s) - 2 * cml : 0.0;
    o[7 + pop] = good ? h / sqrt(hh_s) : 0.0;
}

/* marginal_run's best fits alone (its rows' entries 5 - 8; 0 - 4 NaN) of n models */
static void best_fit_rows(const MargCtx *c, Py_ssize_t n, const double *X, double *O)
{
    for (Py_ssize_t j = 0; j < n; j++) {
        double *o = O + 9 * j;
        for (int t = 0; t < 5; t++) o[t] = NAN;
        for (int pop = 0; pop < 2; pop++) best_fit_one(X + 15 * j, pop, &c->P, o);
    }
}

static __attribute__((noinline)) int marginal_run(const MargCtx *c, Py_ssize_t n, const double *X, double *O)
{
    const Py_ssize_t nf = c->nf, nfine = c->nfine;
    const double *u = c->u, *uf = c->uf, *SPL = c->SPL, *ITP = c->ITP;
    MargPar P = c->P;
    double *work = (double *)malloc(28 * MB_L * sizeof(double));
    const double **xp = (const double **)malloc(MB_L * sizeof(double *));
    if (work == NULL || xp == NULL) {
        free(work);
        free(xp);
        return -1;
    }
    /* per element: S, log S, log P, log P at h = 0, <B>, gradient and Hessian (5), log integral (val) */
    double *Sk = work, *logS = work + MB_L, *lp = work + 2 * MB_L, *lp0 = work + 3 * MB_L, *mbe = work + 4 * MB_L;
    double *g = work + 5 * MB_L, *val = work + 10 * MB_L, *scratch = work + 11 * MB_L;   /* scratch: 14 */
    /* per model of the batch: the flux range [lo, hi] and whether the model correlates with the data */
    double *lo_m = work + 25 * MB_L, *hi_m = work + 26 * MB_L, *good_m = work + 27 * MB_L;
    const Py_ssize_t per = MB_L / nf;   /* models per batch */
    P.log_ei_tcrit = log_ei(P.tcrit);
    for (Py_ssize_t i0 = 0; i0 < n; i0 += per) {
        const Py_ssize_t nm = i0 + per <= n ? per : n - i0, ne = nm * nf;
        for (int pop = 0; pop < 2; pop++) {
            for (Py_ssize_t j = 0; j < nm; j++) {
                const double *x = X + 15 * (i0 + j);
                double h = x[6 * pop], hh = x[12 + pop];
                int good = (hh > 0) && (h > 0);
                double hh_s = good ? hh : 1.0, s_ml = good ? h / hh_s : 1.0, sig = 1.0 / sqrt(hh_s);
                double lo = fmax(s_ml - P.halfwidth * sig, 0.02 * s_ml), hi = s_ml + P.halfwidth * sig;
                for (Py_ssize_t k = 0; k < nf; k++) {
                    Sk[j * nf + k] = lo + (hi - lo) * u[k];
                    xp[j * nf + k] = x;
                }
                lo_m[j] = lo;
                hi_m[j] = hi;
                good_m[j] = good;
            }
            vlog(Sk, logS, ne);
            if (pop == 0)
                disk_vec(ne, Sk, xp, &P, lp, lp0, mbe, g, scratch);
            else
                bulge_vec(ne, Sk, xp, lp, lp0, g);
            position_vec(ne, lp, lp0, g, g + MB_L, g + 2 * MB_L, g + 3 * MB_L, g + 4 * MB_L, &P, val, scratch);
            for (Py_ssize_t j = 0; j < nm; j++) {
                const double *x = X + 15 * (i0 + j);
                double *o = O + 9 * (i0 + j);    /* logl_d, logl_b, flux_d, flux_b, meanb_d, chi2_d, chi2_b, snr_d, snr_b */
                const int good = good_m[j] != 0;
                const double lo = lo_m[j], hi = hi_m[j];
                double lpk[MAXF];
                for (Py_ssize_t k = 0; k < nf; k++)
                    lpk[k] = good ? val[j * nf + k] - P.slope * logS[j * nf + k] : -INFINITY;
                const double *mb = mbe + j * nf;
                /* the cubic spline of log P over the flux nodes, integrated on the fine grid (_spline_logint) */
                double rowmax = -INFINITY;
                for (Py_ssize_t k = 0; k < nf; k++) if (isfinite(lpk[k]) && lpk[k] > rowmax) rowmax = lpk[k];
                int good_row = isfinite(rowmax);
                double floor_ = good_row ? rowmax - 40.0 : 0.0;
                double lv[MAXF];
                for (Py_ssize_t k = 0; k < nf; k++) lv[k] = isfinite(lpk[k]) ? fmax(lpk[k], floor_) : floor_;
                double vf[4 * MAXF], bf[4 * MAXF], m;
                spline_rows(lv, SPL, nf, nfine, vf);
                if (pop == 0) spline_rows(mb, ITP, nf, nfine, bf);
                m = max_from_first(vf, nfine);
                double integral = 0.0, wsum = 0.0, ws = 0.0, wb = 0.0, wprev = 0.0, wv[4 * MAXF];
                vexp_shift(vf, m, wv, nfine);
                for (Py_ssize_t q = 0; q < nfine; q++) {
                    double w = wv[q];
                    if (q > 0) integral += 0.5 * (w + wprev) * (uf[q] - uf[q - 1]);
                    wprev = w;
                    wsum += w;
                    ws += w * (lo + (hi - lo) * uf[q]);
                    wb += pop == 0 ? w * bf[q] : w;
                }
                if (!(wsum > 0)) wsum = 1.0;
                double logint = good_row ? m + log(integral) : -INFINITY;
                logint += log(hi - lo);
                o[pop] = good ? logint : -INFINITY;
                o[2 + pop] = ws / wsum;
                if (pop == 0) o[4] = wb / wsum;
                best_fit_one(x, pop, &P, o);
            }
        }
    }
    free(work);
    free(xp);
    return 0;
}

static PyObject *marginal(PyObject *self, PyObject *args)
{
    Py_buffer sums, ub, ufb, spl, itp, par, out;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*w*", &sums, &ub, &ufb, &spl, &itp, &par, &out)) return NULL;
    MargCtx c;
    Py_ssize_t n = sums.len / (15 * (Py_ssize_t)sizeof(double));
    if (marg_check(&c, &ub, &ufb, &spl, &itp, &par) != 0 || out.len < 9 * n * (Py_ssize_t)sizeof(double)) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "marginal: inconsistent buffers");
        RELEASE(&sums, &ub, &ufb, &spl, &itp, &par, &out);
        return NULL;
    }
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = marginal_run(&c, n, (const double *)sums.buf, (double *)out.buf);
    Py_END_ALLOW_THREADS
    RELEASE(&sums, &ub, &ufb, &spl, &itp, &par, &out);
    if (rc != 0) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

/*
 * locate_parabola(ld, lb, lpr, w, xs, top, xpk): sampling.EllipticityLikelihood._locate's peaks (its numpy lines stay
 * as the reference; a test checks they agree to the bit). Per row i of n nodes (xs: n >= 3, uniform): for the disk
 * (ld, weight w[0]) and the pure bulge (lb, w[1]), y = (w + log L, -1e300 where not finite) + lpr; the parabola
 * through the best node k (first maximum, held within 1 .. n - 2) and its neighbours; its peak's offset d (0 where
 * the parabola does not open downwards or is NaN, within +-h) and value. top[i], xpk[i]: the value and xs[k] + d of
 * the population whose parabola peaks higher (the disk's on a tie). The same operations in the same order as the
 * numpy lines, without contraction into fused multiply-adds, so the same numbers.
 */
#if defined(__clang__)
#define NO_CONTRACT
#elif defined(__GNUC__)
#define NO_CONTRACT __attribute__((optimize("fp-contract=off")))
#else
#define NO_CONTRACT
#endif
/* NO_CLONE: a function of NO_CONTRACT that a caller passes constants must not be cloned for them: GCC 12's copy of
   locate_pass_run specialised to sample_chunk's 5 nodes lost fp-contract=off, and the means of its crude integral
   differed from locate_pass' in their last places */
#if defined(__GNUC__) && !defined(__clang__)
#define NO_CLONE __attribute__((noclone))
#else
#define NO_CLONE
#endif
static NO_CONTRACT void locate_rows(const double *LD, const double *LB, const double *LPR, const double *w,
                                    const double *xs, Py_ssize_t nrow, Py_ssize_t n, double *top, double *xpk)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const double h = xs[1] - xs[0], h2 = h * h, hh = 0.5 * h;
    for (Py_ssize_t i = 0; i < nrow; i++) {
        double best_top = 0.0, best_x = 0.0;
        for (int pop = 0; pop < 2; pop++) {
            const double *L = (pop == 0 ? LD : LB) + i * n, *P = LPR + i * n;
            double y[64];
            Py_ssize_t k = 0;
            int nan_at = -1;
            for (Py_ssize_t j = 0; j < n; j++) {
                y[j] = (isfinite(L[j]) ? w[pop] + L[j] : -1e300) + P[j];
                if (nan_at < 0 && y[j] != y[j]) nan_at = (int)j;
                if (y[j] > y[k]) k = j;
            }
            if (nan_at >= 0) k = nan_at;   /* np.argmax: the first NaN */
            k = k < 1 ? 1 : (k > n - 2 ? n - 2 : k);
            const double ym = y[k - 1], y0 = y[k], yp = y[k + 1];
            const double den = ym - 2 * y0 + yp;
            double d = den < 0 ? hh * (ym - yp) / den : 0.0;
            d = d == d ? d : 0.0;
            d = d > -h ? d : -h;   /* np.maximum(d, -h): d is not NaN here */
            d = d < h ? d : h;
            const double a = 0.5 * (yp - ym) / h * d, b = 0.5 * den / h2 * d * d;
            const double v = y0 + a + b;
            /* np.maximum(y0, v): NaN propagates */
            const double t = (y0 != y0 || v != v) ? (y0 != y0 ? y0 : v) : (v > y0 ? v : y0);
            const double x = xs[k] + d;
            if (pop == 0 || t > best_top) {
                best_top = t;
                best_x = x;
            }
        }
        top[i] = best_top;
        xpk[i] = best_x;
    }
}

static PyObject *locate_parabola(PyObject *self, PyObject *args)
{
    Py_buffer db, bb, pb, wb, xb, tb, ob;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*w*", &db, &bb, &pb, &wb, &xb, &tb, &ob)) return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double), n = xb.len / D, nrow = tb.len / D;
    if (n < 3 || n > 64 || db.len != nrow * n * D || bb.len != db.len || pb.len != db.len || wb.len != 2 * D
        || ob.len != tb.len) {
        RELEASE(&db, &bb, &pb, &wb, &xb, &tb, &ob);
        PyErr_SetString(PyExc_ValueError, "locate_parabola: inconsistent buffers");
        return NULL;
    }
    locate_rows((const double *)db.buf, (const double *)bb.buf, (const double *)pb.buf, (const double *)wb.buf,
                (const double *)xb.buf, nrow, n, (double *)tb.buf, (double *)ob.buf);
    RELEASE(&db, &bb, &pb, &wb, &xb, &tb, &ob);
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
/* size_marginal's integrals of ne ellipticities (the arrays as size_marginal's, O: 5 x ne) */
/* (not inlined: size_nodes' caller is compiled without contraction, and this must make size_marginal's numbers) */
static __attribute__((noinline)) void size_marginal_run(
    Py_ssize_t ne, Py_ssize_t nr, Py_ssize_t nf, Py_ssize_t nu, const double *LD, const double *LB, const double *FD,
    const double *FB, const double *BD, const double *LP, const double *LS, const double *SPL, const double *ITP,
    const double *XF, const double *U, const double *RF, const double *L0, const double *LM, double *O,
    const unsigned char *need, Py_ssize_t stride)
{
    for (Py_ssize_t e = 0; e < ne; e++) {
        if (need != NULL && !need[e * stride]) {   /* not made (node_models_versions' need) */
            for (int t = 0; t < 5; t++) O[t * ne + e] = NAN;
            continue;
        }
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
}

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
    size_marginal_run(ne, nr, nf, nu, LD, LB, FD, FB, BD, LP, LS, SPL, ITP, XF, U, RF, L0, LM, O, NULL, 0);
    Py_END_ALLOW_THREADS
    RELEASE(&b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7], &b[8], &b[9], &b[10], &b[11], &b[12], &b[13],
            &b[14]);
    Py_RETURN_NONE;
}

/*
 * quintic_kvalues(table, n, ntab, tx, ty, out): metacal's k-space interpolation (calib/kspace.py, whose numpy
 * kvalues_numpy is the reference). table: complex128 (ntab, n / 2 + 1, n), the transforms of ntab padded images
 * (kx >= 0, then ky); tx, ty: float64, the points in units of the table's step; out: complex128
 * (npts, ntab). Each point takes the 6 x 6 table values around it (periodic in n; a column beyond n / 2 is the
 * conjugate of the mirrored one) with the weights of the quintic kernel (Bernstein & Gruen 2014), one set of
 * weights for the ntab images.
 */
/* the six weights of the quintic kernel at distances f + 2, f + 1, f, 1 - f, 2 - f, 3 - f (f in [0, 1)), for two
   offsets at once (fx, fy: into wx, wy): each distance in a known piece of the kernel, so no branch, and each
   piece evaluated at its four distances (two of x, two of y) as one vector (one weight at a time, the twelve
   polynomials' chains were a fifth of metacal's band loop; the same operations, the same numbers) */
typedef double qw4 __attribute__((vector_size(4 * sizeof(double))));
static inline __attribute__((always_inline)) void quintic_weights(double fx, double fy, double *wx, double *wy)
{
    const qw4 f = {fx, -fx, fy, -fy};
    /* x = f + 2 (tap 0) and 3 - f (tap 5); f + 1 (tap 1) and 2 - f (tap 4); f (tap 2) and 1 - f (tap 3) */
    const qw4 c2 = {2.0, 3.0, 2.0, 3.0}, c1 = {1.0, 2.0, 1.0, 2.0}, c0 = {0.0, 1.0, 0.0, 1.0};
    qw4 x = c2 + f;
    const qw4 w3 = (x - 2.0) * (x - 3.0) * (x - 3.0) * (-9.0 / 4.0 + x * (25.0 / 12.0 + x * (-11.0 / 24.0)));
    x = c1 + f;
    const qw4 w2 = (x - 1.0) * (x - 2.0) * (-23.0 / 4.0 + x * (29.0 / 2.0 + x * (-83.0 / 8.0 + x * (55.0 / 24.0))));
    x = c0 + f;
    const qw4 w1 = 1.0 + x * x * x * (-95.0 / 12.0 + x * (23.0 / 2.0 + x * (-55.0 / 12.0)));
    for (int a = 0; a < 4; a += 2) {   /* lanes 0, 1: x's; 2, 3: y's */
        double *w = a ? wy : wx;
        w[0] = w3[a];
        w[1] = w2[a];
        w[2] = w1[a];
        w[3] = w1[a + 1];
        w[4] = w2[a + 1];
        w[5] = w3[a + 1];
    }
}

#define KI_MAXTAB 8

/* the npts points for NT images (a compile-time constant where the caller's switch makes it one); the table
   is NT planes of nc columns (kx = 0 .. n / 2) of n values (ky), so that each column's six taps are adjacent */
/* one point (tx, ty) for NT images: acc[2 t], acc[2 t + 1] the t-th image's value */
static inline __attribute__((always_inline)) void kvalue_point(
    const double *restrict T, Py_ssize_t n, const Py_ssize_t NT, double tx, double ty, double *restrict acc)
{
    const Py_ssize_t nc = n / 2 + 1, plane = 2 * nc * n;
    const double fx = floor(tx), fy = floor(ty);
    double wx[6], wy[6];
    quintic_weights(tx - fx, ty - fy, wx, wy);
    Py_ssize_t ix = (Py_ssize_t)fx - 2, iy = (Py_ssize_t)fy - 2;
    /* modulo n (a division only for points more than a period away) */
    if (ix < 0 || ix >= n) ix = ix >= -n && ix < 0 ? ix + n : (ix < 2 * n && ix >= n ? ix - n : (ix % n + n) % n);
    if (iy < 0 || iy >= n) iy = iy >= -n && iy < 0 ? iy + n : (iy < 2 * n && iy >= n ? iy - n : (iy % n + n) % n);
    for (Py_ssize_t t = 0; t < 2 * NT; t++) acc[t] = 0.0;
    if (iy >= 1 && iy + 5 < n) {
        /* the usual point: each column's six values adjacent (a mirrored column's, at -ky, in reverse). The six
           columns are summed first, their y taps in vectors (below), the columns of kx >= 0 into L and the mirrored
           ones (in their memory order) into M, chains of six independent sums; then the y weights, once per image.
           (The y weights first, column by column, made each column's sum a chain of six dependent products and the
           point's a chain of six such sums: the band took a tenth longer.) */
#if defined(__AVX__)
        /* three vectors of four doubles (y taps 0-1, 2-3, 4-5) */
        typedef double vq __attribute__((vector_size(32), aligned(sizeof(double))));
        enum { QV = 3 };
        const vq WL[QV] = {{wy[0], wy[0], wy[1], wy[1]}, {wy[2], wy[2], wy[3], wy[3]}, {wy[4], wy[4], wy[5], wy[5]}};
        const vq WM[QV] = {{wy[5], wy[5], wy[4], wy[4]}, {wy[3], wy[3], wy[2], wy[2]}, {wy[1], wy[1], wy[0], wy[0]}};
#else
        /* SSE2's six vectors of two (vectors of four, split by GCC, went through memory: four times as slow) */
        typedef double vq __attribute__((vector_size(16), aligned(sizeof(double))));
        enum { QV = 6 };
        const vq WL[QV] = {{wy[0], wy[0]}, {wy[1], wy[1]}, {wy[2], wy[2]},
                           {wy[3], wy[3]}, {wy[4], wy[4]}, {wy[5], wy[5]}};
        const vq WM[QV] = {{wy[5], wy[5]}, {wy[4], wy[4]}, {wy[3], wy[3]},
                           {wy[2], wy[2]}, {wy[1], wy[1]}, {wy[0], wy[0]}};
#endif
        for (Py_ssize_t t = 0; t < NT; t++) {
            vq L[QV] = {{0}}, M[QV] = {{0}};
            int any_m = 0;
            Py_ssize_t c = ix;
            for (int a = 0; a < 6; a++) {
                if (c <= n / 2) {
                    const vq *v = (const vq *)(T + t * plane + 2 * n * c + 2 * iy);
                    for (int q = 0; q < QV; q++) L[q] += wx[a] * v[q];
                } else {
                    const vq *v = (const vq *)(T + t * plane + 2 * n * (n - c) + 2 * (n - iy - 5));
                    for (int q = 0; q < QV; q++) M[q] += wx[a] * v[q];
                    any_m = 1;
                }
                c = c + 1 == n ? 0 : c + 1;
            }
            vq pl = L[0] * WL[0], pm = M[0] * WM[0];
            for (int q = 1; q < QV; q++) pl += L[q] * WL[q];
            double re = 0.0, im = 0.0;
            for (int q = 0; q < (int)(sizeof(vq) / sizeof(double)); q += 2) {
                re += pl[q];
                im += pl[q + 1];
            }
            if (any_m) {
                for (int q = 1; q < QV; q++) pm += M[q] * WM[q];
                double mr = 0.0, mi = 0.0;
                for (int q = 0; q < (int)(sizeof(vq) / sizeof(double)); q += 2) {
                    mr += pm[q];
                    mi += pm[q + 1];
                }
                re += mr;
                im -= mi;
            }
            acc[2 * t] = re;
            acc[2 * t + 1] = im;
        }
        return;
    }
    Py_ssize_t cy[6], my[6];
    for (int b = 0; b < 6; b++) {
        cy[b] = iy;
        my[b] = iy == 0 ? 0 : n - iy;   /* -ky, for the mirrored columns */
        iy = iy + 1 == n ? 0 : iy + 1;
    }
    for (int a = 0; a < 6; a++) {
        const int low = ix <= n / 2;
        const Py_ssize_t col = low ? ix : n - ix;
        const Py_ssize_t *rows = low ? cy : my;
        /* this column's six values summed with the y weights first; the mirrored column conjugated */
        for (Py_ssize_t t = 0; t < NT; t++) {
            const double *v = T + t * plane + 2 * n * col;
            double re = 0.0, im = 0.0;
            for (int b = 0; b < 6; b++) {
                re += wy[b] * v[2 * rows[b]];
                im += wy[b] * v[2 * rows[b] + 1];
            }
            acc[2 * t] += wx[a] * re;
            acc[2 * t + 1] += (low ? wx[a] : -wx[a]) * im;
        }
        ix = ix + 1 == n ? 0 : ix + 1;
    }
}

/* the npts points for NT images (a compile-time constant where the caller's switch makes it one); the table
   is NT planes of nc columns (kx = 0 .. n / 2) of n values (ky), so that each column's six taps are adjacent */
static inline __attribute__((always_inline)) void kvalues_range(
    const double *restrict T, Py_ssize_t n, const Py_ssize_t NT, const double *restrict TX,
    const double *restrict TY, Py_ssize_t npts, double *restrict O)
{
    for (Py_ssize_t p = 0; p < npts; p++) {
        double acc[2 * KI_MAXTAB];
        kvalue_point(T, n, NT, TX[p], TY[p], acc);
        for (Py_ssize_t t = 0; t < 2 * NT; t++) O[2 * NT * p + t] = acc[t];
    }
}

static PyObject *quintic_kvalues(PyObject *self, PyObject *args)
{
    Py_buffer tab, txb, tyb, out;
    Py_ssize_t n, ntab;
    if (!PyArg_ParseTuple(args, "y*nny*y*w*", &tab, &n, &ntab, &txb, &tyb, &out)) return NULL;
    const Py_ssize_t nc = n / 2 + 1;
    const Py_ssize_t npts = txb.len / (Py_ssize_t)sizeof(double);
    if (n < 2 || ntab < 1 || ntab > KI_MAXTAB || tab.len != n * nc * ntab * 2 * (Py_ssize_t)sizeof(double)
        || tyb.len != txb.len || out.len != npts * ntab * 2 * (Py_ssize_t)sizeof(double)) {
        RELEASE(&tab, &txb, &tyb, &out);
        PyErr_SetString(PyExc_ValueError, "quintic_kvalues: inconsistent buffers");
        return NULL;
    }
    const double *T = (const double *)tab.buf, *TX = (const double *)txb.buf, *TY = (const double *)tyb.buf;
    double *O = (double *)out.buf;
    Py_BEGIN_ALLOW_THREADS
    switch (ntab) {
    case 1: kvalues_range(T, n, 1, TX, TY, npts, O); break;
    case 2: kvalues_range(T, n, 2, TX, TY, npts, O); break;
    case 3: kvalues_range(T, n, 3, TX, TY, npts, O); break;
    case 4: kvalues_range(T, n, 4, TX, TY, npts, O); break;
    default: kvalues_range(T, n, ntab, TX, TY, npts, O); break;
    }
    Py_END_ALLOW_THREADS
    RELEASE(&tab, &txb, &tyb, &out);
    Py_RETURN_NONE;
}

/*
 * quintic_band(table, n, r, dk, A, JT, to_table, lim, gamma, step, phase, out): one metacal version's band
 * (calib/metacal.py's own_kspace_images, whose numpy lines are the reference): for the points kappa = dk (i, j)
 * of the band (rows j = -r .. r, columns i = 0 .. r), the sky wavevector A kappa; where its squared norm is at
 * most lim, the three transforms of table (3 planes: the stamp, its noise, the PSF) at the pixel-frame point
 * JT (A kappa) to_table (quintic_kvalues' interpolation; with step > 0, the version without shear, whose points
 * are the table's own (step i, step j), read directly), and out[t] = table t's value times gamma / the PSF's
 * (t = 0, 1); zero elsewhere. A, JT: float64 2 x 2 (row-major); gamma: complex128 (2 r + 1) (r + 1); out:
 * complex128 2 or 3 of those. With 3 (phase: complex128 r + 1), the noise's band turned (metacal.turned_band:
 * out[2][j, i] = phase[i] noise(-i, j)) is out[2], and out[0] the stamp's plus it. A may hold nv versions' matrices
 * (nv x 2 x 2, step 0) and out their bands one after another (nv blocks of 2 or 3): each version's band is that of
 * its own call, to the bit, the versions taken point by point (their sheared points lie within a tap of each other,
 * so every version reads the table's columns while the first one's reading keeps them in the cache: the table, 900
 * kB for a 48-pixel stamp, no longer fetched again for every version).
 */
/* one band point's two products: f = gamma / the PSF's value (as numpy divides complex numbers, Smith's),
   then o0 = the stamp's value times f, o1 = the noise's */
static inline __attribute__((always_inline)) void band_products(const double *v, double pr, double pi, double gr,
                                                                 double gi, double *o0, double *o1)
{
    double fr, fi;
    if (fabs(pr) >= fabs(pi)) {
        if (pr == 0.0 && pi == 0.0) {
            fr = gr / fabs(pr);
            fi = gi / fabs(pr);
        } else {
            const double rat = pi / pr, scl = 1.0 / (pr + pi * rat);
            fr = (gr + gi * rat) * scl;
            fi = (gi - gr * rat) * scl;
        }
    } else {
        const double rat = pr / pi, scl = 1.0 / (pi + pr * rat);
        fr = (gr * rat + gi) * scl;
        fi = (gi * rat - gr) * scl;
    }
    o0[0] = v[0] * fr - v[1] * fi;
    o0[1] = v[0] * fi + v[1] * fr;
    o1[0] = v[2] * fr - v[3] * fi;
    o1[1] = v[2] * fi + v[3] * fr;
}

/* the noise's band O1 turned (metacal.turned_band: O2[j, i] = phase[i] O1(-i, j), or for j < 0 the conjugate of
   (i, -j); rows r + 1 long) and added to the stamp's O0 */
static void turn_band(double *O0, const double *O1, double *O2, const double *PH, Py_ssize_t r)
{
    const Py_ssize_t w = r + 1;
    for (Py_ssize_t j = -r, p = 0; j <= r; j++) {
        for (Py_ssize_t i = 0; i <= r; i++, p++) {
            double br, bi;
            if (j >= 0) {
                br = O1[2 * ((r - i) * w + j)];
                bi = O1[2 * ((r - i) * w + j) + 1];
            } else {
                br = O1[2 * ((r + i) * w - j)];
                bi = -O1[2 * ((r + i) * w - j) + 1];
            }
            const double cr = PH[2 * i], ci = PH[2 * i + 1];
            O2[2 * p] = br * cr - bi * ci;
            O2[2 * p + 1] = br * ci + bi * cr;
            O0[2 * p] += O2[2 * p];
            O0[2 * p + 1] += O2[2 * p + 1];
        }
    }
}

/* band point (i, j)'s sky wavevector A dk (i, j) into s0, s1 and whether it lies within the band (its squared
   norm at most lim); outside, both products are set to zero */
static inline __attribute__((always_inline)) int band_sky(const double *A, double dk, Py_ssize_t i, Py_ssize_t j,
                                                           double lim, double *s0, double *s1, double *o0,
                                                           double *o1)
{
    const double k0 = dk * (double)i, k1 = dk * (double)j;
    *s0 = A[0] * k0 + A[1] * k1;
    *s1 = A[2] * k0 + A[3] * k1;
    if (*s0 * *s0 + *s1 * *s1 <= lim) return 1;
    o0[0] = o0[1] = o1[0] = o1[1] = 0.0;
    return 0;
}

/* band_sky's test, and the point's sheared wavevector in the stamp's pixels, q = JT (A kappa) */
static inline __attribute__((always_inline)) int band_pixel(const double *A, const double *JT, double dk,
                                                             Py_ssize_t i, Py_ssize_t j, double lim, double *q0,
                                                             double *q1, double *o0, double *o1)
{
    double s0, s1;
    if (!band_sky(A, dk, i, j, lim, &s0, &s1, o0, o1)) return 0;
    *q0 = JT[0] * s0 + JT[1] * s1;
    *q1 = JT[2] * s0 + JT[3] * s1;
    return 1;
}

/* quintic_band's rows in a block (see there) */
#define QB_ROWS 4
static PyObject *quintic_band(PyObject *self, PyObject *args)
{
    Py_buffer tab, ab, jb, gb, phb, ob;
    Py_ssize_t n, r, step;
    double dk, to_table, lim;
    if (!PyArg_ParseTuple(args, "y*nndy*y*ddy*ny*w*", &tab, &n, &r, &dk, &ab, &jb, &to_table, &lim, &gb, &step,
                          &phb, &ob))
        return NULL;
    const Py_ssize_t nc = n / 2 + 1, npts = (2 * r + 1) * (r + 1), cz = 2 * (Py_ssize_t)sizeof(double);
    /* nv versions (A: nv 2 x 2 matrices, out: nv blocks of 2 or 3 bands) */
    const Py_ssize_t nv = ab.len / (4 * (Py_ssize_t)sizeof(double));
    const int turn = nv > 0 && ob.len == nv * 3 * npts * cz;
    const Py_ssize_t nb = turn ? 3 : 2;
    if (n < 2 || r < 0 || tab.len != 3 * nc * n * cz || nv < 1 || ab.len != nv * 4 * (Py_ssize_t)sizeof(double)
        || jb.len != 4 * (Py_ssize_t)sizeof(double) || gb.len != npts * cz || (!turn && ob.len != nv * 2 * npts * cz)
        || (turn && phb.len != (r + 1) * cz) || step < 0 || step * r > n / 2 || (step > 0 && nv != 1)) {
        RELEASE(&tab, &ab, &jb, &gb, &phb, &ob);
        PyErr_SetString(PyExc_ValueError, "quintic_band: inconsistent buffers");
        return NULL;
    }
    const double *T = (const double *)tab.buf, *AV = (const double *)ab.buf, *JT = (const double *)jb.buf,
                 *G = (const double *)gb.buf, *PH = (const double *)phb.buf;
    double *OV = (double *)ob.buf;
    Py_BEGIN_ALLOW_THREADS
    /* the band in blocks of QB_ROWS rows, column by column within a block: a point's six table columns are
       its row neighbours' (three of them) and, a few taps up, its column neighbours' (whose cache lines are
       then still in L1) */
    for (Py_ssize_t j0 = -r; j0 <= r; j0 += QB_ROWS)
        for (Py_ssize_t i = 0; i <= r; i++)
            for (Py_ssize_t j = j0; j <= r && j < j0 + QB_ROWS; j++) {
                const Py_ssize_t p = (j + r) * (r + 1) + i;
                for (Py_ssize_t u = 0; u < nv; u++) {
                    const double *A = AV + 4 * u;
                    double *O0 = OV + 2 * nb * npts * u, *O1 = O0 + 2 * npts;
                    double s0, s1;
                    if (!band_sky(A, dk, i, j, lim, &s0, &s1, O0 + 2 * p, O1 + 2 * p)) continue;
                    double v[6];
                    if (step) {
                        const Py_ssize_t col = step * i, row = step * j < 0 ? step * j + n : step * j;
                        for (int t = 0; t < 3; t++) {
                            v[2 * t] = T[t * 2 * nc * n + 2 * (n * col + row)];
                            v[2 * t + 1] = T[t * 2 * nc * n + 2 * (n * col + row) + 1];
                        }
                    } else {
                        kvalue_point(T, n, 3, (JT[0] * s0 + JT[1] * s1) * to_table,
                                     (JT[2] * s0 + JT[3] * s1) * to_table, v);
                    }
                    band_products(v, v[4], v[5], G[2 * p], G[2 * p + 1], O0 + 2 * p, O1 + 2 * p);
                }
            }
    if (turn)
        for (Py_ssize_t u = 0; u < nv; u++) {
            double *O0 = OV + 2 * nb * npts * u, *O1 = O0 + 2 * npts;
            turn_band(O0, O1, O1 + 2 * npts, PH, r);
        }
    Py_END_ALLOW_THREADS
    RELEASE(&tab, &ab, &jb, &gb, &phb, &ob);
    Py_RETURN_NONE;
}

/* the x-interpolant's transform at u from its table at 0, h, 2 h, ... (even in u; zero beyond the table), by
   four-point Lagrange interpolation */
static inline double xtable(const double *X, Py_ssize_t nx, double h, double u)
{
    const double t = fabs(u) / h;
    Py_ssize_t i = (Py_ssize_t)t;
    if (i >= nx - 2) return 0.0;
    const double f = t - (double)i;
    const double xm = i > 0 ? X[i - 1] : X[1];   /* X(-h) = X(h) */
    return X[i] + f * (0.5 * (X[i + 1] - xm) + f * (xm - 2.5 * X[i] + 2.0 * X[i + 1] - 0.5 * X[i + 2]
                                                      + f * (1.5 * (X[i] - X[i + 1]) + 0.5 * (X[i + 2] - xm))));
}

/*
 * quintic_band_os(stamp, ns, psf, np, k, r, dk, A, JT, lim, gamma, xtab, xh, phase, out): quintic_band for a PSF
 * oversampled k times (calib/metacal.py's _oversampled_kspace_images, whose numpy lines are the reference): the
 * stamp's and its noise's table (2 planes, grid ns) at the sheared wavevector q = JT (A kappa) in the stamp's
 * pixels, the PSF's (1 plane, grid np) at q / k in its own, each times the x-interpolant's transform X there (xtab:
 * X at 0, xh, 2 xh, ..., interpolated), and out[t] = table t's value times gamma X(q) / (the PSF's value X(q / k));
 * with 3 outputs the noise's band turned and added as quintic_band does.
 */
static PyObject *quintic_band_os(PyObject *self, PyObject *args)
{
    Py_buffer sb, pb, ab, jb, gb, xb, phb, ob;
    Py_ssize_t ns, np_, k, r;
    double dk, lim, xh;
    if (!PyArg_ParseTuple(args, "y*ny*nnndy*y*dy*y*dy*w*", &sb, &ns, &pb, &np_, &k, &r, &dk, &ab, &jb, &lim, &gb, &xb,
                          &xh, &phb, &ob))
        return NULL;
    const Py_ssize_t npts = (2 * r + 1) * (r + 1), cz = 2 * (Py_ssize_t)sizeof(double);
    const Py_ssize_t nx = xb.len / (Py_ssize_t)sizeof(double);
    const int turn = ob.len == 3 * npts * cz;
    if (ns < 2 || np_ < 2 || k < 1 || r < 0 || sb.len != 2 * (ns / 2 + 1) * ns * cz
        || pb.len != (np_ / 2 + 1) * np_ * cz || ab.len != 4 * (Py_ssize_t)sizeof(double)
        || jb.len != 4 * (Py_ssize_t)sizeof(double) || gb.len != npts * cz || nx < 4 || !(xh > 0)
        || (!turn && ob.len != 2 * npts * cz) || (turn && phb.len != (r + 1) * cz)) {
        RELEASE(&sb, &pb, &ab, &jb, &gb, &xb, &phb, &ob);
        PyErr_SetString(PyExc_ValueError, "quintic_band_os: inconsistent buffers");
        return NULL;
    }
    const double *S = (const double *)sb.buf, *P = (const double *)pb.buf, *A = (const double *)ab.buf,
                 *JT = (const double *)jb.buf, *G = (const double *)gb.buf, *X = (const double *)xb.buf,
                 *PH = (const double *)phb.buf;
    double *O0 = (double *)ob.buf, *O1 = O0 + 2 * npts;
    const double to_s = (double)ns / (2 * M_PI), to_p = (double)np_ / (2 * M_PI) / (double)k, ik = 1.0 / (double)k;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = -r, p = 0; j <= r; j++) {
        for (Py_ssize_t i = 0; i <= r; i++, p++) {
            double q0, q1;
            if (!band_pixel(A, JT, dk, i, j, lim, &q0, &q1, O0 + 2 * p, O1 + 2 * p)) continue;
            double v[4], w[2];
            kvalue_point(S, ns, 2, q0 * to_s, q1 * to_s, v);
            kvalue_point(P, np_, 1, q0 * to_p, q1 * to_p, w);
            const double xs = xtable(X, nx, xh, q0) * xtable(X, nx, xh, q1);
            const double xp = xtable(X, nx, xh, q0 * ik) * xtable(X, nx, xh, q1 * ik);
            band_products(v, w[0] * xp, w[1] * xp, G[2 * p] * xs, G[2 * p + 1] * xs, O0 + 2 * p, O1 + 2 * p);
        }
    }
    if (turn) turn_band(O0, O1, O1 + 2 * npts, PH, r);
    Py_END_ALLOW_THREADS
    RELEASE(&sb, &pb, &ab, &jb, &gb, &xb, &phb, &ob);
    Py_RETURN_NONE;
}

/*
 * quintic_band_rows(stamp, ns, psf_rows, psf, np, k, r, dk, A, JT, lim, gamma, xtab, xh, step, phase, out): quintic_band_os
 * for a PSF whose padded grid is k times the stamp's (np = k ns), the stamp's and its noise's transforms given in
 * rows (kspace.padded_transforms_rows: complex128 (ns, ns / 2 + 1, 2), ky, then kx, then the image) and the PSF's
 * at the same wavevectors in the same rows (psf_rows: complex128 (ns, ns / 2 + 1), the PSF's padded table at
 * wavevectors within half the stamp's period; psf: that table whole, as quintic_band_os takes it). A point's
 * wavevector is then the same in both tables' units, so they share its taps and weights; the six taps of a row
 * are adjacent in memory, and a band row's points, which step along kx, read the tables' rows in order. Points
 * whose taps reach half the stamp's period read the stamp with its periodic and Hermitian wrap and the PSF from its
 * whole table, as quintic_band_os does. With step > 0, the version without shear, whose points are the tables' own
 * (step i, step j), reads them there (as quintic_band does), and takes the x-interpolant's transforms at the band's
 * own wavevectors dk (i, j) (its q = JT (A kappa) to rounding). The numbers of quintic_band_os to rounding (the sums
 * taken rows first, in pairs). A may hold nv versions' matrices (nv x 2 x 2, step 0) and out their bands one after
 * another (nv blocks of 2 or 3): each version's band is that of its own call, to the bit, the versions taken point
 * by point.
 */
typedef double v4r __attribute__((vector_size(32)));
typedef double v2r __attribute__((vector_size(16)));
/* the same vectors at any double's address (unaligned loads, as v4u's) */
typedef double v2u __attribute__((vector_size(2 * sizeof(double)), aligned(sizeof(double))));
static inline v4r load4(const double *p) { return *(const v4u *)p; }
static inline v2r load2(const double *p) { return *(const v2u *)p; }

/* the stamp's two values (re, im, re, im) at tap (kx, ky) of the rows, any integers: periodic in n, kx > n / 2 or
   kx < 0 read from its Hermitian mirror */
static inline v4r rows_tap_wrapped(const double *SR, Py_ssize_t n, Py_ssize_t kx, Py_ssize_t ky)
{
    const Py_ssize_t nc = n / 2 + 1;
    kx = ((kx % n) + n) % n;
    ky = ((ky % n) + n) % n;
    v4r x;
    if (kx <= n / 2) {
        memcpy(&x, SR + 4 * (ky * nc + kx), sizeof x);
        return x;
    }
    memcpy(&x, SR + 4 * (((n - ky) % n) * nc + (n - kx)), sizeof x);
    const v4r conj = {1.0, -1.0, 1.0, -1.0};
    return x * conj;
}

/* one point's stamp values (v[0 .. 3]) and PSF value (v[4], v[5]) from the rows, first taps ix, iy (floor - 2);
   returns 0 where a tap lies outside (-n / 2, n / 2) (the PSF's rows do not hold it: the caller reads its table) */
static inline __attribute__((always_inline)) int rows_point(const double *restrict SR, const double *restrict PR,
                                                            Py_ssize_t n, Py_ssize_t ix, Py_ssize_t iy,
                                                            const double *wx, const double *wy, double *v)
{
    const Py_ssize_t nc = n / 2 + 1, h = n / 2;
    const int inside = ix > -h && ix + 5 < h && iy > -h && iy + 5 < h;
    v4r rs[6];
    v2r rp[6];
    if (inside && ix >= 0) {
        /* the usual point: each row's six taps adjacent, kx >= 0 */
        for (int b = 0; b < 6; b++) {
            const Py_ssize_t ky = iy + b, row = ky < 0 ? ky + n : ky;
            const double *s = SR + 4 * (row * nc + ix), *p = PR + 2 * (row * nc + ix);
            /* (the taps loaded straight into the products: copied first into arrays of vectors, which GCC made
               for x86-64-v3 as a loop of 16-byte stores read back as 32-byte loads, every load stalled on its
               two stores: the loop took half as long again as for v4) */
            rs[b] = ((wx[0] * load4(s) + wx[1] * load4(s + 4)) + (wx[2] * load4(s + 8) + wx[3] * load4(s + 12)))
                    + (wx[4] * load4(s + 16) + wx[5] * load4(s + 20));
            rp[b] = ((wx[0] * load2(p) + wx[1] * load2(p + 2)) + (wx[2] * load2(p + 4) + wx[3] * load2(p + 6)))
                    + (wx[4] * load2(p + 8) + wx[5] * load2(p + 10));
        }
    } else {
        /* taps at kx < 0 (their Hermitian mirrors), or beyond half the period (the stamp periodic) */
        const v2r conj2 = {1.0, -1.0};
        for (int b = 0; b < 6; b++) {
            const Py_ssize_t ky = iy + b;
            v4r x[6];
            v2r y[6];
            for (int a = 0; a < 6; a++) {
                const Py_ssize_t kx = ix + a;
                x[a] = rows_tap_wrapped(SR, n, kx, ky);
                if (inside) {
                    const Py_ssize_t mx = kx < 0 ? -kx : kx, my = kx < 0 ? -ky : ky, row = my < 0 ? my + n : my;
                    memcpy(&y[a], PR + 2 * (row * nc + mx), sizeof y[a]);
                    if (kx < 0) y[a] = y[a] * conj2;
                } else {
                    y[a] = (v2r){0.0, 0.0};
                }
            }
            rs[b] = ((wx[0] * x[0] + wx[1] * x[1]) + (wx[2] * x[2] + wx[3] * x[3])) + (wx[4] * x[4] + wx[5] * x[5]);
            rp[b] = ((wx[0] * y[0] + wx[1] * y[1]) + (wx[2] * y[2] + wx[3] * y[3])) + (wx[4] * y[4] + wx[5] * y[5]);
        }
    }
    const v4r st = ((wy[0] * rs[0] + wy[1] * rs[1]) + (wy[2] * rs[2] + wy[3] * rs[3])) + (wy[4] * rs[4] + wy[5] * rs[5]);
    const v2r ps = ((wy[0] * rp[0] + wy[1] * rp[1]) + (wy[2] * rp[2] + wy[3] * rp[3])) + (wy[4] * rp[4] + wy[5] * rp[5]);
    v[0] = st[0];
    v[1] = st[1];
    v[2] = st[2];
    v[3] = st[3];
    v[4] = ps[0];
    v[5] = ps[1];
    return inside;
}

static PyObject *quintic_band_rows(PyObject *self, PyObject *args)
{
    Py_buffer sb, cb, pb, ab, jb, gb, xb, phb, ob;
    Py_ssize_t ns, np_, k, r, step;
    double dk, lim, xh;
    if (!PyArg_ParseTuple(args, "y*ny*y*nnndy*y*dy*y*dny*w*", &sb, &ns, &cb, &pb, &np_, &k, &r, &dk, &ab, &jb, &lim,
                          &gb, &xb, &xh, &step, &phb, &ob))
        return NULL;
    const Py_ssize_t npts = (2 * r + 1) * (r + 1), cz = 2 * (Py_ssize_t)sizeof(double);
    const Py_ssize_t nx = xb.len / (Py_ssize_t)sizeof(double), nc = ns / 2 + 1;
    /* nv versions (A: nv 2 x 2 matrices, out: nv blocks of 2 or 3 bands) */
    const Py_ssize_t nv = ab.len / (4 * (Py_ssize_t)sizeof(double));
    const int turn = nv > 0 && ob.len == nv * 3 * npts * cz;
    const Py_ssize_t nb = turn ? 3 : 2;
    if (ns < 12 || k < 1 || np_ != k * ns || r < 0 || sb.len != 2 * nc * ns * cz || cb.len != nc * ns * cz
        || pb.len != (np_ / 2 + 1) * np_ * cz || nv < 1 || ab.len != nv * 4 * (Py_ssize_t)sizeof(double)
        || jb.len != 4 * (Py_ssize_t)sizeof(double) || gb.len != npts * cz || nx < 4 || !(xh > 0)
        || (!turn && ob.len != nv * 2 * npts * cz) || (turn && phb.len != (r + 1) * cz) || step < 0
        || step * r >= ns / 2 || (step > 0 && nv != 1)) {
        RELEASE(&sb, &cb, &pb, &ab, &jb, &gb, &xb, &phb, &ob);
        PyErr_SetString(PyExc_ValueError, "quintic_band_rows: inconsistent buffers");
        return NULL;
    }
    const double *SR = (const double *)sb.buf, *PR = (const double *)cb.buf, *P = (const double *)pb.buf,
                 *AV = (const double *)ab.buf, *JT = (const double *)jb.buf, *G = (const double *)gb.buf,
                 *X = (const double *)xb.buf, *PH = (const double *)phb.buf;
    double *OV = (double *)ob.buf;
    /* (np = k ns: a wavevector's position in the PSF's table units is the stamp's) */
    const double to_s = (double)ns / (2 * M_PI), ik = 1.0 / (double)k;
    /* the version without shear: its points are the tables' own and its wavevectors the band's kappa = dk (i, j),
       so the x-interpolant's transforms are products of one factor in i and one in |j| (X is even), taken once
       per band from the table: X(dk i), X(dk |j|), and at them over k */
    double *XB = NULL;
    if (step) {
        XB = (double *)malloc(2 * (r + 1) * sizeof(double));
        if (XB == NULL) {
            RELEASE(&sb, &cb, &pb, &ab, &jb, &gb, &xb, &phb, &ob);
            return PyErr_NoMemory();
        }
        for (Py_ssize_t i = 0; i <= r; i++) {
            const double ki = dk * (double)i;
            XB[i] = xtable(X, nx, xh, ki);
            XB[(r + 1) + i] = xtable(X, nx, xh, ki * ik);
        }
    }
    Py_BEGIN_ALLOW_THREADS
    if (step) {
        const double *A = AV, *XS = XB, *XP = XB + (r + 1);
        double *O0 = OV, *O1 = O0 + 2 * npts;
        for (Py_ssize_t j = -r, p = 0; j <= r; j++) {
            const Py_ssize_t aj = j < 0 ? -j : j, row = step * j < 0 ? step * j + ns : step * j;
            for (Py_ssize_t i = 0; i <= r; i++, p++) {
                double s0, s1;
                if (!band_sky(A, dk, i, j, lim, &s0, &s1, O0 + 2 * p, O1 + 2 * p)) continue;
                const Py_ssize_t e = row * nc + step * i;
                double v[4];
                memcpy(v, SR + 4 * e, 4 * sizeof(double));
                const double xs = XS[i] * XS[aj], xp = XP[i] * XP[aj];
                band_products(v, PR[2 * e] * xp, PR[2 * e + 1] * xp, G[2 * p] * xs, G[2 * p + 1] * xs, O0 + 2 * p,
                              O1 + 2 * p);
            }
        }
    }
    /* the sheared versions point by point: their sheared wavevectors lie close together, so that every version reads
       the tables' rows while the first one's reading keeps them in the cache (one after another, each version
       fetched the tables, larger than a core's L2 cache, again) */
    for (Py_ssize_t j = -r, p = 0; j <= r && !step; j++) {
        for (Py_ssize_t i = 0; i <= r; i++, p++) {
            for (Py_ssize_t u = 0; u < nv; u++) {
                const double *A = AV + 4 * u;
                double *O0 = OV + 2 * nb * npts * u, *O1 = O0 + 2 * npts;
                double q0, q1;
                if (!band_pixel(A, JT, dk, i, j, lim, &q0, &q1, O0 + 2 * p, O1 + 2 * p)) continue;
                const double tx = q0 * to_s, ty = q1 * to_s;
                double v[6];
                const double fx = floor(tx), fy = floor(ty);
                double wx[6], wy[6];
                quintic_weights(tx - fx, ty - fy, wx, wy);
                if (!rows_point(SR, PR, ns, (Py_ssize_t)fx - 2, (Py_ssize_t)fy - 2, wx, wy, v))
                    kvalue_point(P, np_, 1, tx, ty, v + 4);
                const double xs = xtable(X, nx, xh, q0) * xtable(X, nx, xh, q1);
                const double xp = xtable(X, nx, xh, q0 * ik) * xtable(X, nx, xh, q1 * ik);
                band_products(v, v[4] * xp, v[5] * xp, G[2 * p] * xs, G[2 * p + 1] * xs, O0 + 2 * p, O1 + 2 * p);
            }
        }
    }
    if (turn)
        for (Py_ssize_t u = 0; u < nv; u++) {
            double *O0 = OV + 2 * nb * npts * u, *O1 = O0 + 2 * npts;
            turn_band(O0, O1, O1 + 2 * npts, PH, r);
        }
    Py_END_ALLOW_THREADS
    free(XB);
    RELEASE(&sb, &cb, &pb, &ab, &jb, &gb, &xb, &phb, &ob);
    Py_RETURN_NONE;
}

/*
 * band_rings(column, xx2, labels, thr, out, near): calib/kspace.band_edge's count per ring: out[b] (int64, zeroed here)
 * the number of the points q of column (complex128, flat: kx index, then ky index) of labels[q] = b (int32, the rings
 * of band_edge; none counted at or beyond out's length) where |column[q]| xx[q] > thr, numpy's test (its |z| is
 * hypot), decided by |column[q]|^2 xx2[q] against thr^2 (xx2: xx^2, float64) where these differ by more than 1e-12
 * of it (their rounding is some 1e-16). The points within 1e-12 are left to the caller for numpy's own test: their
 * flat indices written into near (int64; their number returned, -1 where near had too little room).
 */
static PyObject *band_rings(PyObject *self, PyObject *args)
{
    Py_buffer col, xb, lb, ob, nb_;
    double thr;
    if (!PyArg_ParseTuple(args, "y*y*y*dw*w*", &col, &xb, &lb, &thr, &ob, &nb_)) return NULL;
    const Py_ssize_t d = (Py_ssize_t)sizeof(double), nbin = ob.len / (Py_ssize_t)sizeof(long long);
    const Py_ssize_t npts = col.len / (2 * d), nnear = nb_.len / (Py_ssize_t)sizeof(long long);
    if (npts < 1 || xb.len < npts * d || lb.len < npts * (Py_ssize_t)sizeof(int) || nbin < 1) {
        RELEASE(&col, &xb, &lb, &ob, &nb_);
        PyErr_SetString(PyExc_ValueError, "band_rings: inconsistent buffers");
        return NULL;
    }
    const double *P = col.buf, *XX2 = xb.buf;
    const int *L = lb.buf;
    long long *O = ob.buf, *NEAR = nb_.buf;
    Py_ssize_t found = 0;
    Py_BEGIN_ALLOW_THREADS
    const double t2 = thr * thr, hi = t2 * (1 + 1e-12), lo = t2 * (1 - 1e-12);
    for (Py_ssize_t b = 0; b < nbin; b++) O[b] = 0;
    for (Py_ssize_t q = 0; q < npts; q++) {
        const double s2 = (P[2 * q] * P[2 * q] + P[2 * q + 1] * P[2 * q + 1]) * XX2[q];
        if (s2 > hi) {
            const int b = L[q];
            if (b < nbin) O[b] += 1;
        } else if (s2 >= lo) {
            if (found < nnear) NEAR[found] = q;
            found++;
        }
    }
    Py_END_ALLOW_THREADS
    RELEASE(&col, &xb, &lb, &ob, &nb_);
    return PyLong_FromSsize_t(found <= nnear ? found : -1);
}

/*
 * The App. A Moffat's alias tables (model._moffat_table, model._moffat_aliases, whose numpy lines stay as the
 * reference and the fallback; tests check they agree).
 *
 * hermite_log_table(k0, dk, nodes, lv, slope, out): out[i] for i from nodes[0] to nodes[-1] - 1 (k = k0 + i dk)
 * the exponential of the cubic Hermite interpolant of a logarithm through the nodes (table indices, increasing),
 * with values lv and slopes d/dk there; the rest of out untouched.
 */
static void hermite_log_fill(double k0, double dk, const int64_t *N, Py_ssize_t m, const double *LV,
                             const double *SL, const double *CU, double *O)
{
    /* the quintic Hermite interpolant of the logarithm on each segment: values, slopes and curvatures at both
       ends (model._moffat_table's numpy lines, term for term) */
    for (Py_ssize_t s = 0; s + 1 < m; s++) {
        const double ka = k0 + (double)N[s] * dk, h = (double)(N[s + 1] - N[s]) * dk;
        const double a0 = LV[s], a1 = h * SL[s], a2 = h * h * CU[s];
        const double b0 = LV[s + 1], b1 = h * SL[s + 1], b2 = h * h * CU[s + 1];
        for (int64_t i = N[s]; i < N[s + 1]; i++) {
            const double t = (k0 + (double)i * dk - ka) / h, t2 = t * t, t3 = t2 * t, t4 = t3 * t, t5 = t4 * t;
            const double h0 = 1 - 10 * t3 + 15 * t4 - 6 * t5, h1 = t - 6 * t3 + 8 * t4 - 3 * t5;
            const double h2 = 0.5 * (t2 - 3 * t3 + 3 * t4 - t5), g0 = 10 * t3 - 15 * t4 + 6 * t5;
            const double g1 = -4 * t3 + 7 * t4 - 3 * t5, g2 = 0.5 * (t3 - 2 * t4 + t5);
            O[i] = h0 * a0 + h1 * a1 + h2 * a2 + g0 * b0 + g1 * b1 + g2 * b2;
        }
    }
    vexp_shift(O + N[0], 0.0, O + N[0], (Py_ssize_t)(N[m - 1] - N[0]));
}

static PyObject *hermite_log_table(PyObject *self, PyObject *args)
{
    double k0, dk;
    Py_buffer nb, lvb, slb, cub, out;
    if (!PyArg_ParseTuple(args, "ddy*y*y*y*w*", &k0, &dk, &nb, &lvb, &slb, &cub, &out)) return NULL;
    const Py_ssize_t m = nb.len / (Py_ssize_t)sizeof(int64_t), nout = out.len / (Py_ssize_t)sizeof(double);
    const int64_t *N = (const int64_t *)nb.buf;
    int bad = m < 2 || lvb.len != m * (Py_ssize_t)sizeof(double) || slb.len != lvb.len || cub.len != lvb.len;
    for (Py_ssize_t s = 0; !bad && s < m; s++)
        bad = N[s] < 0 || N[s] >= nout || (s > 0 && N[s] <= N[s - 1]);
    if (bad) {
        RELEASE(&nb, &lvb, &slb, &cub, &out);
        PyErr_SetString(PyExc_ValueError, "hermite_log_table: inconsistent buffers");
        return NULL;
    }
    const double *LV = (const double *)lvb.buf, *SL = (const double *)slb.buf, *CU = (const double *)cub.buf;
    double *O = (double *)out.buf;
    Py_BEGIN_ALLOW_THREADS
    hermite_log_fill(k0, dk, N, m, LV, SL, CU, O);
    Py_END_ALLOW_THREADS
    RELEASE(&nb, &lvb, &slb, &cub, &out);
    Py_RETURN_NONE;
}

/*
 * alias_sums(table, i0, w0, w1, kept, A, Gs[, G2max]): G = table[i0] w0 + table[i0 + 1] w1 at every alias of every
 * mode (i0, w0, w1: n_alias blocks of n modes, alias after alias), A[j] = the sum of G over the aliases of mode j
 * (in alias order), and Gs = G of the aliases listed in kept, block after block; G2max[j], if given, the largest
 * G^2 of mode j over the kept aliases.
 */
/* each mode's largest |G|^2 over the nk kept aliases' transforms G (nk blocks of n; model.py's G2max: |G|
   squared is G squared) */
static void kept_g2max(const double *G, Py_ssize_t nk, Py_ssize_t n, double *M)
{
    for (Py_ssize_t j = 0; j < n; j++) M[j] = G[j] * G[j];
    for (Py_ssize_t c = 1; c < nk; c++) {
        const double *Gc = G + c * n;
        for (Py_ssize_t j = 0; j < n; j++) {
            const double v = Gc[j] * Gc[j];
            M[j] = v > M[j] ? v : M[j];
        }
    }
}

static PyObject *alias_sums(PyObject *self, PyObject *args)
{
    Py_buffer tb, ib, w0b, w1b, kb, ab, gb, mb = {0};
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*w*|w*", &tb, &ib, &w0b, &w1b, &kb, &ab, &gb, &mb)) return NULL;
    const Py_ssize_t ntab = tb.len / (Py_ssize_t)sizeof(double), n = ab.len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t total = ib.len / (Py_ssize_t)sizeof(int64_t), nk = kb.len / (Py_ssize_t)sizeof(int64_t);
    const Py_ssize_t na = n > 0 ? total / n : 0;
    const int64_t *I = (const int64_t *)ib.buf, *K = (const int64_t *)kb.buf;
    int bad = n < 1 || na * n != total || w0b.len != total * (Py_ssize_t)sizeof(double) || w1b.len != w0b.len
              || gb.len != nk * n * (Py_ssize_t)sizeof(double)
              || (mb.buf != NULL && mb.len != n * (Py_ssize_t)sizeof(double));
    for (Py_ssize_t a = 0; !bad && a < nk; a++) bad = K[a] < 0 || K[a] >= na;
    for (Py_ssize_t e = 0; !bad && e < total; e++) bad = I[e] < 0 || I[e] + 1 >= ntab;
    if (bad) {
        RELEASE(&tb, &ib, &w0b, &w1b, &kb, &ab, &gb);
        if (mb.buf != NULL) PyBuffer_Release(&mb);
        PyErr_SetString(PyExc_ValueError, "alias_sums: inconsistent buffers");
        return NULL;
    }
    const double *T = (const double *)tb.buf, *W0 = (const double *)w0b.buf, *W1 = (const double *)w1b.buf;
    double *A = (double *)ab.buf, *G = (double *)gb.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++) A[j] = 0.0;
    /* the aliases in order; a kept one's transform (its G) is made once and added to the sum from there, the
       same numbers as adding it directly */
    for (Py_ssize_t a = 0; a < na; a++) {
        const int64_t *Ia = I + a * n;
        const double *Wa = W0 + a * n, *Wb = W1 + a * n;
        Py_ssize_t c = 0;
        while (c < nk && K[c] != a) c++;
        if (c < nk) {
            double *Gc = G + c * n;
            for (Py_ssize_t j = 0; j < n; j++) {
                Gc[j] = T[Ia[j]] * Wa[j] + T[Ia[j] + 1] * Wb[j];
                A[j] += Gc[j];
            }
            /* a kept alias listed twice gets its copy too */
            for (Py_ssize_t d = c + 1; d < nk; d++)
                if (K[d] == a) memcpy(G + d * n, Gc, n * sizeof(double));
        } else {
            for (Py_ssize_t j = 0; j < n; j++) A[j] += T[Ia[j]] * Wa[j] + T[Ia[j] + 1] * Wb[j];
        }
    }
    if (mb.buf != NULL) kept_g2max(G, nk, n, (double *)mb.buf);
    Py_END_ALLOW_THREADS
    RELEASE(&tb, &ib, &w0b, &w1b, &kb, &ab, &gb);
    if (mb.buf != NULL) PyBuffer_Release(&mb);
    Py_RETURN_NONE;
}

/*
 * alias_sums_mirror(table, i0, w0, w1, kept, A, Gs, G2max, ny, nxh, side): alias_sums' numbers for the alias
 * tables of an rfft grid (ny rows of nxh modes, side x side aliases n = (ny_a, nx_a), alias a = ny_a side +
 * nx_a, the offsets symmetric), made from half of its rows. Row ny - r (ky -> -ky) holds the mirror image of row r:
 * its alias (ny_a, nx_a) is row r's (side - 1 - ny_a, nx_a), every |k + 2 pi n| and pixel response the same to the
 * bit (model._alias_geometry: a test checks it), so its transforms are row r's read in the mirrored order and its
 * sum A is added up in alias order from them, as alias_sums does: the same numbers, half the interpolations.
 */
static PyObject *alias_sums_mirror(PyObject *self, PyObject *args)
{
    Py_buffer tb, ib, w0b, w1b, kb, ab, gb, mb;
    Py_ssize_t ny, nxh, side;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*w*w*nnn", &tb, &ib, &w0b, &w1b, &kb, &ab, &gb, &mb, &ny, &nxh, &side))
        return NULL;
    const Py_ssize_t ntab = tb.len / (Py_ssize_t)sizeof(double), n = ab.len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t total = ib.len / (Py_ssize_t)sizeof(int64_t), nk = kb.len / (Py_ssize_t)sizeof(int64_t);
    const Py_ssize_t na = side * side;
    const int64_t *I = (const int64_t *)ib.buf, *K = (const int64_t *)kb.buf;
    int bad = n < 1 || ny < 1 || nxh < 1 || side < 1 || ny * nxh != n || na * n != total
              || w0b.len != total * (Py_ssize_t)sizeof(double) || w1b.len != w0b.len
              || gb.len != nk * n * (Py_ssize_t)sizeof(double) || mb.len != n * (Py_ssize_t)sizeof(double) || nk < 1;
    /* the rows computed: 0 .. nsrc - 1 (row 0, ky = 0, is its own mirror; an even grid's Nyquist row too); only
       their table indices are read */
    const Py_ssize_t nsrc = ny / 2 + 1, m = nsrc * nxh;
    for (Py_ssize_t a = 0; !bad && a < nk; a++) bad = K[a] < 0 || K[a] >= na;
    for (Py_ssize_t a = 0; !bad && a < na; a++) {
        const int64_t *Ia = I + a * n;
        int64_t lo = 0, hi = 0;
        for (Py_ssize_t j = 0; j < m; j++) {
            lo = Ia[j] < lo ? Ia[j] : lo;
            hi = Ia[j] > hi ? Ia[j] : hi;
        }
        bad = lo < 0 || hi + 1 >= ntab;
    }
    if (bad) {
        RELEASE(&tb, &ib, &w0b, &w1b, &kb, &ab, &gb, &mb);
        PyErr_SetString(PyExc_ValueError, "alias_sums_mirror: inconsistent buffers");
        return NULL;
    }
    double *Gall = (double *)malloc((size_t)(na * m) * sizeof(double));
    if (Gall == NULL) {
        RELEASE(&tb, &ib, &w0b, &w1b, &kb, &ab, &gb, &mb);
        return PyErr_NoMemory();
    }
    const double *T = (const double *)tb.buf, *W0 = (const double *)w0b.buf, *W1 = (const double *)w1b.buf;
    double *A = (double *)ab.buf, *G = (double *)gb.buf, *M = (double *)mb.buf;
    Py_BEGIN_ALLOW_THREADS
    /* every alias's transform at the source rows (their modes are the first m of each alias's block) */
    for (Py_ssize_t a = 0; a < na; a++) {
        const int64_t *Ia = I + a * n;
        const double *Wa = W0 + a * n, *Wb = W1 + a * n;
        double *Ga = Gall + a * m;
        for (Py_ssize_t j = 0; j < m; j++) Ga[j] = T[Ia[j]] * Wa[j] + T[Ia[j] + 1] * Wb[j];
    }
    for (Py_ssize_t r = 0; r < ny; r++) {
        const int mirrored = r >= nsrc;
        const Py_ssize_t src = mirrored ? ny - r : r;
        double *Ar = A + r * nxh;
        for (Py_ssize_t c = 0; c < nxh; c++) Ar[c] = 0.0;
        for (Py_ssize_t a = 0; a < na; a++) {
            const Py_ssize_t b = mirrored ? (side - 1 - a / side) * side + a % side : a;
            const double *Gb = Gall + b * m + src * nxh;
            for (Py_ssize_t c = 0; c < nxh; c++) Ar[c] += Gb[c];
        }
        for (Py_ssize_t k = 0; k < nk; k++) {
            const Py_ssize_t a = (Py_ssize_t)K[k];
            const Py_ssize_t b = mirrored ? (side - 1 - a / side) * side + a % side : a;
            memcpy(G + k * n + r * nxh, Gall + b * m + src * nxh, nxh * sizeof(double));
        }
    }
    kept_g2max(G, nk, n, M);
    Py_END_ALLOW_THREADS
    free(Gall);
    RELEASE(&tb, &ib, &w0b, &w1b, &kb, &ab, &gb, &mb);
    Py_RETURN_NONE;
}

/*
 * fine_modes_select(Ps, A, ok, absG, Gs, absG2max, kyv, kxv, dx, dy, s, ny, nxh, tolerance, ky, kx, T, c) -> m:
 * model.py's _fine_modes_moffat for one PSF, in one pass over its aliases instead of eight array operations.
 * The ratio Ps / A of every sampled mode (Ps: complex, A: float64, ok: uint8, nc = ny nxh each; 0 where not
 * ok); of the s x s aliases of every mode (absG = |G|, Gs = G: float64, (s, s, ny, nxh) flattened) those where
 * |G| |ratio| exceeds tolerance times its largest value (found from absG2max, each mode's largest |G|^2 over
 * its aliases), in that order: their wavevectors (kyv: s ny values, kxv: s nxh), transfer
 * G ratio exp(-i (kx dx + ky dy)) (the phase that puts the model's origin at (dx, dy) pixels) and sampled mode,
 * written to the first m entries of ky, kx (float64), T (complex) and c (int64). The test is made on the
 * squares, |G|^2 |ratio|^2 > tolerance^2 max: the same modes as the numpy lines' up to a rounding at the edge.
 */
static PyObject *fine_modes_select(PyObject *self, PyObject *args)
{
    Py_buffer psb, ab, okb, agb, gb, gmb, kyb, kxb, oyb, oxb, otb, ocb;
    int s;
    Py_ssize_t ny, nxh;
    double tol, dx, dy;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*ddinndw*w*w*w*", &psb, &ab, &okb, &agb, &gb, &gmb, &kyb, &kxb, &dx,
                          &dy, &s, &ny, &nxh, &tol, &oyb, &oxb, &otb, &ocb))
        return NULL;
#define FM_RELEASE RELEASE(&psb, &ab, &okb, &agb, &gb, &gmb, &kyb, &kxb, &oyb, &oxb, &otb, &ocb)
    const Py_ssize_t nc = ny * nxh, na = (Py_ssize_t)s * s, n = na * nc, d = (Py_ssize_t)sizeof(double);
    const int bad = s < 1 || ny < 1 || nxh < 1 || psb.len != 2 * nc * d || ab.len != nc * d || okb.len != nc
                    || agb.len != n * d || gb.len != n * d || gmb.len != nc * d || kyb.len != s * ny * d
                    || kxb.len != s * nxh * d || oyb.len < n * d || oxb.len < n * d || otb.len < 2 * n * d
                    || ocb.len < n * (Py_ssize_t)sizeof(int64_t);
    if (bad) {
        FM_RELEASE;
        PyErr_SetString(PyExc_ValueError, "fine_modes_select: inconsistent buffers");
        return NULL;
    }
    double *rbuf = (double *)malloc(3 * nc * sizeof(double));
    if (rbuf == NULL) {
        FM_RELEASE;
        return PyErr_NoMemory();
    }
    const double *PS = (const double *)psb.buf, *AA = (const double *)ab.buf, *AG = (const double *)agb.buf;
    const double *G = (const double *)gb.buf, *KY = (const double *)kyb.buf, *KX = (const double *)kxb.buf;
    const double *GM = (const double *)gmb.buf;
    const unsigned char *OK = (const unsigned char *)okb.buf;
    double *oy = (double *)oyb.buf, *ox = (double *)oxb.buf, *ot = (double *)otb.buf;
    int64_t *oc = (int64_t *)ocb.buf;
    double *RR = rbuf, *RI = rbuf + nc, *RA = rbuf + 2 * nc;
    /* the phases of the rows and columns of the aliases: exp(-i (ky dy)), exp(-i (kx dx)) */
    double *PHY = (double *)malloc(2 * (s * ny + s * nxh) * sizeof(double)), *PHX = PHY + 2 * s * ny;
    Py_ssize_t m = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < nc; j++) {
        RR[j] = OK[j] ? PS[2 * j] / AA[j] : 0.0;
        RI[j] = OK[j] ? PS[2 * j + 1] / AA[j] : 0.0;
        RA[j] = RR[j] * RR[j] + RI[j] * RI[j];   /* |ratio|^2: the test below is on squares */
    }
    double top = 0.0;   /* the largest |G|^2 |ratio|^2, from each mode's largest |G|^2 over its aliases */
    for (Py_ssize_t j = 0; j < nc; j++) {
        const double v = GM[j] * RA[j];
        top = v > top ? v : top;
    }
    const double thr = tol * tol * top;
    if (PHY != NULL) {
        for (Py_ssize_t i = 0; i < s * ny; i++) {
            PHY[2 * i] = cos(KY[i] * dy);
            PHY[2 * i + 1] = -sin(KY[i] * dy);
        }
        for (Py_ssize_t i = 0; i < s * nxh; i++) {
            PHX[2 * i] = cos(KX[i] * dx);
            PHX[2 * i + 1] = -sin(KX[i] * dx);
        }
        for (Py_ssize_t a = 0; a < na; a++) {
            const Py_ssize_t ay = a / s, ax = a % s;
            for (Py_ssize_t y = 0; y < ny; y++) {
                const Py_ssize_t iy = ay * ny + y;
                const double py_r = PHY[2 * iy], py_i = PHY[2 * iy + 1], kyy = KY[iy];
                const double *agr = AG + a * nc + y * nxh, *gr = G + a * nc + y * nxh;
                const double *rr = RR + y * nxh, *ri = RI + y * nxh, *ra = RA + y * nxh;
                const double *kxr = KX + ax * nxh, *phx = PHX + 2 * ax * nxh;
                for (Py_ssize_t x = 0; x < nxh; x++) {
                    if (!(agr[x] * agr[x] * ra[x] > thr)) continue;   /* kept modes come in runs along a row */
                    const double tr = gr[x] * rr[x], ti = gr[x] * ri[x];
                    const double hr = phx[2 * x] * py_r - phx[2 * x + 1] * py_i;
                    const double hi = phx[2 * x] * py_i + phx[2 * x + 1] * py_r;
                    oy[m] = kyy;
                    ox[m] = kxr[x];
                    ot[2 * m] = tr * hr - ti * hi;
                    ot[2 * m + 1] = tr * hi + ti * hr;
                    oc[m] = (int64_t)(y * nxh + x);
                    m++;
                }
            }
        }
    }
    Py_END_ALLOW_THREADS
    const int failed = PHY == NULL;
    free(PHY);
    free(rbuf);
    FM_RELEASE;
#undef FM_RELEASE
    if (failed) return PyErr_NoMemory();
    return PyLong_FromSsize_t(m);
}

/* the instruction-set level this module was compiled for */
static PyObject *kernel_isa(PyObject *self, PyObject *args)
{
    return PyUnicode_FromString(KERNEL_LEVEL);
}

/*
 * The App. A Moffat's fit (moffat._levenberg_marquardt, whose numpy lines stay as the reference and the
 * fallback; a test checks they agree): the same Levenberg-Marquardt, row after row, with scipy.special's own
 * kv and gamma (their cython_special C entry points, given once by set_bessel).
 *
 * moffat_lm(kr, VR, P, free0, free1, max_iter, ftol, xtol): P (m rows of (log rs, log(beta - 1))) fitted in
 * place, row r to the ring averages VR[r] at the n wavenumbers kr; free0, free1: which parameters vary.
 */
typedef double (*kv_fn)(double, double, int);
static kv_fn sp_kv = NULL;
static special_fn sp_gamma = NULL;
static const char *KV_SIG = "double (double, double, int __pyx_skip_dispatch)";

static PyObject *set_bessel(PyObject *self, PyObject *args)
{
    PyObject *c1, *c2;
    if (!PyArg_ParseTuple(args, "OO", &c1, &c2)) return NULL;
    if (!PyCapsule_IsValid(c1, KV_SIG) || !PyCapsule_IsValid(c2, SPECIAL_SIG)) {
        PyErr_SetString(PyExc_ValueError, "set_bessel: capsules of kv 'double (double, double, int)' and gamma "
                        "'double (double, int)' needed");
        return NULL;
    }
    sp_kv = (kv_fn)PyCapsule_GetPointer(c1, KV_SIG);
    sp_gamma = (special_fn)PyCapsule_GetPointer(c2, SPECIAL_SIG);
    Py_RETURN_NONE;
}

/* the residuals R = f - v at q = (log rs, log nu) and their sum of squares, with f = c x^nu K_nu(x) kept in F
   for the Jacobian (moffat_jac), as moffat.moffat_ft_dlogs's f0 */
static double moffat_resid(const double *kr, const double *v, Py_ssize_t n, const double *q, double *R, double *F)
{
    const double nu = exp(q[1]), rs = exp(q[0]);
    const double c = pow(2.0, 1.0 - nu) / sp_gamma(nu, 0);
    double cost = 0.0;
    for (Py_ssize_t k = 0; k < n; k++) {
        const double x = kr[k] * rs;
        F[k] = c * pow(x, nu) * sp_kv(nu, x, 0);
        R[k] = F[k] - v[k];
        cost += R[k] * R[k];
    }
    return cost;
}

/* the Jacobian J (n x 2: d/dlog rs, d/dlog nu) at q, f there in F (moffat_resid's): df/dlog rs = -c x^(nu+1)
   K_(nu-1)(x), df/dlog nu by a forward difference of 1e-7, as moffat.moffat_ft_dlogs. Made only where the fit
   takes a step from q (until session 82 at every trial point too, rejected or final: the same numbers) */
static void moffat_jac(const double *kr, Py_ssize_t n, const double *q, const double *F, double *J)
{
    const double h = 1e-7;
    const double nu = exp(q[1]), nu2 = nu * exp(h), rs = exp(q[0]);
    const double c = pow(2.0, 1.0 - nu) / sp_gamma(nu, 0), c2 = pow(2.0, 1.0 - nu2) / sp_gamma(nu2, 0);
    for (Py_ssize_t k = 0; k < n; k++) {
        const double x = kr[k] * rs;
        J[2 * k] = -c * pow(x, nu + 1.0) * sp_kv(nu - 1.0, x, 0);
        J[2 * k + 1] = (c2 * pow(x, nu2) * sp_kv(nu2, x, 0) - F[k]) / h;
    }
}

/*
 * moffat_start(kr, vr, nus, x50, ratio, out): moffat._start of each row of vr (the ring averages at kr) in one call
 * (its numpy lines stay as the reference; a test checks they agree to the bit): out (rows of 2) holds what the start
 * is the logarithm of (numpy's log is taken by the caller: it is not the C library's everywhere), (x50(nu) / k50,
 * nu) where the running minimum of the row falls through 0.5 and 0.15 inside the band, else (1.2 / k_half, 2).
 * np.interp's arithmetic (compiled without contraction, as numpy's baseline build).
 */
static NO_CONTRACT double np_interp1(double x, const double *xp, const double *fp, Py_ssize_t n, int reversed)
{
#define XP(i) (reversed ? xp[n - 1 - (i)] : xp[i])
#define FP(i) (reversed ? fp[n - 1 - (i)] : fp[i])
    if (x < XP(0)) return FP(0);
    if (x > XP(n - 1)) return FP(n - 1);
    if (x == XP(n - 1)) return FP(n - 1);
    if (!(x >= XP(0))) return x;   /* NaN */
    Py_ssize_t lo = 0, hi = n - 1;   /* XP(lo) <= x < XP(hi) */
    while (hi - lo > 1) {
        const Py_ssize_t mid = lo + (hi - lo) / 2;
        if (XP(mid) <= x) lo = mid;
        else hi = mid;
    }
    const Py_ssize_t j = lo;
    if (XP(j) == x) return FP(j);
    const double slope = (FP(j + 1) - FP(j)) / (XP(j + 1) - XP(j));
    double r = slope * (x - XP(j)) + FP(j);
    if (r != r) {
        r = slope * (x - XP(j + 1)) + FP(j + 1);
        if (r != r && FP(j) == FP(j + 1)) r = FP(j);
    }
    return r;
#undef XP
#undef FP
}

static PyObject *moffat_start(PyObject *self, PyObject *args)
{
    Py_buffer kb, vb, nb, xb, rb, ob;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*", &kb, &vb, &nb, &xb, &rb, &ob)) return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double), nr = kb.len / D, nt = nb.len / D;
    const Py_ssize_t nf = nr > 0 ? vb.len / (nr * D) : 0;
    if (nr < 1 || nr > 4096 || vb.len != nf * nr * D || xb.len != nt * D || rb.len != nt * D || nt < 2
        || ob.len != 2 * nf * D) {
        RELEASE(&kb, &vb, &nb, &xb, &rb, &ob);
        PyErr_SetString(PyExc_ValueError, "moffat_start: inconsistent buffers");
        return NULL;
    }
    const double *kr = (const double *)kb.buf, *V = (const double *)vb.buf, *nus = (const double *)nb.buf;
    const double *x50 = (const double *)xb.buf, *ratio = (const double *)rb.buf;
    double *O = (double *)ob.buf, v[4096];
    for (Py_ssize_t f = 0; f < nf; f++) {
        const double *vr = V + f * nr;
        int finite = 1;
        for (Py_ssize_t i = 0; i < nr; i++) {   /* np.minimum.accumulate (NaN propagates) */
            v[i] = i == 0 ? vr[0] : (vr[i] < v[i - 1] || vr[i] != vr[i] ? vr[i] : v[i - 1]);
            if (!isfinite(v[i])) finite = 0;
        }
        if (nr >= 3 && v[0] > 0.5 && v[nr - 1] < 0.15 && finite) {
            const double k50 = np_interp1(0.5, v, kr, nr, 1), k15 = np_interp1(0.15, v, kr, nr, 1);
            if (k50 > 0 && k15 > k50) {
                const double nu = np_interp1(k15 / k50, ratio, nus, nt, 1);
                O[2 * f] = np_interp1(nu, nus, x50, nt, 0) / k50;
                O[2 * f + 1] = nu;
                continue;
            }
        }
        int any = 0;
        for (Py_ssize_t i = 0; i < nr; i++) any |= vr[i] < 0.5;
        /* np.argmin of |vr - 0.5|: the first least, or the first NaN */
        Py_ssize_t best = 0;
        double bd = fabs(vr[0] - 0.5);
        for (Py_ssize_t i = 1; bd == bd && i < nr; i++) {
            const double d = fabs(vr[i] - 0.5);
            if (d != d) {
                best = i;
                break;
            }
            if (d < bd) {
                best = i;
                bd = d;
            }
        }
        O[2 * f] = 1.2 / (any ? kr[best] : 0.5);
        O[2 * f + 1] = 2.0;
    }
    RELEASE(&kb, &vb, &nb, &xb, &rb, &ob);
    Py_RETURN_NONE;
}

/* whether the step from p to q is below the tolerance in both parameters (numpy: np.all(|Q - P| <= ...)) */
static int lm_small(const double *q, const double *p, double xtol)
{
    return fabs(q[0] - p[0]) <= xtol * (fabs(p[0]) + xtol) && fabs(q[1] - p[1]) <= xtol * (fabs(p[1]) + xtol);
}

static PyObject *moffat_lm(PyObject *self, PyObject *args)
{
    Py_buffer kb, vb, pb;
    int free0, free1, max_iter;
    double ftol, xtol;
    if (!PyArg_ParseTuple(args, "y*y*w*iiidd", &kb, &vb, &pb, &free0, &free1, &max_iter, &ftol, &xtol)) return NULL;
    const Py_ssize_t n = kb.len / (Py_ssize_t)sizeof(double), m = pb.len / (2 * (Py_ssize_t)sizeof(double));
    if (sp_kv == NULL || sp_gamma == NULL || n < 1 || vb.len != m * n * (Py_ssize_t)sizeof(double)
        || pb.len != 2 * m * (Py_ssize_t)sizeof(double) || !(free0 || free1)) {
        RELEASE(&kb, &vb, &pb);
        PyErr_SetString(PyExc_ValueError, "moffat_lm: inconsistent buffers (or set_bessel not called)");
        return NULL;
    }
    double *buf = (double *)malloc(7 * n * sizeof(double));
    if (buf == NULL) { RELEASE(&kb, &vb, &pb); return PyErr_NoMemory(); }
    const double *kr = (const double *)kb.buf;
    double *P = (double *)pb.buf;
    Py_BEGIN_ALLOW_THREADS
    double *R = buf, *J = buf + n, *Rq = buf + 3 * n, *F = buf + 4 * n, *Fq = buf + 5 * n;
    const int fr[2] = {free0, free1};
    for (Py_ssize_t r = 0; r < m; r++) {
        const double *v = (const double *)vb.buf + r * n;
        double *p = P + 2 * r;
        double lam = 1e-3;
        double cost = moffat_resid(kr, v, n, p, R, F);
        moffat_jac(kr, n, p, F, J);
        for (int it = 0; it < max_iter; it++) {
            /* the normal equations of the free parameters, damped by lam times their diagonal */
            double a00 = 0, a01 = 0, a11 = 0, g0 = 0, g1 = 0;
            for (Py_ssize_t k = 0; k < n; k++) {
                a00 += J[2 * k] * J[2 * k];
                a01 += J[2 * k] * J[2 * k + 1];
                a11 += J[2 * k + 1] * J[2 * k + 1];
                g0 += J[2 * k] * R[k];
                g1 += J[2 * k + 1] * R[k];
            }
            double step[2] = {0.0, 0.0};
            if (fr[0] && fr[1]) {
                const double A[2][2] = {{a00 + lam * (a00 + 1e-30), a01}, {a01, a11 + lam * (a11 + 1e-30)}};
                const double g[2] = {g0, g1};
                /* LU with partial pivoting, as LAPACK's gesv; an exactly singular pivot stops the fit */
                const int pv = fabs(A[1][0]) > fabs(A[0][0]) ? 1 : 0, o = 1 - pv;
                if (A[pv][0] == 0.0) { step[0] = step[1] = NAN; }
                else {
                    const double l = A[o][0] * (1.0 / A[pv][0]), u11 = A[o][1] - l * A[pv][1];
                    if (u11 == 0.0) { step[0] = step[1] = NAN; }
                    else {
                        const double x1 = (g[o] - l * g[pv]) / u11;
                        step[1] = -x1;
                        step[0] = -((g[pv] - A[pv][1] * x1) / A[pv][0]);
                    }
                }
            } else {
                const int f = fr[0] ? 0 : 1;
                const double a = f ? a11 + lam * (a11 + 1e-30) : a00 + lam * (a00 + 1e-30), g = f ? g1 : g0;
                step[f] = a == 0.0 ? NAN : -(g / a);
            }
            const int bad = !(isfinite(step[0]) && isfinite(step[1]));
            double q[2] = {p[0], p[1]};
            for (int t = 0; t < 2; t++)
                if (fr[t]) {
                    const double s = bad ? 0.0 : step[t];
                    q[t] += s < -2.0 ? -2.0 : (s > 2.0 ? 2.0 : s);
                }
            if (bad || lm_small(q, p, xtol)) break;   /* a singular system, or a step below the tolerance */
            const double cq = moffat_resid(kr, v, n, q, Rq, Fq);
            const int accept = isfinite(cq) && cq <= cost;
            const int converged = accept && ((cost - cq <= ftol * cost) || lm_small(q, p, xtol));
            if (accept) {
                p[0] = q[0];
                p[1] = q[1];
                cost = cq;
                memcpy(R, Rq, n * sizeof(double));
                if (!converged) moffat_jac(kr, n, p, Fq, J);   /* (a converged fit takes no step from here) */
            }
            lam = accept ? (lam / 3.0 > 1e-12 ? lam / 3.0 : 1e-12) : lam * 4.0;
            if (converged || (!accept && lam > 1e12)) break;
        }
    }
    Py_END_ALLOW_THREADS
    free(buf);
    RELEASE(&kb, &vb, &pb);
    Py_RETURN_NONE;
}

/* the Moffat's transform c x^nu K_nu(x) at x = k rs (1 at x <= 1e-8), as moffat.moffat_ft */
static double moffat_ft1(double x, double nu, double c)
{
    return x > 1e-8 ? c * pow(x, nu) * sp_kv(nu, x, 0) : 1.0;
}

/*
 * moffat_table(k, rs, beta, x_exact, h0, grow, floor, out): model._moffat_table's numbers (its numpy lines stay
 * as the reference and the fallback; a test checks they agree) on the uniform grid k: exact up to x = k rs =
 * x_exact, beyond it the quintic Hermite interpolant of the logarithm through exact nodes h0 + grow x apart, with
 * the exact slopes -rs K_(nu-1) / K_nu and curvatures (Bessel's equation) there, and 0 beyond the last node above
 * floor. scipy's kv and gamma (set_bessel).
 */
static PyObject *moffat_table(PyObject *self, PyObject *args)
{
    Py_buffer kb, ob;
    double rs, beta, x_exact, h0, grow, floor_;
    if (!PyArg_ParseTuple(args, "y*ddddddw*", &kb, &rs, &beta, &x_exact, &h0, &grow, &floor_, &ob)) return NULL;
    const Py_ssize_t n = kb.len / (Py_ssize_t)sizeof(double);
    if (sp_kv == NULL || sp_gamma == NULL || n < 2 || ob.len != kb.len || !(rs > 0) || !(beta > 1) || !(grow > 0)) {
        RELEASE(&kb, &ob);
        PyErr_SetString(PyExc_ValueError, "moffat_table: inconsistent arguments (or set_bessel not called)");
        return NULL;
    }
    const double *k = (const double *)kb.buf;
    double *out = (double *)ob.buf;
    const double nu = beta - 1.0, c = pow(2.0, 1.0 - nu) / sp_gamma(nu, 0);
    const double dx = (k[1] - k[0]) * rs;
    const Py_ssize_t j = (Py_ssize_t)ceil(x_exact / dx);
    int done = 0, nomem = 0;
    if (n - j >= 8) {
        const double a = x_exact + h0 / grow;
        const double top = (k[n - 1] * rs + h0 / grow) / a;
        const Py_ssize_t count = (Py_ssize_t)ceil(log(top) / log1p(grow)) + 1;
        int64_t *nodes = (int64_t *)malloc((count > 0 ? count : 1) * sizeof(int64_t));
        double *buf = (double *)malloc(4 * (count > 0 ? count : 1) * sizeof(double));
        if (nodes == NULL || buf == NULL) nomem = 1;
        Py_ssize_t nn = 0;
        for (Py_ssize_t i = 0; !nomem && i < count; i++) {
            double xi = a * pow(1.0 + grow, (double)i) - h0 / grow;
            double r = nearbyint(xi / dx);
            int64_t v = r < (double)j ? (int64_t)j : (r > (double)(n - 1) ? (int64_t)(n - 1) : (int64_t)r);
            if (nn == 0 || v != nodes[nn - 1]) nodes[nn++] = v;
        }
        if (!nomem) {
            double *V = buf, *KV = buf + count, *LV = buf + 2 * count, *CU = buf + 3 * count;
            Py_ssize_t m = 0;
            for (Py_ssize_t i = 0; i < nn; i++) {
                const double xn = k[nodes[i]] * rs;
                KV[i] = sp_kv(nu, xn, 0);
                V[i] = c * pow(xn, nu) * KV[i];
                m += V[i] >= floor_;
            }
            if (m >= 4) {
                for (Py_ssize_t i = 0; i < n; i++) out[i] = 0.0;
                for (Py_ssize_t i = 0; i < j; i++) out[i] = moffat_ft1(k[i] * rs, nu, c);
                /* the slopes d log f / dk at the nodes, in KV's place, and the curvatures d^2 log f / dk^2 from
                   Bessel's equation (K''/K = 1 + nu^2 / x^2 - (K'/K) / x) */
                for (Py_ssize_t i = 0; i < m; i++) {
                    const double xn = k[nodes[i]] * rs;
                    const double ratio = sp_kv(nu - 1.0, xn, 0) / KV[i], rho = -ratio - nu / xn;
                    KV[i] = -rs * ratio;
                    CU[i] = rs * rs * ((1.0 + (nu * nu - nu) / (xn * xn)) - rho / xn - rho * rho);
                    LV[i] = log(V[i]);
                }
                hermite_log_fill(k[0], k[1] - k[0], nodes, m, LV, KV, CU, out);
                for (Py_ssize_t i = 0; i < m; i++) out[nodes[i]] = V[i];
                done = 1;
            }
        }
        free(nodes);
        free(buf);
    }
    if (!done && !nomem)
        for (Py_ssize_t i = 0; i < n; i++) {
            const double v = moffat_ft1(k[i] * rs, nu, c);
            out[i] = v < floor_ ? 0.0 : v;
        }
    RELEASE(&kb, &ob);
    if (nomem) return PyErr_NoMemory();
    return PyBool_FromLong(done);
}

/* the instruction-set levels the CPU supports, as x86-64 micro-architecture levels (GCC and clang on
 * x86-64; elsewhere an empty tuple: only the baseline module exists) */
static PyObject *cpu_levels(PyObject *self, PyObject *args)
{
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    __builtin_cpu_init();
    int v3 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("bmi2")
             && __builtin_cpu_supports("avx") && __builtin_cpu_supports("f16c") && __builtin_cpu_supports("movbe");
    int v4 = v3 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw")
             && __builtin_cpu_supports("avx512cd") && __builtin_cpu_supports("avx512dq")
             && __builtin_cpu_supports("avx512vl");
    if (v4) return Py_BuildValue("(sss)", "baseline", "x86-64-v3", "x86-64-v4");
    if (v3) return Py_BuildValue("(ss)", "baseline", "x86-64-v3");
    return Py_BuildValue("(s)", "baseline");
#else
    return Py_BuildValue("(s)", "baseline");
#endif
}

static PyObject *build_info(PyObject *self, PyObject *args)
{
#if defined(__VERSION__)
    const char *compiler = __VERSION__;
#else
    const char *compiler = "unknown";
#endif
    return Py_BuildValue("{s:s,s:s}", "compiler", compiler, "level", KERNEL_LEVEL);
}

/*
 * find_peak(kx, ky, zr, x0, y0, cell, n_newton) -> (x, y, status): likelihood.find_position's Newton steps
 * on the cross-correlation h(x) = sum_k Re(zr_k exp(-i K_k . x)) of a round model (zr: complex128, the modes'
 * weights times the model's transform), from (x0, y0): each step solves [sum K K^T Re p] step = sum K Im p
 * (p = zr exp(-i K . x)), is shortened to at most ``cell``, and the steps stop once one is shorter than
 * 1e-6 cell. status 0, or 1 where the 2 x 2 system was singular or a step not finite (x is then where that
 * step started). The phases' cosines and sines in one vector loop each (libmvec where glibc has it).
 */
static PyObject *find_peak(PyObject *self, PyObject *args)
{
    Py_buffer kxb, kyb, zb;
    double x0, y0, cell;
    int n_newton;
    if (!PyArg_ParseTuple(args, "y*y*y*dddi", &kxb, &kyb, &zb, &x0, &y0, &cell, &n_newton)) return NULL;
    const Py_ssize_t n = kxb.len / (Py_ssize_t)sizeof(double);
    if (kyb.len != kxb.len || zb.len != 2 * kxb.len || n_newton < 0) {
        RELEASE(&kxb, &kyb, &zb);
        PyErr_SetString(PyExc_ValueError, "find_peak: inconsistent buffers");
        return NULL;
    }
    double *buf = (double *)malloc(3 * (n > 0 ? n : 1) * sizeof(double));
    if (buf == NULL) {
        RELEASE(&kxb, &kyb, &zb);
        return PyErr_NoMemory();
    }
    double *ph = buf, *cs = buf + n, *sn = buf + 2 * n;
    const double *KX = (const double *)kxb.buf, *KY = (const double *)kyb.buf, *Z = (const double *)zb.buf;
    double x = x0, y = y0;
    int status = 0;
    Py_BEGIN_ALLOW_THREADS
    for (int it = 0; it < n_newton; it++) {
        for (Py_ssize_t j = 0; j < n; j++) ph[j] = x * KX[j] + y * KY[j];
        for (Py_ssize_t j = 0; j < n; j++) cs[j] = cos(ph[j]);
        for (Py_ssize_t j = 0; j < n; j++) sn[j] = sin(ph[j]);
        double g0 = 0, g1 = 0, c0 = 0, c1 = 0, c2 = 0;
        for (Py_ssize_t j = 0; j < n; j++) {
            const double a = Z[2 * j], b = Z[2 * j + 1], kx = KX[j], ky = KY[j];
            const double re = a * cs[j] + b * sn[j], im = b * cs[j] - a * sn[j];
            g0 += kx * im;
            g1 += ky * im;
            c0 += kx * kx * re;
            c1 += kx * ky * re;
            c2 += ky * ky * re;
        }
        const double det = c0 * c2 - c1 * c1;
        if (det == 0.0) { status = 1; break; }
        double s0 = (c2 * g0 - c1 * g1) / det, s1 = (c0 * g1 - c1 * g0) / det;
        if (!isfinite(s0) || !isfinite(s1)) { status = 1; break; }
        const double nrm = hypot(s0, s1);
        if (nrm > cell) { s0 *= cell / nrm; s1 *= cell / nrm; }
        x += s0;
        y += s1;
        if (nrm < 1e-6 * cell) break;
    }
    Py_END_ALLOW_THREADS
    free(buf);
    RELEASE(&kxb, &kyb, &zb);
    return Py_BuildValue("ddi", x, y, status);
}

/* np.interp's value at x of the table xp, fp (m nodes; right beyond its end), its node found from x's bit pattern
   (index: per bucket of 2^shift patterns from base, the last node at or below its start), not fused */
static inline NO_CONTRACT double table_lookup(const double *XP, const double *FP, Py_ssize_t m, const int *IDX,
                                              Py_ssize_t nidx, long long base, int shift, double right, double x)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    if (x != x) return x;
    if (x < XP[0]) return FP[0];
    if (x > XP[m - 1]) return right;
    if (x == XP[m - 1]) return FP[m - 1];
    Py_ssize_t j = 0;
    if (x >= XP[1]) {
        long long bits;
        memcpy(&bits, &x, sizeof bits);
        long long b = (bits - base) >> shift;
        j = (Py_ssize_t)IDX[b < nidx ? b : nidx - 1];
        if (j > m - 2) j = m - 2;
        while (j < m - 2 && XP[j + 1] <= x) j++;
    }
    if (XP[j] == x) return FP[j];
    const double slope = (FP[j + 1] - FP[j]) / (XP[j + 1] - XP[j]);
    return slope * (x - XP[j]) + FP[j];
}

/* whether a table and its bucket index are usable by table_lookup: at least 3 nodes, a shift and base in range,
   and every bucket's node within the table */
static int table_ok(const int *IDX, Py_ssize_t nidx, Py_ssize_t m, int shift, long long base)
{
    if (m < 3 || nidx < 1 || shift < 0 || shift > 62 || base < 0) return 0;
    for (Py_ssize_t b = 0; b < nidx; b++)
        if (IDX[b] < 0 || IDX[b] > m - 1) return 0;
    return 1;
}

/* table_lookup of n values */
static NO_CONTRACT void table_lookup_n(const double *XP, const double *FP, Py_ssize_t m, const int *IDX,
                                       Py_ssize_t nidx, long long base, int shift, double right, const double *X,
                                       Py_ssize_t n, double *O)
{
    for (Py_ssize_t i = 0; i < n; i++) O[i] = table_lookup(XP, FP, m, IDX, nidx, base, shift, right, X[i]);
}

/*
 * table_interp(x, xp, fp, index, base, shift, right, out): np.interp(x, xp, fp, right=right) (left = fp[0]),
 * the same numbers (the same slope and sum, not fused), for a table xp of non-negative, increasing nodes with
 * xp[0] = 0 (the profiles' rho^2 tables). np.interp bisects the table for every unsorted x; here a node at or
 * below x comes from the bucket of x's bit pattern (index[b], int32: the last node at or below the bucket's
 * start, buckets of 2^shift patterns from the pattern ``base`` of xp[1]), and a few steps forward find x's node.
 */
static PyObject *table_interp(PyObject *self, PyObject *args)
{
    Py_buffer xb, xpb, fpb, ib, ob;
    long long base;
    int shift;
    double right;
    if (!PyArg_ParseTuple(args, "y*y*y*y*Lidw*", &xb, &xpb, &fpb, &ib, &base, &shift, &right, &ob)) return NULL;
    const Py_ssize_t n = xb.len / (Py_ssize_t)sizeof(double), m = xpb.len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t nidx = ib.len / (Py_ssize_t)sizeof(int);
    const int *IDX = (const int *)ib.buf;
    if (fpb.len != xpb.len || ob.len != xb.len || !table_ok(IDX, nidx, m, shift, base)) {
        RELEASE(&xb, &xpb, &fpb, &ib, &ob);
        PyErr_SetString(PyExc_ValueError, "table_interp: inconsistent buffers or an index outside the table");
        return NULL;
    }
    const double *X = (const double *)xb.buf, *XP = (const double *)xpb.buf, *FP = (const double *)fpb.buf;
    double *O = (double *)ob.buf;
    Py_BEGIN_ALLOW_THREADS
    table_lookup_n(XP, FP, m, IDX, nidx, base, shift, right, X, n, O);
    Py_END_ALLOW_THREADS
    RELEASE(&xb, &xpb, &fpb, &ib, &ob);
    Py_RETURN_NONE;
}

/*
 * size_nodes(bins, marg, e_index, rc, expx, x0, xf, interp, spline, u, half_log_u, l0, logmix, prior, shift, out,
 *            best): sampling.EllipticityLikelihood._nodes in one call (its Python lines stay as the reference: a
 * test checks they agree). For each ellipticity i (e_index[i] among the bins), its size nodes r = rc[i] expx[n]
 * (expx: exp of the nodes' ln r offsets x, n_r of them, x0 the first); their sums (binned_sums), each marginalised
 * over bulge fraction, position and flux (marginal), and the size integral (size_marginal) against the size prior
 * ln[p(r) r] = c - 2 ln a + 2 ln r - exp(alpha (ln r - ln a)) (prior: c, ln a, alpha) at ln r + shift[i] (shift:
 * one per ellipticity, or none); out: 5 x n_e (logl_disk, logl_bulge, mean_r, mean_b, mean_flux). best: the lowest
 * single-component chi^2 over the models and that model's SNR (in and out: updated where a model beats it).
 * bins: the tuple of binned_sums' arguments without r2, e_index and out; marg: marginal's without sums and out.
 */
/* (the tuples are parsed on their own: PyArg_ParseTuple sizes its list of buffers to release on failure by the
   top-level items, and the buffers of a nested tuple's items overran it) */
#define BINS_FMT "y*y*y*y*y*iy*y*nndddddddy*y*y*y*d"
#define BINS_ARGS(b, c) &b[0], &b[1], &b[2], &b[3], &b[4], &c.nb, &b[5], &b[6], &c.M, &c.J, &c.start, &c.per_oct, \
    &c.low_f, &c.low_g, &c.zero_f, &c.zero_g, &c.ratio2, &b[7], &b[8], &b[9], &b[10], &c.pair_tol
#define BINS_CHECK(b, c) bins_check(&c, &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7], &b[8], &b[9], &b[10])
#define MARG_FMT "y*y*y*y*y*"
#define MARG_ARGS(m) &m[0], &m[1], &m[2], &m[3], &m[4]

/* the release of size_nodes' and locate_pass' buffers: the bins' 11, the marginal's 5, then n more */
static void release_many(Py_buffer *b, int n)
{
    for (int i = 0; i < n; i++)
        if (b[i].obj != NULL) PyBuffer_Release(&b[i]);
}

/* a call of size_nodes or locate_pass: its buffers (the bins' 11, the marginal's 5, then its own), the bins' and
   the marginal's contexts and their tuples */
typedef struct {
    Py_buffer b[32];
    BinsCtx bc;
    MargCtx mc;
    PyObject *bt, *mt;
} CallCtx;

/* the end of a call of size_nodes or locate_pass: its n buffers released; None, or MemoryError where rc says memory
   ran out */
static PyObject *finish_call(int rc, Py_buffer *b, int n)
{
    release_many(b, n);
    if (rc != 0) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

/* the bins' and the marginal's tuples of a call parsed into its buffers 0 .. 15 and checked: 0, or -1 with an error
   set (the caller releases the buffers) */
static int parse_contexts(CallCtx *k)
{
    Py_buffer *b = k->b, *m = k->b + 11;
    if (!PyArg_ParseTuple(k->bt, BINS_FMT, BINS_ARGS(b, k->bc)) || !PyArg_ParseTuple(k->mt, MARG_FMT, MARG_ARGS(m)))
        return -1;
    if (BINS_CHECK(b, k->bc) != 0 || marg_check(&k->mc, &m[0], &m[1], &m[2], &m[3], &m[4]) != 0) return -1;
    return 0;
}

/* ln[p(r) r] of the size prior at ln r = lnr (sampling: priors.log_size_prior_per_lnr; pr: c, ln a, alpha) */
static inline double log_size_prior(double lnr, const double *pr)
{
    return (pr[0] - 2 * pr[1]) + 2 * lnr - exp(pr[2] * (lnr - pr[1]));
}

/* the sums and marginals of the models r = rc[i] ex[n] (n < nx) of nv versions of one object on the same modes
   (size_nodes_versions; nv = 1: one object): version v's bins at ellipticity i are entry E[i] + v; version 0's sums
   are binned_sums_run's, the others' linear sums binned_lin_run's with version 0's quadratic sums (ff, gg, fg: the
   modes' weights q and the fold pairs are the modes', not the data's, so each version's own are these to the bit);
   R: the models' r; mg: nv blocks of ne nx rows of 9, each version's marginals. need (NULL: every one): ne x nv
   flags, version v's models at ellipticity i marginalised only where need[i nv + v], elsewhere their best fits
   alone (best_fit_rows: their sums are made, the flux and bulge-fraction marginals not; entries 0 - 4 NaN), so that
   each version's best fit is the one over every model, as without need. 0, or -1 where memory ran out */
static __attribute__((noinline)) int node_models_versions(const BinsCtx *bc, const MargCtx *mc, Py_ssize_t ne,
                                                          const long long *E, Py_ssize_t nv, const double *rc,
                                                          const double *ex, Py_ssize_t nx, double *R, double *mg,
                                                          const unsigned char *need)
{
    const Py_ssize_t nm = ne * nx, n1 = nm > 0 ? nm : 1, ns = nv > 1 ? 2 : 1;
    double *sums = (double *)malloc((ns * NOUT + 1) * n1 * sizeof(double));
    long long *em = (long long *)malloc(n1 * sizeof(long long));
    /* with need: the rows of sums of the models a version marginalises, gathered, and their marginals */
    double *cw = need != NULL ? (double *)malloc((NOUT + 9) * n1 * sizeof(double)) : NULL;
    if (sums == NULL || em == NULL || (need != NULL && cw == NULL)) {
        free(sums);
        free(em);
        free(cw);
        return -1;
    }
    double *s1 = sums + NOUT * n1 * (ns - 1), *r2 = sums + ns * NOUT * n1;
    for (Py_ssize_t i = 0; i < ne; i++)
        for (Py_ssize_t n = 0; n < nx; n++) {
            const double r = rc[i] * ex[n];
            R[i * nx + n] = r;
            r2[i * nx + n] = r * r;
        }
    int rc_ = 0;
    for (Py_ssize_t v = 0; v < nv && rc_ == 0; v++) {
        for (Py_ssize_t i = 0; i < ne; i++)
            for (Py_ssize_t n = 0; n < nx; n++) em[i * nx + n] = E[i] + v;
        const double *sv = sums;
        if (v == 0) {
            rc_ = binned_sums_run(bc, nm, em, r2, sums);
        } else {
            rc_ = binned_lin_run(bc, nm, em, r2, s1);
            for (Py_ssize_t m = 0; m < nm; m++)
                for (int t = 12; t < 15; t++) s1[NOUT * m + t] = sums[NOUT * m + t];
            sv = s1;
        }
        if (rc_ != 0) break;
        double *mv = mg + 9 * nm * v;
        if (need == NULL) {
            rc_ = marginal_run(mc, nm, sv, mv);
            continue;
        }
        double *cs = cw, *co = cw + NOUT * n1;
        Py_ssize_t k = 0;
        for (Py_ssize_t i = 0; i < ne; i++) {
            if (need[i * nv + v]) {
                memcpy(cs + NOUT * k, sv + NOUT * i * nx, NOUT * nx * sizeof(double));
                k += nx;
            } else {
                best_fit_rows(mc, nx, sv + NOUT * i * nx, mv + 9 * i * nx);
            }
        }
        rc_ = marginal_run(mc, k, cs, co);
        for (Py_ssize_t i = 0, j = 0; i < ne; i++)
            if (need[i * nv + v]) {
                memcpy(mv + 9 * i * nx, co + 9 * j, 9 * nx * sizeof(double));
                j += nx;
            }
    }
    free(sums);
    free(em);
    free(cw);
    return rc_;
}

/* node_models_versions of one object */
static int node_models(const BinsCtx *bc, const MargCtx *mc, Py_ssize_t ne, const long long *E, const double *rc,
                       const double *ex, Py_ssize_t nx, double *R, double *mg)
{
    return node_models_versions(bc, mc, ne, E, 1, rc, ex, nx, R, mg, NULL);
}

/* size_nodes of nv versions (nv > 1: node_models_versions, E[i] + v version v's entry; L0, O and best: nv blocks of
   2, 5 ne and 2), each version's numbers those of its own call; need (NULL: every one) as node_models_versions'
   (version v's outputs at ellipticity i NaN where it is not set; its best fit over every model, as without need) */
static NO_CONTRACT NO_CLONE int size_nodes_run(const BinsCtx *bc, const MargCtx *mc, Py_ssize_t ne, const long long *E,
                                      Py_ssize_t nv, const double *rc, const double *ex, Py_ssize_t nr, double x0,
                                      const double *XF, Py_ssize_t nf, const double *ITP, const double *SPL,
                                      const double *U, const double *HLU, Py_ssize_t nu, const double *L0,
                                      const double *LM, const double *PR, const double *SH, double *O, double *best,
                                      const unsigned char *need)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const Py_ssize_t nm = ne * nr;
    const Py_ssize_t n1 = nm > 0 ? nm : 1, e1 = ne > 0 ? ne : 1;
    double *buf = (double *)malloc(((1 + 9 * nv) * n1 + (2 * nf + nu) * e1) * sizeof(double));
    if (buf == NULL) return -1;
    double *R = buf, *mgs = buf + n1, *col = mgs + 9 * nv * n1;
    double *LP = col + 0, *RF = LP + nf * e1, *LS = RF + nf * e1;
    if (node_models_versions(bc, mc, ne, E, nv, rc, ex, nr, R, mgs, need) != 0) {
        free(buf);
        return -1;
    }
    /* the size integral's inputs per ellipticity: the fine grid's r and prior, the first segment's prior */
    const double lo12 = log(1e-12);
    for (Py_ssize_t i = 0; i < ne; i++) {
        const double sh = SH != NULL ? SH[i] : 0.0;
        const double l0 = log(R[i * nr]) - x0;
        for (Py_ssize_t q = 0; q < nf; q++) {
            const double lnrf = l0 + XF[q];
            RF[i * nf + q] = exp(lnrf);
            LP[i * nf + q] = log_size_prior(lnrf + sh, PR);
        }
        const double lnrf0 = l0 + XF[0];
        for (Py_ssize_t j = 0; j < nu; j++) {
            double v = lnrf0 + HLU[j];
            v = v != v ? v : (v > lo12 ? v : lo12);   /* np.maximum */
            LS[i * nu + j] = log_size_prior(v + sh, PR) - 2 * v;
        }
    }
    /* the models' marginals as the columns size_marginal takes (n_e x n_r each) */
    double *LD = (double *)malloc(5 * n1 * sizeof(double));
    if (LD == NULL) {
        free(buf);
        return -1;
    }
    double *LB = LD + n1, *FD = LB + n1, *FB = FD + n1, *BD = FB + n1;
    for (Py_ssize_t v = 0; v < nv; v++) {
        const double *mg = mgs + 9 * nm * v;
        double *bv = best + 2 * v;
        /* the best single-component fit among the models (np.argmin of the lesser chi^2: its first minimum, or its
           first NaN, which beats nothing) */
        Py_ssize_t ib = -1;
        double cb = 0.0;
        for (Py_ssize_t m = 0; m < nm; m++) {
            const double a = mg[9 * m + 5], b = mg[9 * m + 6];
            const double c = (a != a || b != b) ? (a != a ? a : b) : (b < a ? b : a);   /* np.minimum */
            if (c != c) { ib = -1; cb = c; break; }
            if (ib < 0 || c < cb) { ib = m; cb = c; }
        }
        if (ib >= 0 && cb < bv[0]) {
            bv[0] = cb;
            bv[1] = mg[9 * ib + 8] > mg[9 * ib + 7] ? mg[9 * ib + 8] : mg[9 * ib + 7];   /* Python's max(d, b) */
        }
        for (Py_ssize_t m = 0; m < nm; m++) {
            LD[m] = mg[9 * m];
            LB[m] = mg[9 * m + 1];
            FD[m] = mg[9 * m + 2];
            FB[m] = mg[9 * m + 3];
            BD[m] = mg[9 * m + 4];
        }
        size_marginal_run(ne, nr, nf, nu, LD, LB, FD, FB, BD, LP, LS, SPL, ITP, XF, U, RF, L0 + 2 * v, LM,
                          O + 5 * ne * v, need != NULL ? need + v : NULL, nv);
    }
    free(LD);
    free(buf);
    return 0;
}

/* size_nodes and size_nodes_versions: with versions, nv (after e_index) versions binned together */
static PyObject *size_nodes_call(PyObject *args, int versions)
{
    CallCtx k = {0};
    Py_buffer *a = k.b + 16;   /* its own buffers */
    double x0;
    Py_ssize_t nv = 1;
    const char *name = versions ? "size_nodes_versions" : "size_nodes";
    int ok = versions
        ? PyArg_ParseTuple(args, "O!O!y*ny*y*dy*y*y*y*y*y*y*y*y*w*w*|y*", &PyTuple_Type, &k.bt, &PyTuple_Type,
                           &k.mt, &a[0], &nv, &a[1], &a[2], &x0, &a[3], &a[4], &a[5], &a[6], &a[7], &a[8], &a[9],
                           &a[10], &a[11], &a[12], &a[13], &a[14])
        : PyArg_ParseTuple(args, "O!O!y*y*y*dy*y*y*y*y*y*y*y*y*w*w*", &PyTuple_Type, &k.bt, &PyTuple_Type, &k.mt,
                           &a[0], &a[1], &a[2], &x0, &a[3], &a[4], &a[5], &a[6], &a[7], &a[8], &a[9], &a[10], &a[11],
                           &a[12], &a[13]);
    if (!ok) return NULL;
    if (parse_contexts(&k) != 0) {
        release_many(k.b, 32);
        return NULL;
    }
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    const Py_ssize_t ne = a[0].len / (Py_ssize_t)sizeof(long long), nr = a[2].len / D, nf = a[3].len / D;
    const Py_ssize_t nu = a[6].len / D;
    const long long *E = (const long long *)a[0].buf;
    int bad = ne < 0 || nv < 1 || a[1].len != ne * D || nr < 2 || nf < 2 || nu < 2 || nr > MAXN || nf > MAXN
              || nu > MAXN || a[4].len != nr * nf * D || a[5].len != nr * nf * D || a[7].len != nu * D
              || a[8].len != 2 * nv * D || a[9].len != 2 * D || a[10].len != 3 * D
              || (a[11].len != 0 && a[11].len != ne * D) || a[12].len != 5 * ne * nv * D || a[13].len != 2 * nv * D
              || (a[14].len != 0 && a[14].len != ne * nv);
    for (Py_ssize_t i = 0; !bad && i < ne; i++) bad = E[i] < 0 || E[i] > k.bc.n_e - nv;
    if (bad) {
        release_many(k.b, 32);
        PyErr_Format(PyExc_ValueError, "%s: inconsistent buffers", name);
        return NULL;
    }
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = size_nodes_run(&k.bc, &k.mc, ne, E, nv, (const double *)a[1].buf, (const double *)a[2].buf, nr, x0,
                        (const double *)a[3].buf, nf, (const double *)a[4].buf, (const double *)a[5].buf,
                        (const double *)a[6].buf, (const double *)a[7].buf, nu, (const double *)a[8].buf,
                        (const double *)a[9].buf, (const double *)a[10].buf,
                        a[11].len ? (const double *)a[11].buf : NULL, (double *)a[12].buf, (double *)a[13].buf,
                        a[14].len ? (const unsigned char *)a[14].buf : NULL);
    Py_END_ALLOW_THREADS
    return finish_call(rc, k.b, 32);
}

static PyObject *size_nodes(PyObject *self, PyObject *args)
{
    return size_nodes_call(args, 0);
}

/*
 * size_nodes_versions(bins, marg, e_index, nv, rc, expx, x0, xf, interp, spline, u, half_log_u, l0, logmix, prior,
 *                     shift, out, best[, need]): size_nodes of nv versions of one object, binned together
 * (likelihood.mode_bins_versions: version v's bins at ellipticity i are entry e_index[i] + v) on the same modes and
 * size nodes, each with its own point source (l0: nv x 2), output (out: nv x 5 x n_e) and best fit (best: nv x 2):
 * the numbers of size_nodes on each version, with the quadratic sums and fold pairs, which are the modes' and not
 * the data's, summed once for all (sampling.VersionLikelihoods). need (n_e x nv bytes, row-major; absent or empty:
 * every one): version v's size integral made at ellipticity i only where need[i, v] != 0 (its out NaN elsewhere),
 * its models' flux and bulge-fraction marginals only there; its best fit (best) still over every model, and its
 * numbers where it is needed those without need.
 */
static PyObject *size_nodes_versions(PyObject *self, PyObject *args)
{
    return size_nodes_call(args, 1);
}

/*
 * locate_pass(bins, marg, e_index, rc, expx, xs, prior, shift, w, detail, r_peak, top, point): one pass of
 * sampling.EllipticityLikelihood._locate in one call (its Python lines stay as the reference: a test checks they
 * agree). For each ellipticity i, the models r = rc[i] expx[n] at the pass's ln r offsets xs (n < n_x), their sums and
 * marginals as size_nodes', the size prior per ln r at ln r + shift[i] (prior and shift as size_nodes'), and the
 * parabolas of locate_parabola (w: the populations' log weights): r_peak = rc exp(offset of the higher one's peak),
 * top its value. With detail, point (5 x n_e) is the crude size integral over the pass's nodes (_locate's): log L of
 * each population (trapezoid in ln r: log sum exp over the nodes plus log h), and the posterior means of r, B and
 * the flux over the nodes.
 */
static double np_logaddexp(double x, double y)
{
    if (x == y) return x + M_LN2;
    const double t = x - y;
    if (t > 0) return x + log1p(exp(-t));
    if (t <= 0) return y + log1p(exp(t));
    return t;
}

static double nan_to_num(double v)
{
    return v != v ? 0.0 : (v == INFINITY ? DBL_MAX : (v == -INFINITY ? -DBL_MAX : v));
}

static NO_CONTRACT NO_CLONE int locate_pass_run(const BinsCtx *bc, const MargCtx *mc, Py_ssize_t ne, const long long *E,
                                       const double *rc, const double *ex, const double *xs, Py_ssize_t nx,
                                       const double *PR, const double *SH, const double *W, int detail, double *RP,
                                       double *TOP, double *PT)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const Py_ssize_t nm = ne * nx, n1 = nm > 0 ? nm : 1;
    double *buf = (double *)malloc((15 * n1 + (ne > 0 ? ne : 1)) * sizeof(double));
    if (buf == NULL) return -1;
    double *R = buf, *mg = R + n1, *LD = mg + 9 * n1, *LB = LD + n1, *LPR = LB + n1, *XPK = LPR + n1;
    double *Y = XPK + (ne > 0 ? ne : 1), *A = Y + n1;
    if (node_models(bc, mc, ne, E, rc, ex, nx, R, mg) != 0) {
        free(buf);
        return -1;
    }
    for (Py_ssize_t i = 0; i < ne; i++)
        for (Py_ssize_t n = 0; n < nx; n++) {
            const Py_ssize_t m = i * nx + n;
            LD[m] = mg[9 * m];
            LB[m] = mg[9 * m + 1];
            LPR[m] = log_size_prior(log(R[m]) + (SH != NULL ? SH[i] : 0.0), PR);
        }
    locate_rows(LD, LB, LPR, W, xs, ne, nx, TOP, XPK);
    for (Py_ssize_t i = 0; i < ne; i++) RP[i] = rc[i] * exp(XPK[i]);
    if (detail) {
        const double lh = log(xs[1] - xs[0]);
        for (Py_ssize_t i = 0; i < ne; i++) {
            const Py_ssize_t m0 = i * nx;
            double ymax = -INFINITY;
            for (Py_ssize_t n = 0; n < nx; n++) {
                const Py_ssize_t m = m0 + n;
                double y = np_logaddexp(W[0] + LD[m], W[1] + LB[m]) + LPR[m];
                y = isfinite(y) ? y : -1e300;
                Y[m] = y;
                ymax = y > ymax ? y : ymax;
            }
            double wsum = 0.0;
            for (Py_ssize_t n = 0; n < nx; n++) {
                A[m0 + n] = exp(Y[m0 + n] - ymax);
                wsum += A[m0 + n];
            }
            double mr = 0.0, mb = 0.0, mf = 0.0;
            for (Py_ssize_t n = 0; n < nx; n++) {
                const Py_ssize_t m = m0 + n;
                const double w = A[m] / wsum;
                mr += w * R[m];
                mb += w * nan_to_num(mg[9 * m + 4]);
                mf += w * nan_to_num(mg[9 * m + 2]);
            }
            for (int pop = 0; pop < 2; pop++) {
                /* _logsumexp_rows of (log L, -1e300 where not finite) + lpr + log h */
                double v[64], mx = -INFINITY;
                int vnan = 0;
                for (Py_ssize_t n = 0; n < nx; n++) {
                    const double l = (pop == 0 ? LD : LB)[m0 + n];
                    v[n] = (isfinite(l) ? l : -1e300) + LPR[m0 + n] + lh;
                    if (v[n] != v[n]) vnan = 1;
                    mx = v[n] > mx ? v[n] : mx;
                }
                if (vnan) mx = NAN;
                const double ms = isfinite(mx) ? mx : 0.0;
                double t = 0.0;
                for (Py_ssize_t n = 0; n < nx; n++) t += exp(v[n] - ms);
                PT[pop * ne + i] = ms + log(t);
            }
            PT[2 * ne + i] = mr;
            PT[3 * ne + i] = mb;
            PT[4 * ne + i] = mf;
        }
    }
    free(buf);
    return 0;
}

static PyObject *locate_pass(PyObject *self, PyObject *args)
{
    CallCtx k = {0};
    Py_buffer *a = k.b + 16;   /* its own buffers */
    int detail;
    if (!PyArg_ParseTuple(args, "O!O!y*y*y*y*y*y*y*iw*w*w*", &PyTuple_Type, &k.bt, &PyTuple_Type, &k.mt, &a[0], &a[1],
                          &a[2], &a[3], &a[4], &a[5], &a[6], &detail, &a[7], &a[8], &a[9]))
        return NULL;
    if (parse_contexts(&k) != 0) {
        release_many(k.b, 32);
        return NULL;
    }
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    const Py_ssize_t ne = a[0].len / (Py_ssize_t)sizeof(long long), nx = a[2].len / D;
    const long long *E = (const long long *)a[0].buf;
    int bad = a[1].len != ne * D || nx < 3 || nx > 64 || a[3].len != nx * D || a[4].len != 3 * D
              || (a[5].len != 0 && a[5].len != ne * D) || a[6].len != 2 * D || a[7].len != ne * D
              || a[8].len != ne * D || (detail && a[9].len != 5 * ne * D);
    for (Py_ssize_t i = 0; !bad && i < ne; i++) bad = E[i] < 0 || E[i] >= k.bc.n_e;
    if (bad) {
        release_many(k.b, 32);
        PyErr_SetString(PyExc_ValueError, "locate_pass: inconsistent buffers");
        return NULL;
    }
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = locate_pass_run(&k.bc, &k.mc, ne, E, (const double *)a[1].buf, (const double *)a[2].buf,
                         (const double *)a[3].buf, nx, (const double *)a[4].buf,
                         a[5].len ? (const double *)a[5].buf : NULL, (const double *)a[6].buf, detail,
                         (double *)a[7].buf, (double *)a[8].buf, (double *)a[9].buf);
    Py_END_ALLOW_THREADS
    return finish_call(rc, k.b, 32);
}

/* the chunk's shape matrices (model.shape_matrix's arithmetic) */
static NO_CONTRACT void shape_rows(const double *e1, const double *e2, Py_ssize_t n, double *S)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        const double e = hypot(e1[i], e2[i]);
        const double q = (1.0 - e) / (1.0 + e);
        const int pos = e > 0;
        const double safe = pos ? e : 1.0;
        const double c2 = pos ? e1[i] / safe : 1.0;
        const double s2 = e2[i] / safe;
        const double qq = q * q;
        const double mean = 0.5 * (1.0 + qq), half = 0.5 * (1.0 - qq);
        const double hc = half * c2;
        S[3 * i] = mean + hc;
        S[3 * i + 1] = half * s2;
        S[3 * i + 2] = mean - hc;
    }
}

static NO_CONTRACT int chunk_run(const BinsCtx *bc, const MargCtx *mc, Py_ssize_t ne, const double *rc, const double *SH,
                     const double *LXS, const double *LEX, Py_ssize_t nw, double ratio, double tail_skip,
                     const double *ex, Py_ssize_t nr, double x0, const double *XF, Py_ssize_t nf, const double *ITP,
                     const double *SPL, const double *U, const double *HLU, Py_ssize_t nu, const double *L0,
                     const double *LM, const double *PR, double *O, double *RC, double *state)
{
    const Py_ssize_t n1 = ne > 0 ? ne : 1;
    long long *E = (long long *)malloc(2 * n1 * sizeof(long long));
    double *buf = (double *)malloc((9 * n1) * sizeof(double));
    if (E == NULL || buf == NULL) {
        free(E);
        free(buf);
        return -1;
    }
    long long *EF = E + n1;
    double *RN = buf, *TOP = RN + n1, *PT = TOP + n1, *RF = PT + 5 * n1, *SF = RF + n1;
    int rc_ = 0;
    for (Py_ssize_t i = 0; i < ne; i++) {
        E[i] = i;
        RC[i] = nw > 0 ? rc[i] * ratio : rc[i];
    }
    Py_ssize_t nfull = ne;
    for (Py_ssize_t k = 0; rc_ == 0 && k < nw; k++) {
        const int detail = k == nw - 1 && tail_skip > 0;
        rc_ = locate_pass_run(bc, mc, ne, E, RC, LEX + 5 * k, LXS + 5 * k, 5, PR, SH, LM, detail, RN, TOP, PT);
        if (rc_ != 0) break;
        state[3] += (double)(5 * ne);
        memcpy(RC, RN, ne * sizeof(double));
        if (!detail) continue;
        double pm = -INFINITY;   /* np.max: NaN where any is */
        for (Py_ssize_t i = 0; i < ne; i++) {
            if (TOP[i] != TOP[i]) { pm = TOP[i]; break; }
            pm = TOP[i] > pm ? TOP[i] : pm;
        }
        if (pm > state[0]) state[0] = pm;   /* max(peak_max, pm): the first unless the second is greater */
        nfull = 0;
        for (Py_ssize_t i = 0; i < ne; i++)
            if (!(TOP[i] < state[0] - tail_skip)) EF[nfull++] = i;
    }
    if (rc_ == 0 && nfull == ne) {
        rc_ = size_nodes_run(bc, mc, ne, E, 1, RC, ex, nr, x0, XF, nf, ITP, SPL, U, HLU, nu, L0, LM, PR, SH, O, state + 1,
                             NULL);
        state[3] += (double)(ne * nr);
    } else if (rc_ == 0) {
        /* the tail's crude values, the others' nodes */
        for (int f = 0; f < 5; f++)
            for (Py_ssize_t i = 0; i < ne; i++) O[f * ne + i] = PT[f * ne + i];
        if (nfull > 0) {
            for (Py_ssize_t j = 0; j < nfull; j++) {
                RF[j] = RC[EF[j]];
                SF[j] = SH != NULL ? SH[EF[j]] : 0.0;
            }
            double *of = (double *)malloc(5 * nfull * sizeof(double));
            if (of == NULL) rc_ = -1;
            else {
                rc_ = size_nodes_run(bc, mc, nfull, EF, 1, RF, ex, nr, x0, XF, nf, ITP, SPL, U, HLU, nu, L0, LM, PR,
                                     SH != NULL ? SF : NULL, of, state + 1, NULL);
                for (int f = 0; rc_ == 0 && f < 5; f++)
                    for (Py_ssize_t j = 0; j < nfull; j++) O[f * ne + EF[j]] = of[f * nfull + j];
                free(of);
            }
            state[3] += (double)(nfull * nr);
        }
    }
    free(E);
    free(buf);
    return rc_;
}

/* what a chunk's evaluation takes of the object alone (sampling.EllipticityLikelihood._chunk_args, its tuple parsed
   by chunk_args_parse): the bins' other arguments, the marginal's, make_bins' (basis32, channels32,
   bins_per_octave, polar or None, out buffer), the locating passes and the size nodes' constants */
typedef struct {
    PyObject *brest, *mt, *binning;
    const double *LXS, *LEX, *ex, *XF, *ITP, *SPL, *U, *HLU, *L0, *LM, *PR;
    Py_ssize_t nw, nr, nf, nu;
    double ratio, tail_skip, x0;
} ChunkArgs;

#define CHUNK_BUFS 13
/* the tuple (bins_rest, marg, binning, locate_xs, locate_ex, locate_ratio, tail_skip, expx, x0, xf, interp, spline,
   u, half_log_u, l0, logmix, prior) into A (its buffers in b, CHUNK_BUFS of them, released by the caller): 0, or -1
   with an error set */
static int chunk_args_parse(PyObject *t, ChunkArgs *A, Py_buffer *b)
{
    if (!PyTuple_Check(t)
        || !PyArg_ParseTuple(t, "O!O!O!y*y*ddy*dy*y*y*y*y*y*y*y*", &PyTuple_Type, &A->brest, &PyTuple_Type, &A->mt,
                             &PyTuple_Type, &A->binning, &b[0], &b[1], &A->ratio, &A->tail_skip, &b[2], &A->x0,
                             &b[3], &b[4], &b[5], &b[6], &b[7], &b[8], &b[9], &b[10])) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_TypeError, "sample_chunk: the object's arguments are a tuple");
        return -1;
    }
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    A->nw = b[0].len / (5 * D);
    A->nr = b[2].len / D;
    A->nf = b[3].len / D;
    A->nu = b[6].len / D;
    if (b[0].len != A->nw * 5 * D || b[1].len != b[0].len || A->nr < 2 || A->nf < 2 || A->nu < 2 || A->nr > MAXN
        || A->nf > MAXN || A->nu > MAXN || b[4].len != A->nr * A->nf * D || b[5].len != A->nr * A->nf * D
        || b[7].len != A->nu * D || b[8].len != 2 * D || b[9].len != 2 * D || b[10].len != 3 * D
        || PyTuple_GET_SIZE(A->binning) != 5 || PyTuple_GET_SIZE(A->brest) != 17) {
        PyErr_SetString(PyExc_ValueError, "sample_chunk: inconsistent buffers");
        return -1;
    }
    A->LXS = (const double *)b[0].buf;
    A->LEX = (const double *)b[1].buf;
    A->ex = (const double *)b[2].buf;
    A->XF = (const double *)b[3].buf;
    A->ITP = (const double *)b[4].buf;
    A->SPL = (const double *)b[5].buf;
    A->U = (const double *)b[6].buf;
    A->HLU = (const double *)b[7].buf;
    A->L0 = (const double *)b[8].buf;
    A->LM = (const double *)b[9].buf;
    A->PR = (const double *)b[10].buf;
    return 0;
}

/* one chunk of ne ellipticities (e1, e2; size centres rc, prior shifts SH or NULL) as sample_chunk: O (5 x ne), RC
   (the centres used), state (peak_max, best chi^2, its SNR, models += ). *need: the doubles make_bins' columns took
   where they did not fit in the out buffer (else left). Holds the GIL (make_bins' objects), releases it for the
   arithmetic. 0, or -1 with an error set */
static int chunk_eval(const ChunkArgs *A, Py_ssize_t ne, const double *e1, const double *e2, const double *rc,
                      const double *SH, double *O, double *RC, double *state, long long *need)
{
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    int ret = -1;
    PyObject *shape = NULL, *bins = NULL, *mbargs = NULL, *cols = NULL, *bt = NULL;
    CallCtx k;
    memset(&k, 0, sizeof(k));
    Py_buffer cb = {0};
    shape = PyBytes_FromStringAndSize(NULL, 3 * ne * D);
    if (shape == NULL) goto done;
    shape_rows(e1, e2, ne, (double *)PyBytes_AS_STRING(shape));
    PyObject *outbuf = PyTuple_GET_ITEM(A->binning, 4);
    mbargs = Py_BuildValue("(OOOOiOO)", shape, PyTuple_GET_ITEM(A->binning, 0), PyTuple_GET_ITEM(A->binning, 1),
                           PyTuple_GET_ITEM(A->binning, 2), 1, PyTuple_GET_ITEM(A->binning, 3), outbuf);
    if (mbargs == NULL) goto done;
    bins = make_bins(NULL, mbargs);
    if (bins == NULL) goto done;
    PyObject *offs = PyTuple_GET_ITEM(bins, 1);
    const long long *OFF = (const long long *)PyBytes_AS_STRING(offs);
    PyObject *c = PyTuple_GET_ITEM(bins, 2);
    if (c == Py_None) {   /* in the out buffer: its first NCH offsets[-1] doubles */
        if (PyObject_GetBuffer(outbuf, &cb, PyBUF_SIMPLE) != 0) goto done;
        cols = PyMemoryView_FromMemory((char *)cb.buf, NCH * OFF[ne] * D, PyBUF_READ);
        if (cols == NULL) goto done;
    } else {
        long long n = (long long)(PyBytes_GET_SIZE(c) / D);
        if (n > *need) *need = n;
        cols = c;
        Py_INCREF(cols);
    }
    bt = PyTuple_New(22);
    if (bt == NULL) goto done;
    PyObject *first[5] = {shape, PyTuple_GET_ITEM(bins, 0), offs, cols, PyTuple_GET_ITEM(bins, 3)};
    for (int t = 0; t < 5; t++) {
        Py_INCREF(first[t]);
        PyTuple_SET_ITEM(bt, t, first[t]);
    }
    for (int t = 0; t < 17; t++) {
        PyObject *o = PyTuple_GET_ITEM(A->brest, t);
        Py_INCREF(o);
        PyTuple_SET_ITEM(bt, 5 + t, o);
    }
    k.bt = bt;
    k.mt = A->mt;
    if (parse_contexts(&k) != 0) goto done;
    if (k.bc.n_e != ne) {
        PyErr_SetString(PyExc_ValueError, "sample_chunk: the bins are not the chunk's");
        goto done;
    }
    int rc_;
    Py_BEGIN_ALLOW_THREADS
    rc_ = chunk_run(&k.bc, &k.mc, ne, rc, SH, A->LXS, A->LEX, A->nw, A->ratio, A->tail_skip, A->ex, A->nr, A->x0,
                    A->XF, A->nf, A->ITP, A->SPL, A->U, A->HLU, A->nu, A->L0, A->LM, A->PR, O, RC, state);
    Py_END_ALLOW_THREADS
    if (rc_ != 0) PyErr_NoMemory();
    else ret = 0;
done:
    release_many(k.b, 32);
    if (cb.obj != NULL) PyBuffer_Release(&cb);
    Py_XDECREF(bt);
    Py_XDECREF(cols);
    Py_XDECREF(bins);
    Py_XDECREF(mbargs);
    Py_XDECREF(shape);
    return ret;
}

/*
 * sample_chunk(args, e1, e2, rc, shift, out, rc_out, state) -> int: sampling.EllipticityLikelihood._chunk in one call,
 * where the size peak is located afresh at every ellipticity (its Python lines stay as the reference: a test checks
 * they agree to the bit). args: the object's (EllipticityLikelihood._chunk_args, with make_bins' out buffer), as
 * chunk_args_parse reads them. The chunk's shape matrices (model.shape_matrix's arithmetic) and bins (make_bins); with
 * locating passes (a row of 5 ln r offsets and their exp per pass, none without) their passes from rc *
 * locate_ratio, the last with detail where tail_skip > 0: a sample whose peak lies more than tail_skip below the
 * highest so far (state[0], updated) keeps that pass's crude size integral; the others' size nodes as size_nodes
 * (best = state[1 .. 2]). out: 5 x n_e; rc_out: the size centres used; state[3] += the models evaluated. Returns the
 * doubles make_bins' columns took where they did not fit in the out buffer (the caller's buffer should grow), 0
 * where they did.
 */
static PyObject *sample_chunk(PyObject *self, PyObject *args)
{
    PyObject *targs;
    Py_buffer a[8], cbuf[CHUNK_BUFS];
    memset(a, 0, sizeof(a));
    memset(cbuf, 0, sizeof(cbuf));
    PyObject *res = NULL;
    ChunkArgs A;
    if (!PyArg_ParseTuple(args, "O!y*y*y*y*w*w*w*", &PyTuple_Type, &targs, &a[0], &a[1], &a[2], &a[3], &a[4], &a[5],
                          &a[6]))
        return NULL;
    if (chunk_args_parse(targs, &A, cbuf) != 0) goto done;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    const Py_ssize_t ne = a[0].len / D;
    if (a[1].len != ne * D || a[2].len != ne * D || (a[3].len != 0 && a[3].len != ne * D) || a[4].len != 5 * ne * D
        || a[5].len != ne * D || a[6].len != 4 * D) {
        PyErr_SetString(PyExc_ValueError, "sample_chunk: inconsistent buffers");
        goto done;
    }
    long long need = 0;
    if (chunk_eval(&A, ne, (const double *)a[0].buf, (const double *)a[1].buf, (const double *)a[2].buf,
                   a[3].len ? (const double *)a[3].buf : NULL, (double *)a[4].buf, (double *)a[5].buf,
                   (double *)a[6].buf, &need) == 0)
        res = PyLong_FromLongLong(need);
done:
    release_many(cbuf, CHUNK_BUFS);
    release_many(a, 8);
    return res;
}

/*
 * adaptive_samples(args, prior_disk, prior_bulge, growth, shift, ints, params, state) -> (samples, n, need):
 * sampling.adaptive_samples of an EllipticityLikelihood whose chunks sample_chunk evaluates, in one call (its Python
 * lines stay as the reference: a test checks they agree to the bit). The lattice of step unit, points (i, j) with
 * |i|, |j| <= half: prior_disk, prior_bulge (the log ellipticity priors), growth (min(q^(-1/3), the growth's cap),
 * EllipticityLikelihood.centre over r_center) and shift (the size prior's axis shift, or empty) at each point,
 * row i + half, column j + half. ints: half, the start step, the pre-pass step, the first box's half-width n, n_above,
 * chunk. params: unit, model_e_limit, the log thresholds of the pre-pass (log posterior_cut - margin), of the count
 * (log above_fraction) and of the refinement (log min(posterior_cut, above_fraction)), log(1 - f_B), log f_B,
 * r_center. state: as sample_chunk's. samples: 11 rows of n doubles (e1, e2, area, logl, logpost, the five fields
 * of the EPoint, the size centre), bytes; need: as sample_chunk's return.
 */
typedef struct {
    long long *key;   /* (i, j) packed, -1: empty */
    int *val;
    Py_ssize_t cap;
} LatMap;

static inline long long lat_key(long long i, long long j) { return ((i + (1LL << 30)) << 32) | (j + (1LL << 30)); }

static inline Py_ssize_t lat_slot(const LatMap *m, long long key)
{
    unsigned long long h = (unsigned long long)key * 0x9E3779B97F4A7C15ULL;
    Py_ssize_t s = (Py_ssize_t)(h >> 20) & (m->cap - 1);
    while (m->key[s] != -1 && m->key[s] != key) s = (s + 1) & (m->cap - 1);
    return s;
}

static int lat_grow(LatMap *m)
{
    LatMap n = {NULL, NULL, m->cap * 2};
    n.key = (long long *)malloc(n.cap * sizeof(long long));
    n.val = (int *)malloc(n.cap * sizeof(int));
    if (n.key == NULL || n.val == NULL) {
        free(n.key);
        free(n.val);
        return -1;
    }
    for (Py_ssize_t s = 0; s < n.cap; s++) n.key[s] = -1;
    for (Py_ssize_t s = 0; s < m->cap; s++)
        if (m->key[s] != -1) {
            Py_ssize_t t = lat_slot(&n, m->key[s]);
            n.key[t] = m->key[s];
            n.val[t] = m->val[s];
        }
    free(m->key);
    free(m->val);
    *m = n;
    return 0;
}

typedef struct {
    long long step, i0, j0, ni, nj;
    unsigned char *mask;
} LatRegion;

typedef struct {
    const ChunkArgs *A;
    const double *PD, *PB, *GR, *SHT;
    long long half, chunk;
    double unit, limit2, ld0, lb0, r_center;
    LatMap map;
    Py_ssize_t n, cap;
    long long *I, *J;
    double *col;   /* 11 rows of cap: e1, e2, area, logl, logpost, point (5), rc */
    LatRegion *reg;
    Py_ssize_t nreg, capreg;
    long long *pi, *pj;   /* the points of the last _points, and their count */
    Py_ssize_t npts, cappts;
    double *state;
    long long need;
} LatStore;

static int store_reserve(LatStore *s, Py_ssize_t n)
{
    if (n <= s->cap) return 0;
    Py_ssize_t cap = s->cap * 2 > n ? s->cap * 2 : n;
    long long *I = (long long *)realloc(s->I, cap * sizeof(long long));
    if (I != NULL) s->I = I;
    long long *J = (long long *)realloc(s->J, cap * sizeof(long long));
    if (J != NULL) s->J = J;
    double *col = (double *)malloc(11 * cap * sizeof(double));
    if (I == NULL || J == NULL || col == NULL) {
        free(col);
        return -1;
    }
    for (int r = 0; s->n > 0 && r < 11; r++) memcpy(col + r * cap, s->col + r * s->cap, s->n * sizeof(double));
    free(s->col);
    s->col = col;
    s->cap = cap;
    return 0;
}

/* _Store._points: the step's lattice points of the region (mask over the box from (i0, j0), ni x nj; the store
   takes the mask) with i^2 + j^2 below the limit, row after row, into pi, pj; records the region */
static int store_points(LatStore *s, long long step, long long i0, long long j0, long long ni, long long nj,
                        unsigned char *mask)
{
    if (s->nreg == s->capreg) {
        Py_ssize_t cap = s->capreg ? 2 * s->capreg : 16;
        LatRegion *r = (LatRegion *)realloc(s->reg, cap * sizeof(LatRegion));
        if (r == NULL) {
            free(mask);
            return -1;
        }
        s->reg = r;
        s->capreg = cap;
    }
    LatRegion R = {step, i0, j0, ni, nj, mask};
    s->reg[s->nreg++] = R;
    s->npts = 0;
    const long long a0 = ((-i0) % step + step) % step, b0 = ((-j0) % step + step) % step;
    for (long long a = a0; a < ni; a += step)
        for (long long b = b0; b < nj; b += step) {
            const long long I = i0 + a, J = j0 + b;
            if (!mask[a * nj + b] || !((double)(I * I + J * J) < s->limit2)) continue;
            if (s->npts == s->cappts) {
                Py_ssize_t cap = s->cappts ? 2 * s->cappts : 256;
                long long *pi = (long long *)realloc(s->pi, cap * sizeof(long long));
                if (pi != NULL) s->pi = pi;
                long long *pj = (long long *)realloc(s->pj, cap * sizeof(long long));
                if (pi == NULL || pj == NULL) return -1;
                s->pj = pj;
                s->cappts = cap;
            }
            s->pi[s->npts] = I;
            s->pj[s->npts] = J;
            s->npts++;
        }
    return 0;
}

/* _Store._box: the box clipped to the lattice; 1 and a zeroed mask (ni x nj), or 0 where it is empty */
static int store_box(const LatStore *s, long long imin, long long imax, long long jmin, long long jmax, long long *i0,
                     long long *j0, long long *ni, long long *nj, unsigned char **mask)
{
    const long long h = s->half;
    imin = imin > -h ? imin : -h;
    jmin = jmin > -h ? jmin : -h;
    imax = imax < h ? imax : h;
    jmax = jmax < h ? jmax : h;
    if (imax < imin || jmax < jmin) return 0;
    *i0 = imin;
    *j0 = jmin;
    *ni = imax - imin + 1;
    *nj = jmax - jmin + 1;
    *mask = (unsigned char *)calloc((size_t)(*ni * *nj), 1);
    return *mask == NULL ? -1 : 1;
}

/* _Store.add of the points pi, pj: the new ones evaluated in chunks of s->chunk, mixed with the priors */
static int store_add(LatStore *s)
{
    /* the points not yet sampled, in order (a point twice in the list: once) */
    Py_ssize_t nn = 0;
    for (Py_ssize_t p = 0; p < s->npts; p++) {
        if (2 * (s->n + nn + 1) > s->map.cap && lat_grow(&s->map) != 0) return -1;
        const long long key = lat_key(s->pi[p], s->pj[p]);
        Py_ssize_t slot = lat_slot(&s->map, key);
        if (s->map.key[slot] != -1) continue;
        s->map.key[slot] = key;
        s->map.val[slot] = (int)(s->n + nn);
        s->pi[nn] = s->pi[p];
        s->pj[nn] = s->pj[p];
        nn++;
    }
    if (nn == 0) return 0;
    if (store_reserve(s, s->n + nn) != 0) return -1;
    const Py_ssize_t cap = s->cap, w = 2 * s->half + 1;
    double *E1 = s->col, *E2 = s->col + cap, *AR = s->col + 2 * cap, *LL = s->col + 3 * cap, *LP = s->col + 4 * cap;
    double *PT = s->col + 5 * cap, *RCo = s->col + 10 * cap;
    const Py_ssize_t c = (Py_ssize_t)s->chunk;
    double *rc = (double *)malloc(2 * c * sizeof(double) + 5 * c * sizeof(double));
    if (rc == NULL) return -1;
    double *sh = rc + c, *o = sh + c;
    for (Py_ssize_t p = 0; p < nn; p++) {
        const Py_ssize_t m = s->n + p;
        s->I[m] = s->pi[p];
        s->J[m] = s->pj[p];
        E1[m] = (double)s->pi[p] * s->unit;
        E2[m] = (double)s->pj[p] * s->unit;
        AR[m] = 0.0;
    }
    int ret = 0;
    for (Py_ssize_t c0 = 0; ret == 0 && c0 < nn; c0 += c) {
        const Py_ssize_t ne = nn - c0 < c ? nn - c0 : c, m0 = s->n + c0;
        for (Py_ssize_t q = 0; q < ne; q++) {
            const Py_ssize_t at = (s->I[m0 + q] + s->half) * w + (s->J[m0 + q] + s->half);
            rc[q] = s->r_center * s->GR[at];
            sh[q] = s->SHT != NULL ? s->SHT[at] : 0.0;
        }
        ret = chunk_eval(s->A, ne, E1 + m0, E2 + m0, rc, s->SHT != NULL ? sh : NULL, o, RCo + m0, s->state, &s->need);
        if (ret != 0) break;
        for (Py_ssize_t q = 0; q < ne; q++) {
            const Py_ssize_t m = m0 + q, at = (s->I[m] + s->half) * w + (s->J[m] + s->half);
            for (int f = 0; f < 5; f++) PT[f * cap + m] = o[f * ne + q];
            const double la = s->ld0 + o[q], lb = s->lb0 + o[ne + q];
            LL[m] = np_logaddexp(la, lb);
            LP[m] = np_logaddexp(la + s->PD[at], lb + s->PB[at]);
        }
    }
    free(rc);
    if (ret == 0) s->n += nn;
    return ret;
}

/* _Store.above_log: into sel (s->n), whether each sample's posterior lies above exp(lf) of the largest; the count */
static Py_ssize_t store_above(const LatStore *s, double lf, unsigned char *sel)
{
    const double *LP = s->col + 4 * s->cap;
    int finite = 0;
    double mx = -INFINITY;
    int nan = 0;
    for (Py_ssize_t m = 0; m < s->n; m++) {
        finite |= isfinite(LP[m]);
        if (LP[m] != LP[m]) nan = 1;
        else if (LP[m] > mx) mx = LP[m];
    }
    Py_ssize_t k = 0;
    const double t = (nan ? NAN : mx) + lf;
    for (Py_ssize_t m = 0; m < s->n; m++) {
        sel[m] = finite && LP[m] > t;
        k += sel[m];
    }
    return k;
}

/* _Store.lattice_around: the step's points within reach (Chebyshev) of the samples sel, then their evaluation */
static int store_around(LatStore *s, const unsigned char *sel, long long step, long long reach)
{
    long long imin = LLONG_MAX, imax = LLONG_MIN, jmin = LLONG_MAX, jmax = LLONG_MIN;
    int any = 0;
    for (Py_ssize_t m = 0; m < s->n; m++)
        if (sel[m]) {
            any = 1;
            imin = s->I[m] < imin ? s->I[m] : imin;
            imax = s->I[m] > imax ? s->I[m] : imax;
            jmin = s->J[m] < jmin ? s->J[m] : jmin;
            jmax = s->J[m] > jmax ? s->J[m] : jmax;
        }
    if (!any) return 0;
    long long i0, j0, ni, nj;
    unsigned char *mask;
    const int got = store_box(s, imin - reach, imax + reach, jmin - reach, jmax + reach, &i0, &j0, &ni, &nj, &mask);
    if (got <= 0) return got;
    for (Py_ssize_t m = 0; m < s->n; m++) {
        if (!sel[m]) continue;
        long long a_lo = s->I[m] - reach - i0, a_hi = s->I[m] + reach - i0 + 1;
        long long b_lo = s->J[m] - reach - j0, b_hi = s->J[m] + reach - j0 + 1;
        a_lo = a_lo > 0 ? a_lo : 0;
        b_lo = b_lo > 0 ? b_lo : 0;
        a_hi = a_hi < ni ? a_hi : ni;
        b_hi = b_hi < nj ? b_hi : nj;
        for (long long a = a_lo; a < a_hi; a++) memset(mask + a * nj + b_lo, 1, b_hi > b_lo ? b_hi - b_lo : 0);
    }
    if (store_points(s, step, i0, j0, ni, nj, mask) != 0) return -1;
    return store_add(s);
}

static void store_free(LatStore *s)
{
    free(s->map.key);
    free(s->map.val);
    free(s->I);
    free(s->J);
    free(s->col);
    for (Py_ssize_t r = 0; r < s->nreg; r++) free(s->reg[r].mask);
    free(s->reg);
    free(s->pi);
    free(s->pj);
}

static PyObject *adaptive_samples_c(PyObject *self, PyObject *args)
{
    PyObject *targs, *res = NULL;
    Py_buffer a[7], cbuf[CHUNK_BUFS];
    memset(a, 0, sizeof(a));
    memset(cbuf, 0, sizeof(cbuf));
    ChunkArgs A;
    LatStore s;
    memset(&s, 0, sizeof(s));
    unsigned char *sel = NULL;
    if (!PyArg_ParseTuple(args, "O!y*y*y*y*y*y*w*", &PyTuple_Type, &targs, &a[0], &a[1], &a[2], &a[3], &a[4], &a[5],
                          &a[6]))
        return NULL;
    if (chunk_args_parse(targs, &A, cbuf) != 0) goto done;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    const long long *IN = (const long long *)a[4].buf;
    const double *PA = (const double *)a[5].buf;
    if (a[4].len != 6 * (Py_ssize_t)sizeof(long long) || a[5].len != 10 * D || a[6].len != 4 * D) {
        PyErr_SetString(PyExc_ValueError, "adaptive_samples: inconsistent buffers");
        goto done;
    }
    const long long half = IN[0], w = 2 * half + 1;
    long long step = IN[1], pre = IN[2];
    const long long n0 = IN[3], n_above = IN[4];
    if (half < 1 || half > 100000 || step < 1 || pre < 1 || IN[5] < 1 || a[0].len != w * w * D
        || a[1].len != a[0].len || a[2].len != a[0].len || (a[3].len != 0 && a[3].len != a[0].len)) {
        PyErr_SetString(PyExc_ValueError, "adaptive_samples: inconsistent buffers");
        goto done;
    }
    s.A = &A;
    s.PD = (const double *)a[0].buf;
    s.PB = (const double *)a[1].buf;
    s.GR = (const double *)a[2].buf;
    s.SHT = a[3].len ? (const double *)a[3].buf : NULL;
    s.half = half;
    s.chunk = IN[5];
    s.unit = PA[0];
    const double limit = PA[1] / PA[0];
    s.limit2 = limit * limit;
    const double lf_pre = PA[2], lf_count = PA[3], lf_refine = PA[4];
    s.ld0 = PA[5];
    s.lb0 = PA[6];
    s.r_center = PA[7];
    s.state = (double *)a[6].buf;
    s.map.cap = 1024;
    s.map.key = (long long *)malloc(s.map.cap * sizeof(long long));
    s.map.val = (int *)malloc(s.map.cap * sizeof(int));
    s.cap = 0;
    if (s.map.key == NULL || s.map.val == NULL || store_reserve(&s, 512) != 0) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t q = 0; q < s.map.cap; q++) s.map.key[q] = -1;
    {
        long long i0, j0, ni, nj;
        unsigned char *mask;
        int got = store_box(&s, -n0, n0, -n0, n0, &i0, &j0, &ni, &nj, &mask);
        if (got < 0) { PyErr_NoMemory(); goto done; }
        if (got > 0) {
            memset(mask, 1, (size_t)(ni * nj));
            if (store_points(&s, pre, i0, j0, ni, nj, mask) != 0 || store_add(&s) != 0) {
                if (!PyErr_Occurred()) PyErr_NoMemory();
                goto done;
            }
        }
    }
    while (pre > step) {
        free(sel);
        sel = (unsigned char *)malloc(s.n > 0 ? s.n : 1);
        if (sel == NULL) { PyErr_NoMemory(); goto done; }
        store_above(&s, lf_pre, sel);
        const long long nw = pre / 2 > step ? pre / 2 : step;
        if (store_around(&s, sel, nw, pre) != 0) {
            if (!PyErr_Occurred()) PyErr_NoMemory();
            goto done;
        }
        pre = nw;
    }
    for (;;) {
        free(sel);
        sel = (unsigned char *)malloc(s.n > 0 ? s.n : 1);
        if (sel == NULL) { PyErr_NoMemory(); goto done; }
        if (store_above(&s, lf_count, sel) >= n_above || step <= 1) break;
        store_above(&s, lf_refine, sel);
        const long long nw = step / 2 > 1 ? step / 2 : 1;
        if (store_around(&s, sel, nw, step) != 0) {
            if (!PyErr_Occurred()) PyErr_NoMemory();
            goto done;
        }
        step = nw;
    }
    /* _Store.result: each sample's cell, from the finest region containing it */
    {
        const Py_ssize_t cap = s.cap, n = s.n;
        PyObject *out = PyBytes_FromStringAndSize(NULL, 11 * (n > 0 ? n : 0) * D);
        if (out == NULL) goto done;
        double *O = (double *)PyBytes_AS_STRING(out);
        for (int r = 0; r < 11; r++)
            if (r != 2) memcpy(O + r * n, s.col + r * cap, n * D);
        for (Py_ssize_t m = 0; m < n; m++) {
            long long st = LLONG_MAX;
            for (Py_ssize_t r = 0; r < s.nreg; r++) {
                const LatRegion *R = &s.reg[r];
                const long long aa = s.I[m] - R->i0, bb = s.J[m] - R->j0;
                if (aa >= 0 && aa < R->ni && bb >= 0 && bb < R->nj && R->mask[aa * R->nj + bb] && R->step < st)
                    st = R->step;
            }
            const int covered = st < LLONG_MAX;
            const long long sv = covered ? st : 1;
            const int on = covered && s.I[m] % sv == 0 && s.J[m] % sv == 0;
            const double cell = (double)sv * s.unit;
            O[2 * n + m] = on ? cell * cell : 0.0;
        }
        res = Py_BuildValue("(NnL)", out, n, s.need);
    }
done:
    free(sel);
    store_free(&s);
    release_many(cbuf, CHUNK_BUFS);
    release_many(a, 7);
    return res;
}

/*
 * join_gather(items, keep) -> (kx, ky, zf, tscaled, group, data, goffset) and join_distinct(kx, ky, order, zdat,
 * group, goffset) -> (first, inv, z, grow): likelihood.join_exposures' concatenation and merging in two calls (its
 * numpy lines stay as the reference; a test checks they agree to the bit), numpy's argsort of kx and the product
 * conj(data) zf between them (or join_distinct's own sort of kx).
 * join_gather: items, per exposure (kx, ky, transfer, coarse, cweight, data_ft, ny, nx, sigma2); keep, per exposure
 * a uint8 mask of its modes or empty (all). The kept modes one exposure after the other: kx, ky, zf = T w / (ny nx
 * sigma2) and tscaled = T sqrt(w / (ny nx sigma2)) (w = cweight[coarse]; complex128), group = coarse + the
 * exposure's offset among the concatenated sampled modes (int64), data = data_ft at the mode's sampled mode
 * (complex128); goffset, the sampled modes in all.
 * join_distinct: one mode per distinct (kx, ky) (exactly equal), in np.unique's order of kx + i ky (order: kx's
 * argsort, or empty for radix_order's; its runs of equal kx are ordered here by ky, then position): first, each
 * distinct pair's first occurrence; inv, each mode's pair; z, zdat summed per pair in the modes' order
 * (complex_bincount's); grow, each mode's sampled mode numbered among those present (int64 each; z complex128).
 */
static PyObject *join_gather(PyObject *self, PyObject *args)
{
    PyObject *items, *keeps;
    if (!PyArg_ParseTuple(args, "O!O!", &PyTuple_Type, &items, &PyTuple_Type, &keeps)) return NULL;
    const Py_ssize_t ne = PyTuple_GET_SIZE(items);
    if (PyTuple_GET_SIZE(keeps) != ne) {
        PyErr_SetString(PyExc_ValueError, "join_gather: a keep mask per exposure");
        return NULL;
    }
    Py_buffer *b = (Py_buffer *)calloc(7 * (ne > 0 ? ne : 1), sizeof(Py_buffer));
    int *ny = (int *)malloc(2 * (ne > 0 ? ne : 1) * sizeof(int)), *nx = ny + (ne > 0 ? ne : 1);
    double *s2 = (double *)malloc((ne > 0 ? ne : 1) * sizeof(double));
    PyObject *res = NULL;
    if (b == NULL || ny == NULL || s2 == NULL) {
        free(b);
        free(ny);
        free(s2);
        return PyErr_NoMemory();
    }
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    Py_ssize_t total = 0, gtot = 0;
    int bad = 0;
    for (Py_ssize_t e = 0; e < ne && !bad; e++) {
        Py_buffer *x = b + 7 * e;
        PyObject *it = PyTuple_GET_ITEM(items, e);
        if (!PyTuple_Check(it) || !PyArg_ParseTuple(it, "y*y*y*y*y*y*iid", &x[0], &x[1], &x[2], &x[3], &x[4], &x[5],
                                                    &ny[e], &nx[e], &s2[e])
            || PyObject_GetBuffer(PyTuple_GET_ITEM(keeps, e), &x[6], PyBUF_SIMPLE) != 0) {
            bad = 2;
            break;
        }
        const Py_ssize_t n = x[0].len / D, ng = x[4].len / D;
        bad = x[1].len != n * D || x[2].len != 2 * n * D || x[3].len != n * (Py_ssize_t)sizeof(long long)
              || x[5].len != 2 * ng * D || (x[6].len != 0 && x[6].len != n) || ny[e] < 1 || nx[e] < 1;
        const long long *co = (const long long *)x[3].buf;
        const unsigned char *k = (const unsigned char *)x[6].buf;
        for (Py_ssize_t j = 0; !bad && j < n; j++) {
            bad = co[j] < 0 || co[j] >= ng;
            if (x[6].len == 0 || k[j]) total++;
        }
        gtot += ng;
    }
    if (bad) {
        if (bad == 1 || !PyErr_Occurred()) {
            PyErr_Clear();
            PyErr_SetString(PyExc_ValueError, "join_gather: inconsistent buffers");
        }
        goto done;
    }
    {
        PyObject *okx = PyBytes_FromStringAndSize(NULL, total * D), *oky = PyBytes_FromStringAndSize(NULL, total * D);
        PyObject *ozf = PyBytes_FromStringAndSize(NULL, 2 * total * D);
        PyObject *ots = PyBytes_FromStringAndSize(NULL, 2 * total * D);
        PyObject *ogr = PyBytes_FromStringAndSize(NULL, total * (Py_ssize_t)sizeof(long long));
        PyObject *oda = PyBytes_FromStringAndSize(NULL, 2 * total * D);
        if (okx && oky && ozf && ots && ogr && oda) {
            double *KX = (double *)PyBytes_AS_STRING(okx), *KY = (double *)PyBytes_AS_STRING(oky);
            double *ZF = (double *)PyBytes_AS_STRING(ozf), *TS = (double *)PyBytes_AS_STRING(ots);
            double *DA = (double *)PyBytes_AS_STRING(oda);
            long long *GR = (long long *)PyBytes_AS_STRING(ogr);
            Py_ssize_t m = 0;
            long long goff = 0;
            for (Py_ssize_t e = 0; e < ne; e++) {
                const Py_buffer *x = b + 7 * e;
                const Py_ssize_t n = x[0].len / D, ng = x[4].len / D;
                const double *kx = (const double *)x[0].buf, *ky = (const double *)x[1].buf;
                const double *T = (const double *)x[2].buf, *cw = (const double *)x[4].buf;
                const double *df = (const double *)x[5].buf;
                const long long *co = (const long long *)x[3].buf;
                const unsigned char *k = (const unsigned char *)x[6].buf;
                const double norm = 1.0 / ((double)((long long)ny[e] * nx[e]) * s2[e]);
                for (Py_ssize_t j = 0; j < n; j++) {
                    if (x[6].len != 0 && !k[j]) continue;
                    const double w = cw[co[j]], tw = w * norm, sq = sqrt(tw);
                    KX[m] = kx[j];
                    KY[m] = ky[j];
                    ZF[2 * m] = (T[2 * j] * w) * norm;
                    ZF[2 * m + 1] = (T[2 * j + 1] * w) * norm;
                    TS[2 * m] = T[2 * j] * sq;
                    TS[2 * m + 1] = T[2 * j + 1] * sq;
                    GR[m] = co[j] + goff;
                    DA[2 * m] = df[2 * co[j]];
                    DA[2 * m + 1] = df[2 * co[j] + 1];
                    m++;
                }
                goff += ng;
            }
            res = Py_BuildValue("(NNNNNNn)", okx, oky, ozf, ots, ogr, oda, gtot);
            okx = oky = ozf = ots = ogr = oda = NULL;
        }
        Py_XDECREF(okx);
        Py_XDECREF(oky);
        Py_XDECREF(ozf);
        Py_XDECREF(ots);
        Py_XDECREF(ogr);
        Py_XDECREF(oda);
    }
done:
    for (Py_ssize_t e = 0; e < 7 * ne; e++)
        if (b[e].obj != NULL) PyBuffer_Release(&b[e]);
    free(b);
    free(ny);
    free(s2);
    return res;
}

/* the positions 0 .. n - 1 ordered by kx ascending, ties by position (a stable LSD radix sort on kx's bits mapped to
   unsigned integers in the doubles' order, 11 bits a pass, a pass skipped where every key shares its digit): the
   order np.argsort(kx, kind="stable") gives for finite kx, except that -0.0 comes before 0.0 (join_distinct orders
   each run of equal kx, -0.0 == 0.0 there, by ky and position itself: the same canonical order). tmp: n slots. */
static int radix_order(const double *KX, Py_ssize_t n, long long *ord, long long *tmp)
{
    enum { RX_BITS = 11, RX_NB = 1 << RX_BITS, RX_PASSES = 6 };
    const Py_ssize_t n1 = n > 0 ? n : 1;
    uint64_t *key = (uint64_t *)malloc(2 * n1 * sizeof(uint64_t)), *key2 = key + n1;
    Py_ssize_t *cnt = (Py_ssize_t *)calloc((size_t)RX_PASSES * RX_NB, sizeof(Py_ssize_t));
    if (key == NULL || cnt == NULL) {
        free(key);
        free(cnt);
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        uint64_t u;
        memcpy(&u, KX + i, sizeof u);
        u = (u >> 63) ? ~u : (u | 0x8000000000000000ULL);
        key[i] = u;
        for (int p = 0; p < RX_PASSES; p++) cnt[p * RX_NB + ((u >> (p * RX_BITS)) & (RX_NB - 1))]++;
        ord[i] = i;
    }
    /* the keys move with their positions (no indirection in the scatter) */
    long long *src = ord, *dst = tmp;
    uint64_t *ks = key, *kd = key2;
    for (int p = 0; p < RX_PASSES; p++) {
        Py_ssize_t *c = cnt + p * RX_NB;
        const int sh = p * RX_BITS;
        if (n > 0 && c[(ks[0] >> sh) & (RX_NB - 1)] == n) continue;   /* one digit for all: nothing moves */
        Py_ssize_t sum = 0;
        for (int d = 0; d < RX_NB; d++) {
            const Py_ssize_t v = c[d];
            c[d] = sum;
            sum += v;
        }
        for (Py_ssize_t i = 0; i < n; i++) {
            const uint64_t k = ks[i];
            const Py_ssize_t at = c[(k >> sh) & (RX_NB - 1)]++;
            kd[at] = k;
            dst[at] = src[i];
        }
        long long *t = src;
        src = dst;
        dst = t;
        uint64_t *tk = ks;
        ks = kd;
        kd = tk;
    }
    if (src != ord) memcpy(ord, src, n * sizeof(long long));
    free(key);
    free(cnt);
    return 0;
}

static PyObject *join_distinct(PyObject *self, PyObject *args)
{
    Py_buffer kb = {0}, yb = {0}, ob = {0}, zb = {0}, gb = {0};
    Py_ssize_t goffset;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*n", &kb, &yb, &ob, &zb, &gb, &goffset)) return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double), L = (Py_ssize_t)sizeof(long long);
    const Py_ssize_t n = kb.len / D;
    const double *KX = (const double *)kb.buf, *KY = (const double *)yb.buf, *Z = (const double *)zb.buf;
    const long long *O = (const long long *)ob.buf, *G = (const long long *)gb.buf;
    const int own_order = ob.len == 0 && n > 0;   /* no order given: kx's own (radix_order) */
    int bad = yb.len != n * D || (ob.len != n * L && !own_order) || zb.len != 2 * n * D || gb.len != n * L
              || goffset < 0;
    for (Py_ssize_t i = 0; !bad && i < n; i++) bad = (!own_order && (O[i] < 0 || O[i] >= n)) || G[i] < 0 || G[i] >= goffset;
    if (bad) {
        RELEASE(&kb, &yb, &ob, &zb, &gb);
        PyErr_SetString(PyExc_ValueError, "join_distinct: inconsistent buffers");
        return NULL;
    }
    const Py_ssize_t n1 = n > 0 ? n : 1;
    long long *ord = (long long *)malloc(2 * n1 * L), *first = ord + n1;
    long long *pres = (long long *)calloc(goffset > 0 ? goffset : 1, L);
    double *acc = (double *)calloc(2 * n1, D);
    if (ord == NULL || pres == NULL || acc == NULL) {
        free(ord);
        free(pres);
        free(acc);
        RELEASE(&kb, &yb, &ob, &zb, &gb);
        return PyErr_NoMemory();
    }
    if (own_order) {
        if (radix_order(KX, n, ord, first) != 0) {   /* (first: scratch until the pairs are found) */
            free(ord);
            free(pres);
            free(acc);
            RELEASE(&kb, &yb, &ob, &zb, &gb);
            return PyErr_NoMemory();
        }
    }
    else memcpy(ord, O, n * L);
    /* the runs of equal kx in kx's order, each ordered by ky, then position (insertion sort: the runs are the
       exposures' K = 0 and other exact coincidences, short) */
    for (Py_ssize_t i = 0; i < n;) {
        Py_ssize_t j = i + 1;
        while (j < n && KX[ord[j]] == KX[ord[i]]) j++;
        for (Py_ssize_t a = i + 1; a < j; a++) {
            const long long v = ord[a];
            Py_ssize_t c = a;
            while (c > i && (KY[ord[c - 1]] > KY[v] || (KY[ord[c - 1]] == KY[v] && ord[c - 1] > v))) {
                ord[c] = ord[c - 1];
                c--;
            }
            ord[c] = v;
        }
        i = j;
    }
    PyObject *oinv = PyBytes_FromStringAndSize(NULL, n * L), *ogrow = PyBytes_FromStringAndSize(NULL, n * L);
    PyObject *res = NULL;
    if (oinv != NULL && ogrow != NULL) {
        long long *INV = (long long *)PyBytes_AS_STRING(oinv), *GROW = (long long *)PyBytes_AS_STRING(ogrow);
        Py_ssize_t nd = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            const long long o = ord[i];
            if (i == 0 || KX[o] != KX[ord[i - 1]] || KY[o] != KY[ord[i - 1]]) first[nd++] = o;
            INV[o] = nd - 1;
        }
        /* complex_bincount: each pair's real and imaginary sums in the modes' order */
        for (Py_ssize_t j = 0; j < n; j++) {
            acc[2 * INV[j]] += Z[2 * j];
            acc[2 * INV[j] + 1] += Z[2 * j + 1];
        }
        for (Py_ssize_t j = 0; j < n; j++) pres[G[j]] = 1;
        long long c = -1;
        for (Py_ssize_t g = 0; g < goffset; g++) {
            c += pres[g];
            pres[g] = c;
        }
        for (Py_ssize_t j = 0; j < n; j++) GROW[j] = pres[G[j]];
        PyObject *ofirst = PyBytes_FromStringAndSize((const char *)first, nd * L);
        PyObject *oz = PyBytes_FromStringAndSize((const char *)acc, 2 * nd * D);
        if (ofirst != NULL && oz != NULL) res = Py_BuildValue("(NNNN)", ofirst, oinv, oz, ogrow);
        else {
            Py_XDECREF(ofirst);
            Py_XDECREF(oz);
        }
        if (res != NULL) oinv = ogrow = NULL;
    }
    Py_XDECREF(oinv);
    Py_XDECREF(ogrow);
    free(ord);
    free(pres);
    free(acc);
    RELEASE(&kb, &yb, &ob, &zb, &gb);
    return res;
}

/*
 * masked_stamp(image, weight, y) -> (count, lo, hi, sumsq): model._masked_stamp and the figures that noise_variance
 * and _data_modes take, in one pass (their numpy lines stay as the reference; a test checks they agree): y = image
 * where weight > 0, else 0 (float64 each, one size); count, the weights > 0; lo and hi, their least and largest
 * (NaN weights are not > 0); sumsq, np.sum(y * y) (numpy's pairwise summation).
 */
/* numpy's pairwise sum of n doubles (its add.reduce of a contiguous array: blocks of up to 128 summed with eight
   accumulators joined as ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)), halves of larger ranges split at a
   multiple of 8; numpy's np.sum is 0.0 plus this): the same additions in the same order */
static NO_CONTRACT double np_pairwise_sum(const double *a, Py_ssize_t n)
{
    if (n < 8) {
        double res = -0.0;
        for (Py_ssize_t i = 0; i < n; i++) res += a[i];
        return res;
    }
    if (n <= 128) {
        double r[8];
        for (int j = 0; j < 8; j++) r[j] = a[j];
        Py_ssize_t i = 8;
        for (; i < n - (n % 8); i += 8)
            for (int j = 0; j < 8; j++) r[j] += a[i + j];
        double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++) res += a[i];
        return res;
    }
    Py_ssize_t n2 = n / 2;
    n2 -= n2 % 8;
    return np_pairwise_sum(a, n2) + np_pairwise_sum(a + n2, n - n2);
}

static PyObject *masked_stamp(PyObject *self, PyObject *args)
{
    Py_buffer ib, wb, yb;
    if (!PyArg_ParseTuple(args, "y*y*w*", &ib, &wb, &yb)) return NULL;
    const Py_ssize_t n = ib.len / (Py_ssize_t)sizeof(double);
    if (wb.len != ib.len || yb.len != ib.len || ib.len % (Py_ssize_t)sizeof(double) != 0) {
        RELEASE(&ib, &wb, &yb);
        PyErr_SetString(PyExc_ValueError, "masked_stamp: inconsistent buffers");
        return NULL;
    }
    const double *I = (const double *)ib.buf, *W = (const double *)wb.buf;
    double *Y = (double *)yb.buf, lo = INFINITY, hi = -INFINITY;
    Py_ssize_t count = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double w = W[i];
        const int on = w > 0;
        Y[i] = on ? I[i] : 0.0;
        if (on) {
            count++;
            lo = w < lo ? w : lo;
            hi = w > hi ? w : hi;
        }
    }
    /* np.sum(y * y): 0.0 plus the pairwise sum of the squares */
    double *sq = (double *)malloc((n > 0 ? n : 1) * sizeof(double));
    if (sq == NULL) {
        RELEASE(&ib, &wb, &yb);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; i < n; i++) sq[i] = Y[i] * Y[i];
    const double sumsq = 0.0 + np_pairwise_sum(sq, n);
    free(sq);
    RELEASE(&ib, &wb, &yb);
    return Py_BuildValue("(nddd)", count, lo, hi, sumsq);
}

/*
 * complex_bincount(index, values, out) -> whether every index lay within out: model.complex_bincount's sums (its
 * numpy lines stay as the reference; a test checks they agree to the bit): out (complex128, zeroed here) gets each
 * value (complex128) at its index (int64), the real and imaginary parts summed from 0.0 in the values' order as
 * numpy's bincount sums them. An index outside out leaves out unspecified and returns False (numpy's bincount would
 * widen the result: the caller takes the numpy lines).
 */
static PyObject *complex_bincount(PyObject *self, PyObject *args)
{
    Py_buffer ib, vb, ob;
    if (!PyArg_ParseTuple(args, "y*y*w*", &ib, &vb, &ob)) return NULL;
    const Py_ssize_t z = 2 * (Py_ssize_t)sizeof(double), n = ib.len / (Py_ssize_t)sizeof(long long), m = ob.len / z;
    int ok = vb.len == n * z && ib.len % (Py_ssize_t)sizeof(long long) == 0 && ob.len % z == 0;
    if (!ok) {
        RELEASE(&ib, &vb, &ob);
        PyErr_SetString(PyExc_ValueError, "complex_bincount: inconsistent buffers");
        return NULL;
    }
    const long long *I = ib.buf;   /* (the indices, the values as re, im pairs, out likewise: zeroed, then summed) */
    const double *V = vb.buf;
    double *O = memset(ob.buf, 0, (size_t)ob.len);
    for (Py_ssize_t i = 0; i < n; i++) {
        const long long j = I[i];
        if (j < 0 || j >= m) {
            ok = 0;
            break;
        }
        O[2 * j] += V[2 * i];
        O[2 * j + 1] += V[2 * i + 1];
    }
    RELEASE(&ib, &vb, &ob);
    return PyBool_FromLong(ok);
}

/*
 * padded_rows(a, b, h, w, n, rows): calib/kspace._row_transforms' input for two h x w float64 images (the numpy
 * lines stay as the reference; a test checks they agree): rows (2, h, n) float64, each image's rows with column
 * w // 2 at index 0 (the columns left of it at the row's end), zero between.
 * padded_place(part, h, n, out): padded_transforms_rows' placement of the row transforms (part: complex128 (2, h,
 * n // 2 + 1)) into out (complex128 (n, n // 2 + 1, 2)): row h // 2 at index 0, the rows above it at the end, zero
 * between.
 */
static PyObject *padded_rows(PyObject *self, PyObject *args)
{
    Py_buffer ib, nb, rb;
    Py_ssize_t h, w, n;
    if (!PyArg_ParseTuple(args, "y*y*nnnw*", &ib, &nb, &h, &w, &n, &rb)) return NULL;
    const Py_ssize_t dz = (Py_ssize_t)sizeof(double);
    if (h < 1 || w < 1 || w > n || h > n || ib.len != h * w * dz || nb.len != h * w * dz
        || rb.len != 2 * h * n * dz) {
        RELEASE(&ib, &nb, &rb);
        PyErr_SetString(PyExc_ValueError, "padded_rows: inconsistent buffers");
        return NULL;
    }
    const double *I = (const double *)ib.buf, *N = (const double *)nb.buf;
    double *R = (double *)rb.buf;
    const Py_ssize_t c = w / 2;
    memset(R, 0, 2 * h * n * sizeof(double));
    for (Py_ssize_t y = 0; y < h; y++) {
        double *r0 = R + y * n, *r1 = R + (h + y) * n;
        for (Py_ssize_t x = 0; x < w; x++) {
            const Py_ssize_t to = x >= c ? x - c : n - c + x;
            r0[to] = I[y * w + x];
            r1[to] = N[y * w + x];
        }
    }
    RELEASE(&ib, &nb, &rb);
    Py_RETURN_NONE;
}

static PyObject *padded_place(PyObject *self, PyObject *args)
{
    Py_buffer pb, ob;
    Py_ssize_t h, n;
    if (!PyArg_ParseTuple(args, "y*nnw*", &pb, &h, &n, &ob)) return NULL;
    const Py_ssize_t nc = n / 2 + 1, cz = 2 * (Py_ssize_t)sizeof(double);
    if (h < 1 || h > n || pb.len != 2 * h * nc * cz || ob.len != n * nc * 2 * cz) {
        RELEASE(&pb, &ob);
        PyErr_SetString(PyExc_ValueError, "padded_place: inconsistent buffers");
        return NULL;
    }
    const double *P = (const double *)pb.buf;
    double *O = (double *)ob.buf;
    const Py_ssize_t c = h / 2;
    memset(O, 0, n * nc * 2 * cz);
    for (Py_ssize_t y = 0; y < h; y++) {
        const Py_ssize_t row = y >= c ? y - c : n - c + y;
        for (int t = 0; t < 2; t++) {
            const double *src = P + 2 * ((t * h + y) * nc);
            double *dst = O + 2 * (row * nc * 2 + t);
            for (Py_ssize_t kx = 0; kx < nc; kx++) {
                dst[4 * kx] = src[2 * kx];
                dst[4 * kx + 1] = src[2 * kx + 1];
            }
        }
    }
    RELEASE(&pb, &ob);
    Py_RETURN_NONE;
}

/*
 * metacal_noise(weight, image, noise, ny, nx, edge, grow, y, mask) -> var_in: calib/metacal.py's
 * metacal_observations before the images (its numpy lines stay as the reference; a test checks they agree to the
 * bit), for a stamp of ny x nx float64 pixels: y = image where weight > 0, else 0; noise (the symmetrising field's
 * unit normals, in place) times sigma = 1 / sqrt(weight) where weight > 0, else 0; mask (uint8) the pixels within
 * edge of the stamp's border and, unless every weight is positive (whole), those within grow steps of a pixel whose
 * weight is not (the four neighbours' cross, nothing beyond the border); var_in, numpy's mean of sigma^2 over the
 * pixels not masked (in C order: 0.0 plus their pairwise sum, over their count), or 1.0 where none is.
 */
/* numpy's mean of X^2 over the pixels not masked (C order) into *out; returns how many there are, or -1 where memory
   ran out */
static NO_CONTRACT Py_ssize_t np_mean_masked_square(const double *X, const unsigned char *M, Py_ssize_t n, double *out)
{
    double *sq = (double *)malloc((n > 0 ? n : 1) * sizeof(double));
    if (sq == NULL) return -1;
    Py_ssize_t m = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        if (!M[i]) {
            sq[m] = X[i] * X[i];
            m++;
        }
    *out = m ? (0.0 + np_pairwise_sum(sq, m)) / (double)m : 0.0;
    free(sq);
    return m;
}

static PyObject *metacal_noise(PyObject *self, PyObject *args)
{
    Py_buffer wb, ib, nb, yb, mb;
    Py_ssize_t ny, nx, edge, grow;
    if (!PyArg_ParseTuple(args, "y*y*w*nnnnw*w*", &wb, &ib, &nb, &ny, &nx, &edge, &grow, &yb, &mb)) return NULL;
    const Py_ssize_t n = ny * nx, dz = (Py_ssize_t)sizeof(double);
    if (ny < 1 || nx < 1 || edge < 0 || grow < 0 || wb.len != n * dz || ib.len != n * dz || nb.len != n * dz
        || yb.len != n * dz || mb.len != n) {
        RELEASE(&wb, &ib, &nb, &yb, &mb);
        PyErr_SetString(PyExc_ValueError, "metacal_noise: inconsistent buffers");
        return NULL;
    }
    const double *W = (const double *)wb.buf, *I = (const double *)ib.buf;
    double *N = (double *)nb.buf, *Y = (double *)yb.buf;
    unsigned char *M = (unsigned char *)mb.buf;
    double *sigma = (double *)malloc(n * sizeof(double));
    unsigned char *tmp = NULL;   /* (the grown mask's scratch, only where a pixel is masked) */
    if (sigma == NULL) {
        RELEASE(&wb, &ib, &nb, &yb, &mb);
        return PyErr_NoMemory();
    }
    int whole = 1;
    for (Py_ssize_t i = 0; i < n; i++) {
        const int good = W[i] > 0;
        whole &= good;
        sigma[i] = good ? 1.0 / sqrt(W[i]) : 0.0;
        N[i] *= sigma[i];
        Y[i] = good ? I[i] : 0.0;
        M[i] = !good;
    }
    if (whole) {
        memset(M, 0, n);
    } else if (grow > 0) {
        tmp = (unsigned char *)malloc(n);
        if (tmp == NULL) {
            free(sigma);
            RELEASE(&wb, &ib, &nb, &yb, &mb);
            return PyErr_NoMemory();
        }
        /* the masked pixels grown by the four neighbours' cross, grow times (metacal._grown) */
        for (Py_ssize_t g = 0; g < grow; g++) {
            memcpy(tmp, M, n);
            for (Py_ssize_t y = 0; y < ny; y++)
                for (Py_ssize_t x = 0; x < nx; x++) {
                    const Py_ssize_t i = y * nx + x;
                    M[i] = tmp[i] | (y > 0 && tmp[i - nx]) | (y + 1 < ny && tmp[i + nx]) | (x > 0 && tmp[i - 1])
                           | (x + 1 < nx && tmp[i + 1]);
                }
        }
    }
    for (Py_ssize_t y = 0; y < ny; y++)
        for (Py_ssize_t x = 0; x < nx; x++)
            if (y < edge || y >= ny - edge || x < edge || x >= nx - edge) M[y * nx + x] = 1;
    double ms = 0.0;
    const Py_ssize_t some = np_mean_masked_square(sigma, M, n, &ms);
    free(sigma);
    free(tmp);
    RELEASE(&wb, &ib, &nb, &yb, &mb);
    if (some < 0) return PyErr_NoMemory();
    return PyFloat_FromDouble(some ? ms : 1.0);
}

/*
 * metacal_weight(noise0, mask, weight, var_in, out) -> scale: metacal_observations after the images: var_out,
 * numpy's mean of noise0^2 over the pixels not masked (var_in where none is), scale = var_in / max(2 var_out, 1e-300),
 * and out = weight * scale, 0 where masked.
 */
static NO_CONTRACT PyObject *metacal_weight(PyObject *self, PyObject *args)
{
    Py_buffer ob, mb, wb, outb;
    double var_in;
    if (!PyArg_ParseTuple(args, "y*y*y*dw*", &ob, &mb, &wb, &var_in, &outb)) return NULL;
    const Py_ssize_t n = mb.len, dz = (Py_ssize_t)sizeof(double);
    if (ob.len != n * dz || wb.len != n * dz || outb.len != n * dz) {
        RELEASE(&ob, &mb, &wb, &outb);
        PyErr_SetString(PyExc_ValueError, "metacal_weight: inconsistent buffers");
        return NULL;
    }
    const unsigned char *M = (const unsigned char *)mb.buf;
    const double *W = (const double *)wb.buf;
    double *O = (double *)outb.buf;
    double var_out = 0.0;
    const Py_ssize_t some = np_mean_masked_square((const double *)ob.buf, M, n, &var_out);
    if (some < 0) {
        RELEASE(&ob, &mb, &wb, &outb);
        return PyErr_NoMemory();
    }
    if (!some) var_out = var_in;
    /* (Python's max(2 var_out, 1e-300): the first unless the second is larger) */
    const double den = 2.0 * var_out, scale = var_in / (1e-300 > den ? 1e-300 : den);
    for (Py_ssize_t i = 0; i < n; i++) O[i] = M[i] ? 0.0 : W[i] * scale;
    RELEASE(&ob, &mb, &wb, &outb);
    return PyFloat_FromDouble(scale);
}

/*
 * banded_rows(values, start, x, out): out[i, :] = sum_t values[i, t] x[start[i] + t, :] over t = 0 .. w - 1, the
 * product of a banded m x p matrix (row i's w stored values from column start[i], int64, start[i] + w <= p;
 * values m x w float64) with x (p x q float64, C-contiguous) into out (m x q): metacal.dilated_image's products with
 * the Lanczos-15 dilation matrix, whose rows hold at most 30 values (of 144 for an oversampled PSF image), without
 * the zeros' products; each row's terms summed in order of t.
 */
static PyObject *banded_rows(PyObject *self, PyObject *args)
{
    Py_buffer vb, sb, xb, ob;
    if (!PyArg_ParseTuple(args, "y*y*y*w*", &vb, &sb, &xb, &ob)) return NULL;
    const Py_ssize_t dz = (Py_ssize_t)sizeof(double), m = sb.len / (Py_ssize_t)sizeof(long long);
    const Py_ssize_t w = m > 0 ? vb.len / (m * dz) : 0, q = m > 0 ? ob.len / (m * dz) : 0;
    const Py_ssize_t p = q > 0 ? xb.len / (q * dz) : 0;
    const long long *S = (const long long *)sb.buf;
    int bad = m < 1 || w < 1 || q < 1 || vb.len != m * w * dz || ob.len != m * q * dz || xb.len != p * q * dz;
    for (Py_ssize_t i = 0; !bad && i < m; i++) bad = S[i] < 0 || S[i] + w > p;
    if (bad) {
        RELEASE(&vb, &sb, &xb, &ob);
        PyErr_SetString(PyExc_ValueError, "banded_rows: inconsistent buffers");
        return NULL;
    }
    const double *V = (const double *)vb.buf, *X = (const double *)xb.buf;
    double *O = (double *)ob.buf;
    Py_BEGIN_ALLOW_THREADS
    /* each row's sums over t in order: with AVX, BR_COLS columns at a time in registers; SSE2's sixteen registers of
       two doubles would spill them, and it sums the row in memory, as fast there */
    enum { BR_COLS = 16 };
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *v = V + i * w, *x0 = X + S[i] * q;
        double *o = O + i * q;
#if defined(__AVX__)
        Py_ssize_t c0 = 0;
        for (; c0 + BR_COLS <= q; c0 += BR_COLS) {
            v4u a0 = {0.0}, a1 = {0.0}, a2 = {0.0}, a3 = {0.0};
            for (Py_ssize_t t = 0; t < w; t++) {
                const double *x = x0 + t * q + c0;
                const double vt = v[t];
                a0 += vt * *(const v4u *)x;
                a1 += vt * *(const v4u *)(x + 4);
                a2 += vt * *(const v4u *)(x + 8);
                a3 += vt * *(const v4u *)(x + 12);
            }
            *(v4u *)(o + c0) = a0;
            *(v4u *)(o + c0 + 4) = a1;
            *(v4u *)(o + c0 + 8) = a2;
            *(v4u *)(o + c0 + 12) = a3;
        }
        for (Py_ssize_t c = c0; c < q; c++) {
            double acc = 0.0;
            for (Py_ssize_t t = 0; t < w; t++) acc += v[t] * x0[t * q + c];
            o[c] = acc;
        }
#else
        for (Py_ssize_t c = 0; c < q; c++) o[c] = 0.0;
        for (Py_ssize_t t = 0; t < w; t++) {
            const double vt = v[t], *restrict x = x0 + t * q;
            double *restrict oo = o;
            for (Py_ssize_t c = 0; c < q; c++) oo[c] += vt * x[c];
        }
#endif
    }
    Py_END_ALLOW_THREADS
    RELEASE(&vb, &sb, &xb, &ob);
    Py_RETURN_NONE;
}

/*
 * shift_phase(kx, ky, du, dv, out): exp(-i (kx du + ky dv)) per mode (likelihood.shift_joint's numpy line stays as the
 * reference; a test checks they agree to the bit): numpy's complex exp of the purely imaginary -i t is (cos t,
 * sin(-t)) from the C library, t made without contraction as numpy makes it.
 */
#if defined(__GNUC__) && !defined(__clang__)
#define SCALAR_LIBM __attribute__((optimize("fp-contract=off", "no-tree-vectorize")))
#else
#define SCALAR_LIBM NO_CONTRACT
#endif
/* (SCALAR_LIBM: not vectorised, so that cos and sin are the C library's scalar ones, numpy's: GCC's loop of them
   called the vector library's, which differ in the last place) */
static SCALAR_LIBM PyObject *shift_phase(PyObject *self, PyObject *args)
{
    Py_buffer xb, yb, ob;
    double du, dv;
    if (!PyArg_ParseTuple(args, "y*y*ddw*", &xb, &yb, &du, &dv, &ob)) return NULL;
    const Py_ssize_t n = xb.len / (Py_ssize_t)sizeof(double);
    if (yb.len != xb.len || ob.len != 2 * xb.len) {
        RELEASE(&xb, &yb, &ob);
        PyErr_SetString(PyExc_ValueError, "shift_phase: inconsistent buffers");
        return NULL;
    }
    const double *X = (const double *)xb.buf, *Y = (const double *)yb.buf;
    double *O = (double *)ob.buf;
    for (Py_ssize_t j = 0; j < n; j++) {
        const double a = X[j] * du, b = Y[j] * dv, t = a + b;
        O[2 * j] = cos(t);
        O[2 * j + 1] = sin(-t);
    }
    RELEASE(&xb, &yb, &ob);
    Py_RETURN_NONE;
}

/*
 * nearest_map(a, ny, nx, index, inside): pipeline.driver._nearest_map's arrays in one pass (its numpy lines stay as
 * the reference; a test checks they agree): each pixel's offset (dx, dy) from the centre pixel (ny // 2, nx // 2)
 * mapped by the 2 x 2 matrix a (row-major) and rounded half to even (np.rint), a00 dx + a01 dy without contraction
 * as numpy makes it; index (int64) the pixel it lands on, flat, where inside (uint8), else 0.
 */
static NO_CONTRACT PyObject *nearest_map(PyObject *self, PyObject *args)
{
    Py_buffer ab, ib, ob;
    int ny, nx;
    if (!PyArg_ParseTuple(args, "y*iiw*w*", &ab, &ny, &nx, &ib, &ob)) return NULL;
    const Py_ssize_t n = (Py_ssize_t)ny * nx;
    if (ny < 1 || nx < 1 || ab.len != 4 * (Py_ssize_t)sizeof(double) || ib.len != n * (Py_ssize_t)sizeof(long long)
        || ob.len != n) {
        RELEASE(&ab, &ib, &ob);
        PyErr_SetString(PyExc_ValueError, "nearest_map: inconsistent buffers");
        return NULL;
    }
    const double *A = (const double *)ab.buf;
    long long *I = (long long *)ib.buf;
    unsigned char *O = (unsigned char *)ob.buf;
    const int cy = ny / 2, cx = nx / 2;
    for (int y = 0; y < ny; y++)
        for (int x = 0; x < nx; x++) {
            const double dx = (double)(x - cx), dy = (double)(y - cy);
            const double u = A[0] * dx, v = A[1] * dy, s = A[2] * dx, t = A[3] * dy;
            const long long px = (long long)nearbyint(u + v) + cx, py = (long long)nearbyint(s + t) + cy;
            const int in = px >= 0 && px < nx && py >= 0 && py < ny;
            I[(Py_ssize_t)y * nx + x] = in ? py * nx + px : 0;
            O[(Py_ssize_t)y * nx + x] = (unsigned char)in;
        }
    RELEASE(&ab, &ib, &ob);
    Py_RETURN_NONE;
}

/*
 * sky_modes(kx, ky, T, m, flux_scale, Kx, Ky, Ts): model.prepare_exposure's last products in one pass (its numpy lines
 * stay as the reference; a test checks they agree to the bit): the sky wavevectors K = m k (m: the 2 x 2 J^-T,
 * row-major; m00 kx + m01 ky without contraction, as numpy makes it) and the transfer times the flux scale
 * (complex times real, each part one product).
 */
static NO_CONTRACT PyObject *sky_modes(PyObject *self, PyObject *args)
{
    Py_buffer xb, yb, tb, mb, oxb, oyb, otb;
    double fs;
    if (!PyArg_ParseTuple(args, "y*y*y*y*dw*w*w*", &xb, &yb, &tb, &mb, &fs, &oxb, &oyb, &otb)) return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double), n = xb.len / D;
    if (yb.len != xb.len || tb.len != 2 * xb.len || mb.len != 4 * D || oxb.len != xb.len || oyb.len != xb.len
        || otb.len != tb.len) {
        RELEASE(&xb, &yb, &tb, &mb, &oxb, &oyb, &otb);
        PyErr_SetString(PyExc_ValueError, "sky_modes: inconsistent buffers");
        return NULL;
    }
    const double *X = (const double *)xb.buf, *Y = (const double *)yb.buf, *T = (const double *)tb.buf;
    const double *M = (const double *)mb.buf;
    double *OX = (double *)oxb.buf, *OY = (double *)oyb.buf, *OT = (double *)otb.buf;
    for (Py_ssize_t j = 0; j < n; j++) {
        const double a = M[0] * X[j], b = M[1] * Y[j], c = M[2] * X[j], d = M[3] * Y[j];
        OX[j] = a + b;
        OY[j] = c + d;
        OT[2 * j] = T[2 * j] * fs;
        OT[2 * j + 1] = T[2 * j + 1] * fs;
    }
    RELEASE(&xb, &yb, &tb, &mb, &oxb, &oyb, &otb);
    Py_RETURN_NONE;
}

/*
 * coarse_modes(kx, ky, transfer, coarse, keep, data_ft, xp, fp, index, base, shift, r2, out) and
 * coarse_gather(h, nx, sigma2, jinv, grid, total): likelihood.coarse_peak's work per exposure, its numpy lines'
 * arithmetic without fused multiply-adds (numpy's complex product may fuse its own, so the cross-correlation's
 * transform agrees to rounding, and the sums gathered from one h to the bit: a test checks both).
 * coarse_modes: per mode j (those keep marks: uint8, or every mode where keep is empty) the round model's
 * transform R at rho^2 = r2 (kx^2 + ky^2) (table_interp's lookup in the table xp, fp), the products transfer R
 * summed into the sampled modes coarse[j] (complex_bincount's order), and out = conj(conj(data_ft) S), the
 * cross-correlation's transform (complex128 of the stamp's rfft grid, as data_ft).
 * coarse_gather: the exposure's cross-correlation h (ny x nx, unnormalised) divided by sigma2, gathered at the
 * nearest pixel of each sky offset (grid[a], grid[b]) through the inverse Jacobian (jinv: 4 doubles, row-major)
 * and added to total (n x n, n = len(grid)).
 */
/* coarse_modes' arithmetic, without contraction into fused multiply-adds (the numpy lines' numbers); w: scratch
   of 2 n + 2 ng doubles */
static NO_CONTRACT void coarse_modes_loop(const double *KX, const double *KY, const double *T, const long long *CO,
                                          const unsigned char *KEEP, Py_ssize_t n, const double *Y, Py_ssize_t ng,
                                          const double *XP, const double *FP, Py_ssize_t m, const int *IDX,
                                          Py_ssize_t nidx, long long base, int shift, double r2, double *w,
                                          double *O)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    double *x = w, *R = w + n, *acc = w + 2 * n;
    /* the dropped modes' transforms are not needed: rho^2 = 0 finds the table's first node at once */
    for (Py_ssize_t j = 0; j < n; j++) x[j] = KEEP == NULL || KEEP[j] ? r2 * (KX[j] * KX[j] + KY[j] * KY[j]) : 0.0;
    table_lookup_n(XP, FP, m, IDX, nidx, base, shift, 0.0, x, n, R);
    for (Py_ssize_t g = 0; g < 2 * ng; g++) acc[g] = 0.0;
    for (Py_ssize_t j = 0; j < n; j++) {
        if (KEEP != NULL && !KEEP[j]) continue;
        const Py_ssize_t c = (Py_ssize_t)CO[j];
        acc[c] += T[2 * j] * R[j];
        acc[ng + c] += T[2 * j + 1] * R[j];
    }
    for (Py_ssize_t g = 0; g < ng; g++) {
        const double yr = Y[2 * g], yi = Y[2 * g + 1], sr = acc[g], si = acc[ng + g];
        O[2 * g] = yr * sr - (-yi) * si;
        O[2 * g + 1] = -(yr * si + (-yi) * sr);
    }
}

static PyObject *coarse_modes(PyObject *self, PyObject *args)
{
    Py_buffer kxb, kyb, tb, cb, keb, yb, xpb, fpb, ib, ob;
    long long base;
    int shift;
    double r2;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*Lidw*", &kxb, &kyb, &tb, &cb, &keb, &yb, &xpb, &fpb, &ib, &base,
                          &shift, &r2, &ob)) return NULL;
#define CM_RELEASE RELEASE(&kxb, &kyb, &tb, &cb, &keb, &yb, &xpb, &fpb, &ib, &ob)
    const Py_ssize_t D = (Py_ssize_t)sizeof(double);
    const Py_ssize_t n = kxb.len / D, ng = yb.len / (2 * D), m = xpb.len / D, nidx = ib.len / (Py_ssize_t)sizeof(int);
    const int *IDX = (const int *)ib.buf;
    int bad = kyb.len != kxb.len || tb.len != 2 * kxb.len || cb.len != n * (Py_ssize_t)sizeof(long long)
              || (keb.len != 0 && keb.len != n) || ob.len != yb.len || fpb.len != xpb.len
              || !table_ok(IDX, nidx, m, shift, base);
    const long long *CO = (const long long *)cb.buf;
    for (Py_ssize_t j = 0; !bad && j < n; j++) bad = CO[j] < 0 || CO[j] >= ng;
    if (bad) {
        CM_RELEASE;
        PyErr_SetString(PyExc_ValueError, "coarse_modes: inconsistent buffers");
        return NULL;
    }
    double *acc = (double *)malloc((2 * n + 2 * ng + 1) * sizeof(double));
    if (acc == NULL) {
        CM_RELEASE;
        return PyErr_NoMemory();
    }
    coarse_modes_loop((const double *)kxb.buf, (const double *)kyb.buf, (const double *)tb.buf, CO,
                      keb.len ? (const unsigned char *)keb.buf : NULL, n, (const double *)yb.buf, ng,
                      (const double *)xpb.buf, (const double *)fpb.buf, m, IDX, nidx, base, shift, r2, acc,
                      (double *)ob.buf);
    free(acc);
    CM_RELEASE;
#undef CM_RELEASE
    Py_RETURN_NONE;
}

static NO_CONTRACT void coarse_gather_loop(const double *H, Py_ssize_t ny, Py_ssize_t nx, double sigma2,
                                           const double *J, const double *grid, Py_ssize_t ng, double *total)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    for (Py_ssize_t a = 0; a < ng; a++) {
        const double gu = grid[a];
        for (Py_ssize_t b = 0; b < ng; b++) {
            const double gv = grid[b];
            long long sx = (long long)rint(J[0] * gu + J[1] * gv) % (long long)nx;
            long long sy = (long long)rint(J[2] * gu + J[3] * gv) % (long long)ny;
            sx += sx < 0 ? nx : 0;
            sy += sy < 0 ? ny : 0;
            total[a * ng + b] += H[sy * nx + sx] / sigma2;
        }
    }
}

static PyObject *coarse_gather(PyObject *self, PyObject *args)
{
    Py_buffer hb, jb, gb, tb;
    Py_ssize_t nx;
    double sigma2;
    if (!PyArg_ParseTuple(args, "y*ndy*y*w*", &hb, &nx, &sigma2, &jb, &gb, &tb)) return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double), ng = gb.len / D;
    const Py_ssize_t ny = nx > 0 ? hb.len / (D * nx) : 0;
    if (nx < 1 || ny < 1 || hb.len != ny * nx * D || jb.len != 4 * D || tb.len != ng * ng * D) {
        RELEASE(&hb, &jb, &gb, &tb);
        PyErr_SetString(PyExc_ValueError, "coarse_gather: inconsistent buffers");
        return NULL;
    }
    const double *J = (const double *)jb.buf;
    const double *grid = (const double *)gb.buf;
    int finite = 1;
    for (int i = 0; i < 4; i++) finite &= isfinite(J[i]);
    for (Py_ssize_t a = 0; a < ng; a++) finite &= isfinite(grid[a]);
    if (!finite) {
        RELEASE(&hb, &jb, &gb, &tb);
        PyErr_SetString(PyExc_ValueError, "coarse_gather: the inverse Jacobian and the grid must be finite");
        return NULL;
    }
    coarse_gather_loop((const double *)hb.buf, ny, nx, sigma2, J, grid, ng, (double *)tb.buf);
    RELEASE(&hb, &jb, &gb, &tb);
    Py_RETURN_NONE;
}

/*
 * fold_groups(row, col, t, n, q) -> None or (multi, msizes, data, indices, indptr): likelihood._fold_groups's
 * numbers (its numpy lines stay as the reference; a test checks they agree) for the entries t (complex128) of a
 * sparse F at (row, col) (int64, each pair at most once), n columns. q (n doubles, written): H's diagonal for the
 * columns that share no row with another, 0 elsewhere. Where some do, the fold groups (the columns linked
 * through shared rows, each labelled by its least column, ordered by label, columns ascending within) and H
 * restricted to them in csr form (int64 multi, msizes, indices, indptr; complex128 data), each element summed
 * over its rows in ascending order, as bytearrays. The products conj(t_a) t_b without fused multiply-adds, as
 * numpy's.
 */
static Py_ssize_t fg_find(Py_ssize_t *parent, Py_ssize_t a)
{
    while (parent[a] != a) {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    return a;
}

static NO_CONTRACT void fg_conj_mul(const double *a, const double *b, double *re, double *im)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const double ar = a[0], ai = -a[1], br = b[0], bi = b[1];
    *re = ar * br - ai * bi;
    *im = ar * bi + ai * br;
}

/* |t|^2 of n complex entries, as numpy's (conj(t) t).real without a fused multiply-add */
static NO_CONTRACT void fg_squares(const double *T, Py_ssize_t n, double *TT)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    for (Py_ssize_t e = 0; e < n; e++) TT[e] = T[2 * e] * T[2 * e] - (-T[2 * e + 1]) * T[2 * e + 1];
}

/* entries (row, index) ordered by row, then index (qsort's comparison) */
static int fg_cmp(const void *x, const void *y)
{
    const int64_t *a = (const int64_t *)x, *b = (const int64_t *)y;
    return a[0] < b[0] ? -1 : a[0] > b[0] ? 1 : (a[1] < b[1] ? -1 : a[1] > b[1]);
}

static PyObject *fold_groups(PyObject *self, PyObject *args)
{
    Py_buffer rb, cb, tb, qb;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "y*y*y*nw*", &rb, &cb, &tb, &n, &qb)) return NULL;
    const Py_ssize_t ne = rb.len / (Py_ssize_t)sizeof(int64_t);
    const int64_t *ROW = (const int64_t *)rb.buf, *COL = (const int64_t *)cb.buf;
    const double *T = (const double *)tb.buf;
    double *Q = (double *)qb.buf;
    int bad = n < 0 || cb.len != rb.len || tb.len != 2 * ne * (Py_ssize_t)sizeof(double)
              || qb.len != n * (Py_ssize_t)sizeof(double);
    Py_ssize_t nrow = 0;
    for (Py_ssize_t e = 0; !bad && e < ne; e++) {
        bad = ROW[e] < 0 || COL[e] < 0 || COL[e] >= n;
        if (!bad && ROW[e] + 1 > nrow) nrow = (Py_ssize_t)ROW[e] + 1;
    }
    if (bad) {
        RELEASE(&rb, &cb, &tb, &qb);
        PyErr_SetString(PyExc_ValueError, "fold_groups: inconsistent buffers");
        return NULL;
    }
    /* scratch: per row its count of entries; |t|^2; per column linked, its root, place and group */
    int32_t *rcount = (int32_t *)calloc((size_t)(nrow + 1), sizeof(int32_t));
    double *TT = (double *)malloc((size_t)(ne + 1) * sizeof(double));
    unsigned char *linked = (unsigned char *)calloc((size_t)(n + 1), 1);
    Py_ssize_t *parent = (Py_ssize_t *)malloc((size_t)(4 * (n + 1)) * sizeof(Py_ssize_t));
    int64_t *rel = NULL, *multi = NULL, *msizes = NULL, *gstart = NULL, *boff = NULL, *ind = NULL, *iptr = NULL;
    double *blk = NULL, *dat = NULL;
    unsigned char *present = NULL;
    PyObject *res = NULL;
    int nomem = rcount == NULL || TT == NULL || linked == NULL || parent == NULL;
    Py_ssize_t nm = 0, ng = 0, nnz = 0, nblk = 0, nrel = 0;
    if (!nomem) {
        for (Py_ssize_t e = 0; e < ne; e++) rcount[ROW[e]]++;
        fg_squares(T, ne, TT);
        for (Py_ssize_t c = 0; c < n; c++) Q[c] = 0.0;
        for (Py_ssize_t e = 0; e < ne; e++) {
            Q[COL[e]] += TT[e];
            if (rcount[ROW[e]] >= 2) linked[COL[e]] = 1;
        }
        for (Py_ssize_t c = 0; c < n; c++) if (linked[c]) { Q[c] = 0.0; nm++; }
        /* the linked columns' entries (row, entry), by row: every entry of a shared row is one */
        for (Py_ssize_t e = 0; e < ne; e++) nrel += linked[COL[e]];
        if (nm > 0) {
            rel = (int64_t *)malloc((size_t)(2 * nrel) * sizeof(int64_t));
            multi = (int64_t *)malloc((size_t)nm * sizeof(int64_t));
            msizes = (int64_t *)malloc((size_t)nm * sizeof(int64_t));
            gstart = (int64_t *)malloc((size_t)(nm + 1) * sizeof(int64_t));
            boff = (int64_t *)malloc((size_t)(nm + 1) * sizeof(int64_t));
            nomem = rel == NULL || multi == NULL || msizes == NULL || gstart == NULL || boff == NULL;
        }
    }
    if (!nomem && nm > 0) {
        Py_ssize_t *pos = parent + (n + 1), *grp = parent + 2 * (n + 1), *lab = parent + 3 * (n + 1);
        Py_ssize_t k = 0;
        for (Py_ssize_t e = 0; e < ne; e++)
            if (linked[COL[e]]) { rel[2 * k] = ROW[e]; rel[2 * k + 1] = e; k++; }
        qsort(rel, (size_t)nrel, 2 * sizeof(int64_t), fg_cmp);
        /* the groups: union of the columns of each shared row, the least column the root */
        for (Py_ssize_t c = 0; c < n; c++) parent[c] = c;
        for (Py_ssize_t k0 = 0; k0 < nrel;) {
            Py_ssize_t k1 = k0 + 1;
            while (k1 < nrel && rel[2 * k1] == rel[2 * k0]) k1++;
            Py_ssize_t a = fg_find(parent, (Py_ssize_t)COL[rel[2 * k0 + 1]]);
            for (Py_ssize_t kk = k0 + 1; kk < k1; kk++) {
                Py_ssize_t b = fg_find(parent, (Py_ssize_t)COL[rel[2 * kk + 1]]);
                if (a == b) continue;
                if (a < b) parent[b] = a;
                else { parent[a] = b; a = b; }
            }
            k0 = k1;
        }
        /* multi: the linked columns by (label, column); groups in label order (pos: a label's count, then its
           group's next place; grp: a label's group number) */
        for (Py_ssize_t c = 0; c < n; c++) pos[c] = 0;
        for (Py_ssize_t c = 0; c < n; c++)
            if (linked[c]) {
                lab[c] = fg_find(parent, c);
                pos[lab[c]]++;
            }
        Py_ssize_t at = 0;
        for (Py_ssize_t c = 0; c < n; c++)
            if (linked[c] && lab[c] == c) {
                const Py_ssize_t size = pos[c];
                grp[c] = ng;
                gstart[ng] = at;
                msizes[ng] = size;
                boff[ng] = nblk;
                nblk += size * size;
                pos[c] = at;
                at += size;
                ng++;
            }
        gstart[ng] = at;
        boff[ng] = nblk;
        for (Py_ssize_t c = 0; c < n; c++)
            if (linked[c]) {
                const Py_ssize_t l = lab[c];
                multi[pos[l]] = c;
                parent[c] = pos[l]++;   /* (parent now holds each linked column's place in multi) */
                grp[c] = grp[l];
            }
        blk = (double *)malloc((size_t)(2 * (nblk > 0 ? nblk : 1)) * sizeof(double));
        present = (unsigned char *)calloc((size_t)(nblk > 0 ? nblk : 1), 1);
        nomem = blk == NULL || present == NULL;
        if (!nomem) {
            /* H's terms, row after row ascending: every pair of a shared row's columns, and a linked column's own
               term on a row it has alone */
            for (Py_ssize_t k0 = 0; k0 < nrel;) {
                Py_ssize_t k1 = k0 + 1;
                while (k1 < nrel && rel[2 * k1] == rel[2 * k0]) k1++;
                for (Py_ssize_t ka = k0; ka < k1; ka++) {
                    const Py_ssize_t ea = (Py_ssize_t)rel[2 * ka + 1], ca = (Py_ssize_t)COL[ea], g = grp[ca];
                    const Py_ssize_t p = msizes[g], li = parent[ca] - gstart[g];
                    for (Py_ssize_t kb = k0; kb < k1; kb++) {
                        const Py_ssize_t eb = (Py_ssize_t)rel[2 * kb + 1], lj = parent[COL[eb]] - gstart[g];
                        const Py_ssize_t at2 = boff[g] + li * p + lj;
                        double re, im;
                        fg_conj_mul(T + 2 * ea, T + 2 * eb, &re, &im);
                        if (present[at2]) {
                            blk[2 * at2] += re;
                            blk[2 * at2 + 1] += im;
                        } else {
                            blk[2 * at2] = re;
                            blk[2 * at2 + 1] = im;
                            present[at2] = 1;
                            nnz++;
                        }
                    }
                }
                k0 = k1;
            }
            ind = (int64_t *)malloc((size_t)(nnz > 0 ? nnz : 1) * sizeof(int64_t));
            iptr = (int64_t *)malloc((size_t)(nm + 1) * sizeof(int64_t));
            dat = (double *)malloc((size_t)(2 * (nnz > 0 ? nnz : 1)) * sizeof(double));
            nomem = ind == NULL || iptr == NULL || dat == NULL;
        }
        if (!nomem) {
            Py_ssize_t z = 0;
            for (Py_ssize_t g = 0; g < ng; g++) {
                const Py_ssize_t p = msizes[g];
                for (Py_ssize_t li = 0; li < p; li++) {
                    iptr[gstart[g] + li] = z;
                    for (Py_ssize_t lj = 0; lj < p; lj++) {
                        const Py_ssize_t at2 = boff[g] + li * p + lj;
                        if (!present[at2]) continue;
                        ind[z] = gstart[g] + lj;
                        dat[2 * z] = blk[2 * at2];
                        dat[2 * z + 1] = blk[2 * at2 + 1];
                        z++;
                    }
                }
            }
            iptr[nm] = z;
            PyObject *o1 = PyByteArray_FromStringAndSize((const char *)multi, nm * 8);
            PyObject *o2 = PyByteArray_FromStringAndSize((const char *)msizes, ng * 8);
            PyObject *o3 = PyByteArray_FromStringAndSize((const char *)dat, nnz * 16);
            PyObject *o4 = PyByteArray_FromStringAndSize((const char *)ind, nnz * 8);
            PyObject *o5 = PyByteArray_FromStringAndSize((const char *)iptr, (nm + 1) * 8);
            if (o1 && o2 && o3 && o4 && o5) res = PyTuple_Pack(5, o1, o2, o3, o4, o5);
            Py_XDECREF(o1); Py_XDECREF(o2); Py_XDECREF(o3); Py_XDECREF(o4); Py_XDECREF(o5);
        }
    }
    free(rcount); free(TT); free(linked); free(parent); free(rel); free(multi); free(msizes); free(gstart);
    free(boff); free(blk); free(present); free(ind); free(iptr); free(dat);
    RELEASE(&rb, &cb, &tb, &qb);
    if (nomem) return PyErr_NoMemory();
    if (res == NULL && !PyErr_Occurred()) Py_RETURN_NONE;
    return res;
}

/*
 * mode_bound(transfer, coarse, cweight, data_ft, norm, p) -> (h, ff): likelihood._mode_bounds' work for one
 * exposure (its numpy lines stay as the reference): per mode j, w = cweight[coarse[j]] and p[j] = w |T_j|^2 norm
 * (|T|^2 as re^2 + im^2, where numpy squares its hypot: the same to rounding); h = norm sum_j Re(conj(Y[coarse[j]])
 * T_j) w and ff = sum_j p[j], summed in order (numpy's sums are pairwise: the same to rounding).
 */
static NO_CONTRACT void mode_bound_loop(const double *T, const int64_t *CO, const double *CW, const double *Y,
                                        Py_ssize_t n, double norm, double *P, double *h_out, double *ff_out)
{
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    double h = 0.0, ff = 0.0;
    for (Py_ssize_t j = 0; j < n; j++) {
        const double w = CW[CO[j]];
        P[j] = w * (T[2 * j] * T[2 * j] + T[2 * j + 1] * T[2 * j + 1]) * norm;
        ff += P[j];
        const double yr = Y[2 * CO[j]], yi = -Y[2 * CO[j] + 1], tr = T[2 * j], ti = T[2 * j + 1];
        h += (yr * tr - yi * ti) * w;
    }
    *h_out = h * norm;
    *ff_out = ff;
}

static PyObject *mode_bound(PyObject *self, PyObject *args)
{
    Py_buffer tb, cb, wb, yb, pb;
    double norm;
    if (!PyArg_ParseTuple(args, "y*y*y*y*dw*", &tb, &cb, &wb, &yb, &norm, &pb)) return NULL;
    const Py_ssize_t n = cb.len / (Py_ssize_t)sizeof(int64_t), nw = wb.len / (Py_ssize_t)sizeof(double);
    const int64_t *CO = (const int64_t *)cb.buf;
    int bad = tb.len != 2 * n * (Py_ssize_t)sizeof(double) || pb.len != n * (Py_ssize_t)sizeof(double)
              || yb.len != 2 * nw * (Py_ssize_t)sizeof(double);
    for (Py_ssize_t j = 0; !bad && j < n; j++) bad = CO[j] < 0 || CO[j] >= nw;
    if (bad) {
        RELEASE(&tb, &cb, &wb, &yb, &pb);
        PyErr_SetString(PyExc_ValueError, "mode_bound: inconsistent buffers");
        return NULL;
    }
    double h, ff;
    mode_bound_loop((const double *)tb.buf, CO, (const double *)wb.buf, (const double *)yb.buf, n, norm,
                    (double *)pb.buf, &h, &ff);
    RELEASE(&tb, &cb, &wb, &yb, &pb);
    return Py_BuildValue("dd", h, ff);
}

/*
 * drop_threshold(b, tolerance) -> t or None: likelihood._drop_threshold's number (its numpy lines stay as the
 * reference; a test checks they agree): the values <= tolerance (-0.0 as 0.0) summed in buckets of their bit
 * patterns (>> 47), in order; the bucket where the cumulative sum first exceeds the tolerance sorted and summed
 * from the buckets below; the largest value that ends a run of equal values with the sum within the tolerance,
 * else the largest value of the buckets below, else None.
 */
static int dbl_cmp(const void *x, const void *y)
{
    const double a = *(const double *)x, b = *(const double *)y;
    return a < b ? -1 : a > b;
}

static PyObject *drop_threshold(PyObject *self, PyObject *args)
{
    Py_buffer bb;
    double tol;
    if (!PyArg_ParseTuple(args, "y*d", &bb, &tol)) return NULL;
    const Py_ssize_t n = bb.len / (Py_ssize_t)sizeof(double);
    const double *B = (const double *)bb.buf;
    double *v = (double *)malloc((size_t)(n + 1) * sizeof(double));
    int64_t *key = (int64_t *)malloc((size_t)(n + 1) * sizeof(int64_t));
    double *csum = NULL, *w = NULL;
    int nomem = v == NULL || key == NULL, found = 0;
    double t = 0.0;
    if (!nomem) {
        Py_ssize_t m = 0;
        for (Py_ssize_t i = 0; i < n; i++)
            if (B[i] <= tol) v[m++] = B[i] + 0.0;
        int64_t k0 = INT64_MAX, k1 = INT64_MIN;
        for (Py_ssize_t i = 0; i < m; i++) {
            int64_t bits;
            memcpy(&bits, v + i, sizeof bits);
            key[i] = bits >> 47;
            if (key[i] < k0) k0 = key[i];
            if (key[i] > k1) k1 = key[i];
        }
        if (m > 0) {
            const Py_ssize_t nb = (Py_ssize_t)(k1 - k0) + 1;
            csum = (double *)calloc((size_t)nb, sizeof(double));
            w = (double *)malloc((size_t)m * sizeof(double));
            nomem = csum == NULL || w == NULL;
            if (!nomem) {
                for (Py_ssize_t i = 0; i < m; i++) { key[i] -= k0; csum[key[i]] += v[i]; }
                for (Py_ssize_t b = 1; b < nb; b++) csum[b] += csum[b - 1];
                Py_ssize_t j = 0;
                while (j < nb && !(csum[j] > tol)) j++;   /* searchsorted(csum, tol, 'right') */
                if (j < nb) {
                    Py_ssize_t nw = 0;
                    for (Py_ssize_t i = 0; i < m; i++) if (key[i] == j) w[nw++] = v[i];
                    qsort(w, (size_t)nw, sizeof(double), dbl_cmp);
                    const double base = j > 0 ? csum[j - 1] : 0.0;
                    double cs = 0.0;
                    for (Py_ssize_t i = 0; i < nw; i++) {
                        cs = i == 0 ? w[0] : cs + w[i];
                        const int last = i + 1 == nw || w[i + 1] != w[i];
                        if (last && base + cs <= tol) { t = w[i]; found = 1; }
                    }
                }
                if (!found && j > 0) {
                    for (Py_ssize_t i = 0; i < m; i++)
                        if (key[i] < j && (!found || v[i] > t)) { t = v[i]; found = 1; }
                }
            }
        }
    }
    free(v); free(key); free(csum); free(w);
    PyBuffer_Release(&bb);
    if (nomem) return PyErr_NoMemory();
    if (!found) Py_RETURN_NONE;
    return PyFloat_FromDouble(t);
}

/*
 * bins_geometry(multi, basis, q, indptr, indices, data, order, b3, qcol) -> (gsel, pa, pb, ph): likelihood.
 * _bins_geometry's arrays (its numpy lines stay as the reference; a test checks they agree to the bit): the
 * modes' order (those alone on their sampled mode ascending, then multi's), b3 = [kx^2, 2 kx ky, ky^2, 0] of
 * each (float32, from basis: 3 x n doubles), qcol (float32): q for the modes alone, H's diagonal (real) for
 * multi's; and the fold groups' pairs: H's (csr over multi: int64 indptr, indices; complex128 data) entries
 * above the diagonal with a real part, in csr order, as (gsel: the modes they touch, ascending, as rows of the
 * order; pa, pb: each pair's two among gsel; ph = 2 Re H_ab), bytearrays.
 */
static PyObject *bins_geometry(PyObject *self, PyObject *args)
{
    Py_buffer mb, bb, qb, ipb, inb, db, ob, b3b, qcb;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*w*w*w*", &mb, &bb, &qb, &ipb, &inb, &db, &ob, &b3b, &qcb)) return NULL;
    const Py_ssize_t n = qb.len / (Py_ssize_t)sizeof(double), nm = mb.len / (Py_ssize_t)sizeof(int64_t);
    const Py_ssize_t nnz = inb.len / (Py_ssize_t)sizeof(int64_t);
    const int64_t *MU = (const int64_t *)mb.buf, *IP = (const int64_t *)ipb.buf, *IN = (const int64_t *)inb.buf;
    int bad = nm > n || bb.len != 3 * n * (Py_ssize_t)sizeof(double) || ipb.len != (nm + 1) * (Py_ssize_t)sizeof(int64_t)
              || db.len != 2 * nnz * (Py_ssize_t)sizeof(double) || ob.len != n * (Py_ssize_t)sizeof(int64_t)
              || b3b.len != 4 * n * (Py_ssize_t)sizeof(float) || qcb.len != n * (Py_ssize_t)sizeof(float);
    for (Py_ssize_t i = 0; !bad && i < nm; i++) bad = MU[i] < 0 || MU[i] >= n;
    for (Py_ssize_t i = 0; !bad && i < nm; i++) bad = IP[i] < 0 || IP[i] > IP[i + 1] || IP[i + 1] > nnz;
    bad = bad || (nm > 0 && IP[0] != 0);
    for (Py_ssize_t k = 0; !bad && k < nnz; k++) bad = IN[k] < 0 || IN[k] >= nm;
    if (bad) {
        RELEASE(&mb, &bb, &qb, &ipb, &inb, &db, &ob, &b3b, &qcb);
        PyErr_SetString(PyExc_ValueError, "bins_geometry: inconsistent buffers");
        return NULL;
    }
    const double *B = (const double *)bb.buf, *Q = (const double *)qb.buf, *D = (const double *)db.buf;
    int64_t *O = (int64_t *)ob.buf;
    float *B3 = (float *)b3b.buf, *QC = (float *)qcb.buf;
    unsigned char *inm = (unsigned char *)calloc((size_t)(n + 1), 1);
    int64_t *pr = (int64_t *)malloc((size_t)(2 * nnz + 1) * sizeof(int64_t));
    double *ph = (double *)malloc((size_t)(nnz + 1) * sizeof(double));
    int64_t *map = (int64_t *)malloc((size_t)(nm + 1) * sizeof(int64_t));
    PyObject *res = NULL;
    if (inm == NULL || pr == NULL || ph == NULL || map == NULL) {
        free(inm); free(pr); free(ph); free(map);
        RELEASE(&mb, &bb, &qb, &ipb, &inb, &db, &ob, &b3b, &qcb);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; i < nm; i++) inm[MU[i]] = 1;
    Py_ssize_t ns = 0;
    for (Py_ssize_t j = 0; j < n; j++) if (!inm[j]) O[ns++] = j;
    const Py_ssize_t n_single = ns;
    for (Py_ssize_t i = 0; i < nm; i++) O[n_single + i] = MU[i];
    for (Py_ssize_t i = 0; i < n; i++) {
        const int64_t j = O[i];
        B3[4 * i] = (float)B[j];
        B3[4 * i + 1] = (float)B[n + j];
        B3[4 * i + 2] = (float)B[2 * n + j];
        B3[4 * i + 3] = 0.0f;
        QC[i] = i < n_single ? (float)Q[j] : 0.0f;
    }
    /* H's diagonal (real) for multi's rows, and its pairs above the diagonal with a real part */
    Py_ssize_t np_ = 0;
    for (Py_ssize_t i = 0; i < nm; i++) map[i] = 0;
    for (Py_ssize_t i = 0; i < nm; i++)
        for (int64_t k = IP[i]; k < IP[i + 1]; k++) {
            const int64_t c = IN[k];
            const double re = D[2 * k];
            if (c == i) QC[n_single + i] = (float)re;
            if (i < c && re != 0) {
                pr[2 * np_] = i;
                pr[2 * np_ + 1] = c;
                ph[np_] = 2.0 * re;
                map[i] = map[c] = 1;
                np_++;
            }
        }
    Py_ssize_t ng = 0;
    for (Py_ssize_t i = 0; i < nm; i++) map[i] = map[i] ? ng++ : -1;
    int64_t *gsel = (int64_t *)malloc((size_t)(ng + 1) * sizeof(int64_t));
    int64_t *pa = (int64_t *)malloc((size_t)(np_ + 1) * sizeof(int64_t));
    int64_t *pb = (int64_t *)malloc((size_t)(np_ + 1) * sizeof(int64_t));
    if (gsel != NULL && pa != NULL && pb != NULL) {
        for (Py_ssize_t i = 0; i < nm; i++) if (map[i] >= 0) gsel[map[i]] = n_single + i;
        for (Py_ssize_t k = 0; k < np_; k++) {
            pa[k] = map[pr[2 * k]];
            pb[k] = map[pr[2 * k + 1]];
        }
        PyObject *o1 = PyByteArray_FromStringAndSize((const char *)gsel, ng * 8);
        PyObject *o2 = PyByteArray_FromStringAndSize((const char *)pa, np_ * 8);
        PyObject *o3 = PyByteArray_FromStringAndSize((const char *)pb, np_ * 8);
        PyObject *o4 = PyByteArray_FromStringAndSize((const char *)ph, np_ * 8);
        if (o1 && o2 && o3 && o4) res = PyTuple_Pack(4, o1, o2, o3, o4);
        Py_XDECREF(o1); Py_XDECREF(o2); Py_XDECREF(o3); Py_XDECREF(o4);
    }
    int nomem = gsel == NULL || pa == NULL || pb == NULL;
    free(inm); free(pr); free(ph); free(map); free(gsel); free(pa); free(pb);
    RELEASE(&mb, &bb, &qb, &ipb, &inb, &db, &ob, &b3b, &qcb);
    if (nomem) return PyErr_NoMemory();
    return res;
}

/*
 * bins_channels(order, z, kx, ky, qcol, c8): likelihood._packed_bins' weights (its numpy lines stay as the
 * reference; a test checks they agree to the bit): per mode i of the order, the six linear vectors of mode
 * order[i] (Re z, kx Im z, ky Im z, -kx kx Re z, -kx ky Re z, -ky ky Re z, as _linear_rows multiplies them), its
 * qcol and 0, as float32 (n x 8).
 */
static PyObject *bins_channels(PyObject *self, PyObject *args)
{
    Py_buffer ob, zb, xb, yb, qb, cb;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*", &ob, &zb, &xb, &yb, &qb, &cb)) return NULL;
    const Py_ssize_t n = ob.len / (Py_ssize_t)sizeof(int64_t), nz = xb.len / (Py_ssize_t)sizeof(double);
    const int64_t *O = (const int64_t *)ob.buf;
    int bad = zb.len != 2 * nz * (Py_ssize_t)sizeof(double) || yb.len != xb.len
              || qb.len != n * (Py_ssize_t)sizeof(float) || cb.len != 8 * n * (Py_ssize_t)sizeof(float);
    for (Py_ssize_t i = 0; !bad && i < n; i++) bad = O[i] < 0 || O[i] >= nz;
    if (bad) {
        RELEASE(&ob, &zb, &xb, &yb, &qb, &cb);
        PyErr_SetString(PyExc_ValueError, "bins_channels: inconsistent buffers");
        return NULL;
    }
    const double *Z = (const double *)zb.buf, *X = (const double *)xb.buf, *Y = (const double *)yb.buf;
    const float *QC = (const float *)qb.buf;
    float *C = (float *)cb.buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        const int64_t j = O[i];
        const double zr = Z[2 * j], zi = Z[2 * j + 1], kx = X[j], ky = Y[j];
        float *c = C + 8 * i;
        c[0] = (float)zr;
        c[1] = (float)(kx * zi);
        c[2] = (float)(ky * zi);
        c[3] = (float)((-kx * kx) * zr);
        c[4] = (float)((-kx * ky) * zr);
        c[5] = (float)((-ky * ky) * zr);
        c[6] = QC[i];
        c[7] = 0.0f;
    }
    RELEASE(&ob, &zb, &xb, &yb, &qb, &cb);
    Py_RETURN_NONE;
}

/*
 * The isophote analysis of pipeline.blends (paper sec. 3.6), its per-object loops in C. Each keeps its numpy lines in
 * blends.py as the reference; tests check the pairs agree to the bit.
 *
 * iso_coadd(items, ny, nx, coadd, inv, bad): the co-add of _stack_coadd. items holds per exposure (image, weight,
 * index, inside): float64 stamps of ny x nx and a nearest-pixel map onto the co-add's grid (int64 flat index into the
 * stamp, uint8 inside; where not inside, value and weight 0) or two empty buffers (the stamp as it is). A pixel is
 * good where its value and weight are finite and the weight positive; elsewhere both are 0 and bad (uint8,
 * exposures x ny x nx) is 1. inv = 1 / sum w where that is positive, else 0; coadd = (sum w s) inv, each sum over the
 * exposures in order from the first (numpy's reduction over the leading axis), without contraction.
 */
static NO_CONTRACT PyObject *iso_coadd(PyObject *self, PyObject *args)
{
    PyObject *items;
    int ny, nx;
    Py_buffer cb, ib, bb;
    if (!PyArg_ParseTuple(args, "O!iiw*w*w*", &PyTuple_Type, &items, &ny, &nx, &cb, &ib, &bb)) return NULL;
    const Py_ssize_t ne = PyTuple_GET_SIZE(items), n = (Py_ssize_t)ny * nx, D = (Py_ssize_t)sizeof(double);
    int bad = ne < 1 || ny < 1 || nx < 1 || cb.len != n * D || ib.len != n * D || bb.len != ne * n;
    double *C = (double *)cb.buf, *I = (double *)ib.buf;
    unsigned char *B = (unsigned char *)bb.buf;
    for (Py_ssize_t e = 0; e < ne && !bad; e++) {
        Py_buffer x[4];
        PyObject *it = PyTuple_GET_ITEM(items, e);
        if (!PyTuple_Check(it) || !PyArg_ParseTuple(it, "y*y*y*y*", &x[0], &x[1], &x[2], &x[3])) {
            bad = 2;
            break;
        }
        const int mapped = x[2].len != 0;
        bad = x[0].len != n * D || x[1].len != n * D
              || (mapped ? x[2].len != n * (Py_ssize_t)sizeof(long long) || x[3].len != n : x[3].len != 0);
        const double *S = (const double *)x[0].buf, *Wt = (const double *)x[1].buf;
        const long long *M = (const long long *)x[2].buf;
        const unsigned char *In = (const unsigned char *)x[3].buf;
        for (Py_ssize_t p = 0; p < n && mapped && !bad; p++) bad = In[p] && (M[p] < 0 || M[p] >= n);
        for (Py_ssize_t p = 0; p < n && !bad; p++) {
            double s, w;
            if (!mapped) {
                s = S[p];
                w = Wt[p];
            } else if (In[p]) {
                s = S[M[p]];
                w = Wt[M[p]];
            } else {
                s = 0.0;
                w = 0.0;
            }
            const int good = isfinite(s) && isfinite(w) && w > 0;
            if (!good) s = w = 0.0;
            B[e * n + p] = (unsigned char)!good;
            const double ws = w * s;
            if (e == 0) {
                I[p] = w;
                C[p] = ws;
            } else {
                I[p] += w;
                C[p] += ws;
            }
        }
        RELEASE(&x[0], &x[1], &x[2], &x[3]);
    }
    if (bad) {
        RELEASE(&cb, &ib, &bb);
        if (bad == 1 || !PyErr_Occurred()) {
            PyErr_Clear();
            PyErr_SetString(PyExc_ValueError, "iso_coadd: inconsistent buffers");
        }
        return NULL;
    }
    for (Py_ssize_t p = 0; p < n; p++) {
        const double inv = I[p] > 0 ? 1.0 / I[p] : 0.0;
        C[p] = C[p] * inv;
        I[p] = inv;
    }
    RELEASE(&cb, &ib, &bb);
    Py_RETURN_NONE;
}

/* the separable smoothing's passes: out = a correlated with the odd, symmetric kernel k of half-width r along columns
   (iso_cols) or rows (iso_rows), zero beyond the box; per pixel the centre tap, then each pair of equal taps, the
   outermost first, its two pixels added first (scipy.ndimage.correlate1d's order for a symmetric kernel). Whole rows
   at a time, so the loops run across a row. zero: nx zeros; pad: nx + 2 r doubles of scratch */
static NO_CONTRACT void iso_cols(const double *a, double *out, Py_ssize_t ny, Py_ssize_t nx, const double *k,
                                 Py_ssize_t r, const double *zero)
{
    for (Py_ssize_t y = 0; y < ny; y++) {
        double *o = out + y * nx;
        const double *x = a + y * nx;
        for (Py_ssize_t i = 0; i < nx; i++) o[i] = x[i] * k[r];
        for (Py_ssize_t j = r; j >= 1; j--) {
            const double *lo = y - j >= 0 ? a + (y - j) * nx : zero, *hi = y + j < ny ? a + (y + j) * nx : zero;
            const double kj = k[r + j];
            for (Py_ssize_t i = 0; i < nx; i++) o[i] += (lo[i] + hi[i]) * kj;
        }
    }
}

static NO_CONTRACT void iso_rows(const double *a, double *out, Py_ssize_t ny, Py_ssize_t nx, const double *k,
                                 Py_ssize_t r, double *pad)
{
    for (Py_ssize_t i = 0; i < r; i++) pad[i] = pad[r + nx + i] = 0.0;
    for (Py_ssize_t y = 0; y < ny; y++) {
        double *o = out + y * nx;
        memcpy(pad + r, a + y * nx, (size_t)nx * sizeof(double));
        const double *x = pad + r;
        for (Py_ssize_t i = 0; i < nx; i++) o[i] = x[i] * k[r];
        for (Py_ssize_t j = r; j >= 1; j--) {
            const double kj = k[r + j];
            for (Py_ssize_t i = 0; i < nx; i++) o[i] += (x[i - j] + x[i + j]) * kj;
        }
    }
}

/*
 * iso_smooth(coadd, inv, ny, nx, kern, kern2, smooth, noise, snr): blends._smoothed's arrays (its numpy and scipy
 * lines stay as the reference; a test checks they agree to the bit): smooth = coadd correlated with the outer product
 * of kern (columns, then rows; zero outside the box), noise = sqrt(inv correlated likewise with kern2), snr = smooth /
 * noise where noise > 0, else 0. Both kernels odd-length and symmetric.
 */
static NO_CONTRACT PyObject *iso_smooth(PyObject *self, PyObject *args)
{
    Py_buffer cb, ib, kb, k2b, sb, nb, rb;
    int ny, nx;
    if (!PyArg_ParseTuple(args, "y*y*iiy*y*w*w*w*", &cb, &ib, &ny, &nx, &kb, &k2b, &sb, &nb, &rb)) return NULL;
    const Py_ssize_t D = (Py_ssize_t)sizeof(double), n = (Py_ssize_t)ny * nx, nk = kb.len / D;
    const double *K = (const double *)kb.buf, *K2 = (const double *)k2b.buf;
    int bad = ny < 1 || nx < 1 || cb.len != n * D || ib.len != n * D || sb.len != n * D || nb.len != n * D
              || rb.len != n * D || nk < 1 || nk % 2 != 1 || k2b.len != kb.len;
    for (Py_ssize_t j = 0; !bad && j < nk; j++) bad = K[j] != K[nk - 1 - j] || K2[j] != K2[nk - 1 - j];
    double *tmp = bad ? NULL : (double *)calloc((size_t)(n + 2 * nx + nk), sizeof(double));
    if (bad || tmp == NULL) {
        RELEASE(&cb, &ib, &kb, &k2b, &sb, &nb, &rb);
        if (bad) PyErr_SetString(PyExc_ValueError, "iso_smooth: inconsistent buffers");
        else PyErr_NoMemory();
        return NULL;
    }
    const Py_ssize_t r = nk / 2;
    double *S = (double *)sb.buf, *N = (double *)nb.buf, *Q = (double *)rb.buf;
    double *zero = tmp + n, *pad = zero + nx;   /* (calloc: zero holds nx zeros) */
    iso_cols((const double *)cb.buf, tmp, ny, nx, K, r, zero);   /* axis 0, then axis 1 */
    iso_rows(tmp, S, ny, nx, K, r, pad);
    iso_cols((const double *)ib.buf, tmp, ny, nx, K2, r, zero);
    iso_rows(tmp, N, ny, nx, K2, r, pad);
    for (Py_ssize_t p = 0; p < n; p++) {
        N[p] = sqrt(N[p]);
        Q[p] = N[p] > 0 ? S[p] / N[p] : 0.0;
    }
    free(tmp);
    RELEASE(&cb, &ib, &kb, &k2b, &sb, &nb, &rb);
    Py_RETURN_NONE;
}

/*
 * iso_regions(snr, nx, bad, x0, y0, nsigma, min_peak, core2, grow, comp, region, others, keep)
 *   -> (target, n_real, ya, yb, xa, xb, peak): blends._isophote's decisions in one pass (its numpy and scipy lines stay
 * as the reference; a test checks they agree). The 8-connected components of snr >= nsigma (comp: int32 scratch),
 * each real where its peak reaches min_peak; the target is the real component at the pixel nearest (x0, y0), else
 * the one of the nearest pixel within 2 pixels (the first in raster order among equals), else none (0). With a
 * target: region (uint8) its pixels, keep (uint8, one per exposure of bad: exposures x ny x nx, uint8) 0 where the
 * exposure has a bad pixel in it, its bounding box [ya, yb) x [xa, xb) and peak; others (uint8, where grow >= 0) the
 * other real components' pixels dilated by a square of half-width grow, less the region. Without one: keep judged on
 * the pixels within sqrt(core2) of (x0, y0). n_real: the real components.
 */
static NO_CONTRACT PyObject *iso_regions(PyObject *self, PyObject *args)
{
    Py_buffer sb, bb, cb, rb, ob, kb;
    int nx, grow;
    double x0, y0, nsigma, min_peak, core2;
    if (!PyArg_ParseTuple(args, "y*iy*dddddiw*w*w*w*", &sb, &nx, &bb, &x0, &y0, &nsigma, &min_peak, &core2, &grow,
                          &cb, &rb, &ob, &kb))
        return NULL;
    const Py_ssize_t n = sb.len / (Py_ssize_t)sizeof(double), ny = nx > 0 ? n / nx : 0, ne = kb.len;
    if (nx < 1 || ny * nx != n || n < 1 || ne < 1 || bb.len != ne * n || cb.len != n * (Py_ssize_t)sizeof(int)
        || rb.len != n || ob.len != (grow >= 0 ? n : 0)) {
        RELEASE(&sb, &bb, &cb, &rb, &ob, &kb);
        PyErr_SetString(PyExc_ValueError, "iso_regions: inconsistent buffers");
        return NULL;
    }
    const double *S = (const double *)sb.buf;
    const unsigned char *Bd = (const unsigned char *)bb.buf;
    int *comp = (int *)cb.buf;
    unsigned char *R = (unsigned char *)rb.buf, *O = (unsigned char *)ob.buf, *K = (unsigned char *)kb.buf;
    Py_ssize_t *stack = (Py_ssize_t *)malloc((size_t)n * sizeof(Py_ssize_t));
    unsigned char *real = (unsigned char *)malloc((size_t)n + 1);
    if (!stack || !real) {
        free(stack);
        free(real);
        RELEASE(&sb, &bb, &cb, &rb, &ob, &kb);
        return PyErr_NoMemory();
    }
    /* components, in raster order of their first pixel, and their peaks */
    for (Py_ssize_t p = 0; p < n; p++) comp[p] = 0;
    int nc = 0, n_real = 0;
    real[0] = 0;
    for (Py_ssize_t p = 0; p < n; p++) {
        if (comp[p] || !(S[p] >= nsigma)) continue;
        const int l = ++nc;
        double peak = S[p];
        Py_ssize_t top = 0;
        stack[top++] = p;
        comp[p] = l;
        while (top) {
            const Py_ssize_t q = stack[--top];
            const Py_ssize_t qy = q / nx, qx = q % nx;
            peak = S[q] > peak ? S[q] : peak;
            for (Py_ssize_t y = qy - 1; y <= qy + 1; y++) {
                if (y < 0 || y >= ny) continue;
                for (Py_ssize_t x = qx - 1; x <= qx + 1; x++) {
                    const Py_ssize_t r = y * nx + x;
                    if (x < 0 || x >= nx || comp[r] || !(S[r] >= nsigma)) continue;
                    comp[r] = l;
                    stack[top++] = r;
                }
            }
        }
        real[l] = peak >= min_peak;
        n_real += real[l];
    }
    /* the target (blends._find_target) */
    int target = 0;
    const long long ix = (long long)floor(x0 + 0.5), iy = (long long)floor(y0 + 0.5);
    if (iy >= 0 && iy < ny && ix >= 0 && ix < nx && real[comp[iy * nx + ix]]) {
        target = comp[iy * nx + ix];
    } else {
        const long long ya = iy - 3 > 0 ? iy - 3 : 0, yb = iy + 4 < ny ? iy + 4 : ny;
        const long long xa = ix - 3 > 0 ? ix - 3 : 0, xb = ix + 4 < nx ? ix + 4 : nx;
        double best = INFINITY;
        for (long long y = ya; y < yb; y++)
            for (long long x = xa; x < xb; x++) {
                const double dx = (double)x - x0, dy = (double)y - y0;
                const double a = dx * dx, b = dy * dy, d2 = a + b;
                const int l = comp[y * nx + x];
                if (real[l] && d2 <= 4.0 && d2 < best) {
                    best = d2;
                    target = l;
                }
            }
    }
    for (Py_ssize_t e = 0; e < ne; e++) K[e] = 1;
    long long ya = ny, yb = 0, xa = nx, xb = 0;
    double peak = -INFINITY;
    if (target == 0) {
        /* the pixels within sqrt(core2) of the position */
        for (Py_ssize_t y = 0; y < ny; y++)
            for (Py_ssize_t x = 0; x < nx; x++) {
                const double dx = (double)x - x0, dy = (double)y - y0;
                const double a = dx * dx, b = dy * dy;
                R[y * nx + x] = 0;
                if (a + b <= core2)
                    for (Py_ssize_t e = 0; e < ne; e++)
                        if (Bd[e * n + y * nx + x]) K[e] = 0;
            }
        if (grow >= 0) memset(O, 0, (size_t)n);
    } else {
        for (Py_ssize_t y = 0; y < ny; y++)
            for (Py_ssize_t x = 0; x < nx; x++) {
                const Py_ssize_t p = y * nx + x;
                R[p] = comp[p] == target;
                if (!R[p]) continue;
                ya = y < ya ? y : ya;
                yb = y + 1 > yb ? y + 1 : yb;
                xa = x < xa ? x : xa;
                xb = x + 1 > xb ? x + 1 : xb;
                peak = S[p] > peak ? S[p] : peak;
                for (Py_ssize_t e = 0; e < ne; e++)
                    if (Bd[e * n + p]) K[e] = 0;
            }
        if (grow >= 0) {
            /* the other real components, dilated: a pixel is masked where one lies within grow in x and y */
            for (Py_ssize_t p = 0; p < n; p++) O[p] = 0;
            for (Py_ssize_t y = 0; y < ny; y++)
                for (Py_ssize_t x = 0; x < nx; x++) {
                    const int l = comp[y * nx + x];
                    if (l == 0 || l == target || !real[l]) continue;
                    for (Py_ssize_t v = y - grow; v <= y + grow; v++) {
                        if (v < 0 || v >= ny) continue;
                        for (Py_ssize_t u = x - grow; u <= x + grow; u++)
                            if (u >= 0 && u < nx) O[v * nx + u] = 1;
                    }
                }
            for (Py_ssize_t p = 0; p < n; p++) O[p] &= !R[p];
        }
    }
    free(stack);
    free(real);
    RELEASE(&sb, &bb, &cb, &rb, &ob, &kb);
    return Py_BuildValue("iiLLLLd", target, n_real, ya, yb, xa, xb, peak);
}

/* the eight neighbours of a pixel of a row of w pixels, flat, in blends._SHIFTS' order */
static void iso_steps(Py_ssize_t w, Py_ssize_t *st)
{
    int k = 0;
    for (int dy = -1; dy <= 1; dy++)
        for (int dx = -1; dx <= 1; dx++)
            if (dy || dx) st[k++] = dy * w + dx;
}

/* the region's pixels are at least one pixel inside the box (the caller pads), so every neighbour is in it */
static int iso_inside(const unsigned char *R, Py_ssize_t h, Py_ssize_t w)
{
    for (Py_ssize_t y = 0; y < h; y++)
        for (Py_ssize_t x = 0; x < w; x++)
            if (R[y * w + x] && (y == 0 || x == 0 || y == h - 1 || x == w - 1)) return 0;
    return 1;
}

/* pixels by value, highest first, ties by position (a stable argsort of -v) */
typedef struct {
    double v;
    Py_ssize_t p;
} iso_key;
static int iso_cmp(const void *a, const void *b)
{
    const iso_key *x = (const iso_key *)a, *y = (const iso_key *)b;
    if (x->v > y->v) return -1;
    if (x->v < y->v) return 1;
    return (x->p > y->p) - (x->p < y->p);
}

/* sort the m pixels of idx so (keys: m of scratch) */
static void iso_sort(const double *V, Py_ssize_t *idx, Py_ssize_t m, iso_key *keys)
{
    for (Py_ssize_t i = 0; i < m; i++) {
        keys[i].v = V[idx[i]];
        keys[i].p = idx[i];
    }
    qsort(keys, (size_t)m, sizeof(iso_key), iso_cmp);
    for (Py_ssize_t i = 0; i < m; i++) idx[i] = keys[i].p;
}

static int pos_cmp(const void *a, const void *b)
{
    const Py_ssize_t i = *(const Py_ssize_t *)a, j = *(const Py_ssize_t *)b;
    return (i > j) - (i < j);
}

/*
 * sig_maxima(v, region, w, nsigma, min_contrast, strong) -> count: blends._significant_maxima. v (float64, -inf off
 * the region) and region (uint8) of a box w pixels wide whose border holds no region pixel; strong (uint8, zeroed
 * here) marks one pixel (the first in raster order) of each significant maximum. A local maximum equals the highest of
 * its 3 x 3 neighbourhood; touching maxima form one plateau; plateaus rank by height, then position; the highest is
 * significant, and a lower one at height h >= nsigma + c when no higher-ranked one is reached from it through region
 * pixels of v >= h - c.
 */
static NO_CONTRACT PyObject *sig_maxima(PyObject *self, PyObject *args)
{
    Py_buffer vb, rb, ob;
    int w;
    double nsigma, c;
    if (!PyArg_ParseTuple(args, "y*y*iddw*", &vb, &rb, &w, &nsigma, &c, &ob)) return NULL;
    const Py_ssize_t n = rb.len, h = w > 0 ? n / w : 0;
    const double *V = (const double *)vb.buf;
    const unsigned char *R = (const unsigned char *)rb.buf;
    unsigned char *O = (unsigned char *)ob.buf;
    if (w < 1 || h * w != n || vb.len != n * (Py_ssize_t)sizeof(double) || ob.len != n || !iso_inside(R, h, w)) {
        RELEASE(&vb, &rb, &ob);
        PyErr_SetString(PyExc_ValueError, "sig_maxima: inconsistent buffers");
        return NULL;
    }
    /* one block: sort keys, representatives, a stack, marks, ranks, the maxima (widest items first) */
    const size_t m = (size_t)n + 1;
    iso_key *keys = (iso_key *)malloc(m * (sizeof(iso_key) + 2 * sizeof(Py_ssize_t) + 2 * sizeof(int) + 1));
    if (keys == NULL) {
        RELEASE(&vb, &rb, &ob);
        return PyErr_NoMemory();
    }
    Py_ssize_t *reps = (Py_ssize_t *)(keys + m), *stack = reps + m;
    int *mark = (int *)(stack + m), *rank = mark + m;
    unsigned char *ismax = (unsigned char *)(rank + m);
    memset(ismax, 0, m);
    Py_ssize_t st[8];
    iso_steps(w, st);
    memset(O, 0, (size_t)n);
    for (Py_ssize_t p = 0; p < n; p++) {
        mark[p] = 0;
        rank[p] = -1;
        if (!R[p]) continue;
        double m = V[p];
        for (int k = 0; k < 8; k++) m = V[p + st[k]] > m ? V[p + st[k]] : m;
        ismax[p] = V[p] == m;
    }
    /* plateaus: one representative each, its first pixel in raster order */
    Py_ssize_t nrep = 0;
    for (Py_ssize_t p = 0; p < n; p++) {
        if (!ismax[p] || mark[p]) continue;
        reps[nrep++] = p;
        Py_ssize_t top = 0;
        stack[top++] = p;
        mark[p] = -1;
        while (top) {
            const Py_ssize_t q = stack[--top];
            for (int k = 0; k < 8; k++) {
                const Py_ssize_t r = q + st[k];
                if (ismax[r] && !mark[r]) {
                    mark[r] = -1;
                    stack[top++] = r;
                }
            }
        }
    }
    int count = 0;
    if (nrep) {
        iso_sort(V, reps, nrep, keys);
        for (Py_ssize_t k = 0; k < nrep; k++) rank[reps[k]] = (int)k;
        O[reps[0]] = 1;
        count = 1;
        const double floor_ = nsigma + c;
        for (Py_ssize_t k = 1; k < nrep && V[reps[k]] >= floor_; k++) {
            /* the component of region & (v >= h - c) holding this maximum: a higher-ranked one in it? */
            const double lo = V[reps[k]] - c;
            const int tag = (int)k + 1;
            int found = 0;
            Py_ssize_t top = 0;
            stack[top++] = reps[k];
            mark[reps[k]] = tag;
            while (top && !found) {
                const Py_ssize_t q = stack[--top];
                for (int j = 0; j < 8; j++) {
                    const Py_ssize_t r = q + st[j];
                    if (R[r] && mark[r] != tag && V[r] >= lo) {
                        if (rank[r] >= 0 && rank[r] < k) {
                            found = 1;
                            break;
                        }
                        mark[r] = tag;
                        stack[top++] = r;
                    }
                }
            }
            if (!found) {
                O[reps[k]] = 1;
                count++;
            }
        }
    }
    free(keys);
    RELEASE(&vb, &rb, &ob);
    return PyLong_FromLong(count);
}

/*
 * deblend_grow(v, region, w, levels, min_pixels, strong, lab) -> regions: the rest of blends._deblend once more than
 * one maximum is significant. The region's pixels, highest first (ties by position), enter level by level (the
 * pixels of v >= each level in turn, the last level all of them); the new pixels of a level go, a pass at a time, to
 * their brightest labelled neighbour (the first in blends._SHIFTS' order among equals), all of a pass judged on the
 * labels before it; those no region reaches become regions of their own, one per 8-connected group, numbered in
 * raster order. Then regions whose peak is not significant or that have fewer than min_pixels pixels are merged,
 * smallest first (the lowest number among equals), into the region holding most of the pixels around them. lab
 * (int32, the box) receives the labels; returns the regions left.
 */
static PyObject *deblend_grow(PyObject *self, PyObject *args)
{
    Py_buffer vb, rb, lvb, sb, lb;
    int w, min_pixels;
    if (!PyArg_ParseTuple(args, "y*y*iy*iy*w*", &vb, &rb, &w, &lvb, &min_pixels, &sb, &lb)) return NULL;
    const Py_ssize_t n = rb.len, h = w > 0 ? n / w : 0, nl = lvb.len / (Py_ssize_t)sizeof(double);
    const double *V = (const double *)vb.buf, *L = (const double *)lvb.buf;
    const unsigned char *R = (const unsigned char *)rb.buf, *S = (const unsigned char *)sb.buf;
    int *lab = (int *)lb.buf;
    if (w < 1 || h * w != n || vb.len != n * (Py_ssize_t)sizeof(double) || nl < 1 || sb.len != n
        || lb.len != n * (Py_ssize_t)sizeof(int) || !iso_inside(R, h, w)) {
        RELEASE(&vb, &rb, &lvb, &sb, &lb);
        PyErr_SetString(PyExc_ValueError, "deblend_grow: inconsistent buffers");
        return NULL;
    }
    /* one block: sort keys; the pixels in order, to do, a stack, their labels got; counts and contacts per label;
       the seeds and the significant labels (zeroed) */
    const size_t m = (size_t)n + 2;
    iso_key *keys = (iso_key *)malloc(m * (sizeof(iso_key) + 6 * sizeof(Py_ssize_t) + 2));
    if (keys == NULL) {
        RELEASE(&vb, &rb, &lvb, &sb, &lb);
        return PyErr_NoMemory();
    }
    Py_ssize_t *order = (Py_ssize_t *)(keys + m), *todo = order + m, *stack = todo + m, *got = stack + m;
    Py_ssize_t *cnt = got + m, *touch = cnt + m;
    unsigned char *seed = (unsigned char *)(touch + m), *sig = seed + m;
    memset(seed, 0, 2 * m);
    Py_ssize_t st[8];
    iso_steps(w, st);
    Py_ssize_t no = 0;
    for (Py_ssize_t p = 0; p < n; p++) {
        lab[p] = 0;
        if (R[p]) order[no++] = p;
    }
    iso_sort(V, order, no, keys);
    int n_reg = 0;
    Py_ssize_t start = 0;
    for (Py_ssize_t i = 0; i < nl; i++) {
        /* the pixels of v >= this level (np.searchsorted on -v, side='right'); the last level takes them all */
        Py_ssize_t end = no;
        if (i < nl - 1) {
            Py_ssize_t a = 0, b = no;
            while (a < b) {
                const Py_ssize_t m = a + (b - a) / 2;
                if (-V[order[m]] <= -L[i]) a = m + 1;
                else b = m;
            }
            end = a;
        }
        if (end <= start) continue;
        Py_ssize_t nt = end - start;
        memcpy(todo, order + start, (size_t)nt * sizeof(Py_ssize_t));
        start = end;
        while (nt) {
            int any = 0;
            for (Py_ssize_t t = 0; t < nt; t++) {
                const Py_ssize_t p = todo[t];
                double best = -INFINITY;
                int g = 0;
                for (int k = 0; k < 8; k++) {
                    const int l = lab[p + st[k]];
                    const double nv = l > 0 ? V[p + st[k]] : -INFINITY;
                    if (k == 0 || nv > best) {
                        best = nv;
                        g = l;
                    }
                }
                got[t] = g;
                any |= g > 0;
            }
            if (!any) break;
            Py_ssize_t keep = 0;
            for (Py_ssize_t t = 0; t < nt; t++) {
                if (got[t] > 0) lab[todo[t]] = (int)got[t];
                else todo[keep++] = todo[t];
            }
            nt = keep;
        }
        if (nt) {
            /* the unreached: a region per 8-connected group, numbered in raster order */
            for (Py_ssize_t t = 0; t < nt; t++) seed[todo[t]] = 1;
            qsort(todo, (size_t)nt, sizeof(Py_ssize_t), pos_cmp);
            for (Py_ssize_t t = 0; t < nt; t++) {
                if (lab[todo[t]]) continue;
                const int l = ++n_reg;
                Py_ssize_t top = 0;
                stack[top++] = todo[t];
                lab[todo[t]] = l;
                while (top) {
                    const Py_ssize_t q = stack[--top];
                    for (int k = 0; k < 8; k++) {
                        const Py_ssize_t r = q + st[k];
                        if (seed[r] && !lab[r]) {
                            lab[r] = l;
                            stack[top++] = r;
                        }
                    }
                }
            }
            for (Py_ssize_t t = 0; t < nt; t++) seed[todo[t]] = 0;
        }
    }
    /* amalgamate the regions that do not count */
    for (Py_ssize_t p = 0; p < n; p++)
        if (S[p] && lab[p] > 0) sig[lab[p]] = 1;
    while (n_reg > 1) {
        memset(cnt, 0, (size_t)(n_reg + 1) * sizeof(Py_ssize_t));
        for (Py_ssize_t p = 0; p < n; p++) cnt[lab[p]]++;
        int alive = 0, r = 0;
        for (int l = 1; l <= n_reg; l++) {
            if (cnt[l] <= 0) continue;
            alive++;
            if ((cnt[l] < min_pixels || !sig[l]) && (r == 0 || cnt[l] < cnt[r])) r = l;
        }
        if (alive <= 1 || r == 0) break;
        memset(touch, 0, (size_t)(n_reg + 1) * sizeof(Py_ssize_t));
        Py_ssize_t total = 0;
        for (Py_ssize_t p = 0; p < n; p++) {
            if (lab[p] <= 0 || lab[p] == r) continue;
            for (int k = 0; k < 8; k++)
                if (lab[p + st[k]] == r) {
                    touch[lab[p]]++;
                    total++;
                    break;
                }
        }
        if (total == 0) break;
        int to = 0;
        for (int l = 1; l <= n_reg; l++)
            if (touch[l] > touch[to]) to = l;
        for (Py_ssize_t p = 0; p < n; p++)
            if (lab[p] == r) lab[p] = to;
    }
    int n_final = 0;
    memset(cnt, 0, (size_t)(n_reg + 1) * sizeof(Py_ssize_t));
    for (Py_ssize_t p = 0; p < n; p++)
        if (lab[p] > 0 && !cnt[lab[p]]++) n_final++;
    free(keys);
    RELEASE(&vb, &rb, &lvb, &sb, &lb);
    return PyLong_FromLong(n_final);
}

static PyMethodDef methods[] = {
    {"kernel_isa", kernel_isa, METH_NOARGS, "kernel_isa() -> the instruction-set level this module was built for"},
    {"cpu_levels", cpu_levels, METH_NOARGS, "cpu_levels() -> the instruction-set levels this CPU runs"},
    {"build_info", build_info, METH_NOARGS, "build_info() -> {'compiler': ..., 'level': ...}"},
    {"model_sums", model_sums, METH_VARARGS,
     "model_sums(coef, modes, table, c, inv_du, ratio2, n_single, group_sizes, group_ranks, group_factors, out)"},
    {"set_special", set_special, METH_VARARGS, "set_special(erfcx_capsule, expi_capsule)"},
    {"marginal", marginal, METH_VARARGS, "marginal(sums, u, u_fine, spline, interp, params, out)"},
    {"size_marginal", size_marginal, METH_VARARGS,
     "size_marginal(ld, lb, fd, fb, bd, logprior, lsegprior, spline, interp, xf, u, rf, l0, logmix, out)"},
    {"make_bins", make_bins, METH_VARARGS,
     "make_bins(shape, basis32, channels32, bins_per_octave[, versions[, (u0, n_u, grid, dc, rows, direct, npsi, "
     "q2min) or None[, out]]]) "
     "-> (lo, offsets, columns, dc)"},
    {"polar_grid", polar_grid, METH_VARARGS,
     "polar_grid(basis32, channels32, bins_per_octave, npsi[, versions[, node_modes]]) -> (u0, n_u, grid, dc, rows, "
     "direct)"},
    {"size_nodes", size_nodes, METH_VARARGS,
     "size_nodes(bins, marg, e_index, rc, expx, x0, xf, interp, spline, u, half_log_u, l0, logmix, prior, shift, out, "
     "best)"},
    {"size_nodes_versions", size_nodes_versions, METH_VARARGS,
     "size_nodes_versions(bins, marg, e_index, nv, rc, expx, x0, xf, interp, spline, u, half_log_u, l0, logmix, "
     "prior, shift, out, best): size_nodes of nv versions binned together, their quadratic sums made once"},
    {"locate_pass", locate_pass, METH_VARARGS,
     "locate_pass(bins, marg, e_index, rc, expx, xs, prior, shift, w, detail, r_peak, top, point)"},
    {"sample_chunk", sample_chunk, METH_VARARGS, "sample_chunk(args, e1, e2, rc, shift, out, rc_out, state) -> int"},
    {"moffat_start", moffat_start, METH_VARARGS, "moffat_start(kr, vr, nus, x50, ratio, out)"},
    {"masked_stamp", masked_stamp, METH_VARARGS, "masked_stamp(image, weight, y) -> (count, lo, hi, sumsq)"},
    {"padded_rows", padded_rows, METH_VARARGS, "padded_rows(a, b, h, w, n, rows)"},
    {"padded_place", padded_place, METH_VARARGS, "padded_place(part, h, n, out)"},
    {"metacal_noise", metacal_noise, METH_VARARGS,
     "metacal_noise(weight, image, noise, ny, nx, edge, grow, y, mask) -> var_in"},
    {"metacal_weight", metacal_weight, METH_VARARGS, "metacal_weight(noise0, mask, weight, var_in, out) -> scale"},
    {"banded_rows", banded_rows, METH_VARARGS, "banded_rows(values, start, x, out): a banded matrix times x"},
    {"shift_phase", shift_phase, METH_VARARGS, "shift_phase(kx, ky, du, dv, out)"},
    {"nearest_map", nearest_map, METH_VARARGS, "nearest_map(a, ny, nx, index, inside)"},
    {"sky_modes", sky_modes, METH_VARARGS, "sky_modes(kx, ky, T, m, flux_scale, Kx, Ky, Ts)"},
    {"complex_bincount", complex_bincount, METH_VARARGS,
     "complex_bincount(index, values, out) -> whether every index lay within out"},
    {"join_gather", join_gather, METH_VARARGS, "join_gather(items, keep) -> (kx, ky, zf, tscaled, group, data, goffset)"},
    {"join_distinct", join_distinct, METH_VARARGS, "join_distinct(kx, ky, order, zdat, group, goffset) -> (first, inv, z, grow)"},
    {"adaptive_samples", adaptive_samples_c, METH_VARARGS,
     "adaptive_samples(args, prior_disk, prior_bulge, growth, shift, ints, params, state) -> (samples, n, need)"},
    {"coarse_modes", coarse_modes, METH_VARARGS,
     "coarse_modes(kx, ky, transfer, coarse, keep, data_ft, xp, fp, index, base, shift, r2, out)"},
    {"mode_bound", mode_bound, METH_VARARGS, "mode_bound(transfer, coarse, cweight, data_ft, norm, p) -> (h, ff)"},
    {"drop_threshold", drop_threshold, METH_VARARGS, "drop_threshold(b, tolerance) -> t or None"},
    {"alias_sums_mirror", alias_sums_mirror, METH_VARARGS,
     "alias_sums_mirror(table, i0, w0, w1, kept, A, Gs, G2max, ny, nxh, side)"},
    {"bins_geometry", bins_geometry, METH_VARARGS,
     "bins_geometry(multi, basis, q, indptr, indices, data, order, b3, qcol) -> (gsel, pa, pb, ph)"},
    {"bins_channels", bins_channels, METH_VARARGS, "bins_channels(order, z, kx, ky, qcol, c8)"},
    {"fold_groups", fold_groups, METH_VARARGS, "fold_groups(row, col, t, n, q) -> None or (multi, msizes, data, indices, indptr)"},
    {"coarse_gather", coarse_gather, METH_VARARGS, "coarse_gather(h, nx, sigma2, jinv, grid, total)"},
    {"table_interp", table_interp, METH_VARARGS,
     "table_interp(x, xp, fp, index, base, shift, right, out): np.interp(x, xp, fp, right=right), bucketed search"},
    {"find_peak", find_peak, METH_VARARGS,
     "find_peak(kx, ky, zr, x0, y0, cell, n_newton) -> (x, y, status): the cross-correlation peak's Newton steps"},
    {"binned_sums", binned_sums, METH_VARARGS,
     "binned_sums(shape, r2, e_index, lo, offsets, columns, dc, bins_per_octave, log_f, log_g, M, J, start, "
     "per_octave, low_f, low_g, zero_f, zero_g, ratio2, pair_basis, pair_a, pair_b, pair_h, out)"},
    {"quintic_kvalues", quintic_kvalues, METH_VARARGS, "quintic_kvalues(table, n, ntab, tx, ty, out)"},
    {"quintic_band", quintic_band, METH_VARARGS,
     "quintic_band(table, n, r, dk, A, JT, to_table, lim, gamma, step, phase, out): metacal versions' bands"},
    {"quintic_band_os", quintic_band_os, METH_VARARGS,
     "quintic_band_os(stamp, ns, psf, np, k, r, dk, A, JT, lim, gamma, xtab, xh, phase, out): an oversampled PSF's"},
    {"quintic_band_rows", quintic_band_rows, METH_VARARGS,
     "quintic_band_rows(stamp, ns, psf_rows, psf, np, k, r, dk, A, JT, lim, gamma, xtab, xh, step, phase, out): "
     "quintic_band_os for a PSF grid k times the stamp's, from the tables' rows, for one or more versions"},
    {"band_rings", band_rings, METH_VARARGS,
     "band_rings(column, xx2, labels, thr, out, near) -> the points left to numpy's test; out: those above, per ring"},
    {"hermite_log_table", hermite_log_table, METH_VARARGS, "hermite_log_table(k0, dk, nodes, lv, slope, curvature, out)"},
    {"set_bessel", set_bessel, METH_VARARGS, "set_bessel(kv_capsule, gamma_capsule)"},
    {"moffat_lm", moffat_lm, METH_VARARGS, "moffat_lm(kr, VR, P, free0, free1, max_iter, ftol, xtol)"},
    {"moffat_table", moffat_table, METH_VARARGS, "moffat_table(k, rs, beta, x_exact, h0, grow, floor, out) -> nodes used"},
    {"alias_sums", alias_sums, METH_VARARGS, "alias_sums(table, i0, w0, w1, kept, A, Gs[, G2max])"},
    {"locate_parabola", locate_parabola, METH_VARARGS, "locate_parabola(ld, lb, lpr, w, xs, top, xpk)"},
    {"fine_modes_select", fine_modes_select, METH_VARARGS,
     "fine_modes_select(Ps, A, ok, absG, Gs, absG2max, kyv, kxv, dx, dy, s, ny, nxh, tolerance, ky, kx, T, c) -> m"},
    {"iso_coadd", iso_coadd, METH_VARARGS, "iso_coadd(items, ny, nx, coadd, inv, bad): the isophote analysis' co-add"},
    {"iso_smooth", iso_smooth, METH_VARARGS,
     "iso_smooth(coadd, inv, ny, nx, kern, kern2, smooth, noise, snr): the isophote analysis' smoothing"},
    {"iso_regions", iso_regions, METH_VARARGS,
     "iso_regions(snr, nx, bad, x0, y0, nsigma, min_peak, core2, grow, comp, region, others, keep) -> (target, "
     "n_real, ya, yb, xa, xb, peak)"},
    {"sig_maxima", sig_maxima, METH_VARARGS, "sig_maxima(v, region, w, nsigma, min_contrast, strong) -> count"},
    {"deblend_grow", deblend_grow, METH_VARARGS, "deblend_grow(v, region, w, levels, min_pixels, strong, lab) -> regions"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, K_STR(KERNEL_MODULE),
                                    "Compiled inner loop of the shearfit likelihood.", -1, methods};

PyMODINIT_FUNC K_CAT(PyInit_, KERNEL_MODULE)(void) { return PyModule_Create(&module); }
