"""The circular Moffat profile in Fourier space and its fit to a native PSF's transform.

A native-sampled PSF carries no information above the Nyquist frequency; the
paper (App. A) stands a circular Moffat in for the PSF there, fitted to the
PSF's transform inside the band. This module holds the Moffat's transform and
that fit; the alias correction that uses them is in :mod:`.model`.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import special

from .kernel import KERNEL, USE_KERNEL, special_capsules

__all__ = ["moffat_norm", "moffat_ft_x", "moffat_ft", "moffat_ft_dlogs", "fit_moffat", "fit_moffats"]


def moffat_norm(nu):
    """c(nu) = 2^(1 - nu) / Gamma(nu), the normalisation of the Moffat's transform c x^nu K_nu(x)."""
    return 2.0 ** (1.0 - nu) / special.gamma(nu)


def moffat_ft_x(x, nu):
    """The unit-flux circular Moffat's transform c x^nu K_nu(x) at x = k rs > 0, nu = beta - 1."""
    return moffat_norm(nu) * x ** nu * special.kv(nu, x)


def moffat_ft(k, rs, beta):
    """Transform of a unit-flux circular Moffat (1+(r/rs)^2)^-beta at |k| (beta > 1)."""
    nu = beta - 1.0
    x = np.asarray(k, dtype=float) * rs
    out = np.ones_like(x)
    pos = x > 1e-8
    out[pos] = moffat_ft_x(x[pos], nu)
    return out


def moffat_ft_dlogs(x, nu):
    """The circular Moffat's transform f(x) = c x^nu K_nu(x), x = k rs > 0, and its derivatives in log rs
    and log nu.

    ``df/dlog rs = x f'(x) = -c x^(nu+1) K_(nu-1)(x)`` (the Bessel recurrence);
    the derivative in ``log nu`` by a forward difference.
    """
    h = 1e-7
    f0 = moffat_ft_x(x, nu)
    d_rs = -moffat_norm(nu) * x ** (nu + 1.0) * special.kv(nu - 1.0, x)
    d_nu = (moffat_ft_x(x, nu * np.exp(h)) - f0) / h
    return f0, d_rs, d_nu


def fit_moffat(psf_ft_coarse, ky, kx, max_iter=100, ftol=1e-10, xtol=1e-8):
    """Fit a circular Moffat (times the pixel response) to a native PSF's transform.

    Only modes well inside the band (|k| < 0.7 pi) enter, where aliasing is
    negligible, so the fitted profile can stand for the PSF above Nyquist. The
    paper fits a circular Moffat near the field centre (App. A); here one is
    fitted per exposure (the pipeline: per CCD).

    The transform is averaged in 14 rings and fitted in (log rs, log(beta-1))
    by Levenberg-Marquardt with the size derivative in closed form; the
    solution is clipped to rs in [0.05, 50] pixels and beta in [1.2, 21].

    Returns (rs, beta) in pixels.
    """
    return fit_moffats([psf_ft_coarse], ky, kx, max_iter, ftol, xtol)[0]


def fit_moffats(psf_fts, ky, kx, max_iter=100, ftol=1e-10, xtol=1e-8):
    """:func:`fit_moffat` of several PSFs' transforms on one grid, as one batch (the Levenberg-Marquardt
    iterations of all of them in the same array operations: an object's exposures' PSFs cost little more than
    one). Every fit is the same, number for number, whatever the batch it is in. Returns [(rs, beta), ...]."""
    sel, pix_sel, idx, nb, count, used, kr = _rings(np.asarray(ky, float), np.asarray(kx, float))
    nf = len(psf_fts)
    # every PSF's ring sums in one bincount (PSF f's rings at f nb + ring): each ring summed in the same order
    # as one PSF at a time
    vals = np.abs(np.asarray(psf_fts).reshape(nf, -1)[:, sel]) / pix_sel
    sums = np.bincount((idx[None, :] + nb * np.arange(nf)[:, None]).ravel(), weights=vals.ravel(),
                       minlength=nf * nb).reshape(nf, nb)
    VR = (sums[:, 1:] / np.maximum(count, 1))[:, used]
    P = _levenberg_marquardt(kr, VR, _starts(kr, VR), (True, True), max_iter, ftol, xtol)
    out = []
    for vr, p in zip(VR, P.tolist()):
        # (np.clip's numbers in Python floats: min(max(x, lo), hi) keeps a NaN x as np.clip does)
        lb = min(max(p[1], _LOG_NU_MIN), _LOG_NU_MAX)
        if lb != p[1]:
            # beta at a bound (a PSF without Moffat wings, e.g. a Gaussian: beta -> infinity): the size refitted
            # for the bound, so that the pair still matches the PSF's width
            p = _levenberg_marquardt(kr, vr[None], np.array([[p[0], lb]]), (True, False), max_iter, ftol,
                                     xtol)[0].tolist()
        lrs = min(max(p[0], _LOG_RS_MIN), _LOG_RS_MAX)
        out.append((float(np.exp(lrs)), float(1.0 + np.exp(lb))))
    return out


#: the bounds of the fitted log(beta - 1) and log rs (pixels), as np.log makes them
_LOG_NU_MIN, _LOG_NU_MAX = float(np.log(0.2)), float(np.log(20.0))
_LOG_RS_MIN, _LOG_RS_MAX = float(np.log(0.05)), float(np.log(50.0))


def _rings(ky, kx):
    """The rings of :func:`fit_moffats` on a grid of wavevectors ky, kx (remembered per grid): the modes used
    (a mask over the flattened grid), their pixel response, ring (np.digitize's index) and the number of
    indices, each ring's count of modes and whether it has any, and the used rings' mean |k|."""
    return _rings_of(ky.tobytes(), kx.tobytes())


@functools.lru_cache(maxsize=16)
def _rings_of(ky_bytes, kx_bytes):
    ky, kx = np.frombuffer(ky_bytes), np.frombuffer(kx_bytes)
    kk = np.hypot(ky[:, None], kx[None, :])
    pix = np.sinc(ky[:, None] / (2 * np.pi)) * np.sinc(kx[None, :] / (2 * np.pi))
    sel = (kk > 0) & (kk < 0.7 * np.pi)
    # azimuthal average in narrow rings keeps the fit cheap and makes it circular
    edges = np.linspace(0, 0.7 * np.pi, 15)
    ks = kk[sel]
    idx = np.digitize(ks, edges)
    count = np.bincount(idx, minlength=edges.size)[1:]
    used = count > 0
    kr = (np.bincount(idx, weights=ks, minlength=edges.size)[1:] / np.maximum(count, 1))[used]
    got = (sel.ravel(), pix[sel], idx, edges.size, count, used, kr)
    for a in got:
        if isinstance(a, np.ndarray):
            a.setflags(write=False)
    return got


@functools.lru_cache(maxsize=1)
def _start_table():
    """Where the Moffat's transform falls to 0.5 and to 0.15, x50 and x15 in x = k rs, against nu = beta - 1
    (0.2 to 20): their ratio falls monotonically with nu (from 5.2 to 1.7), so the ratio of the two
    wavenumbers where a PSF's transform falls to those levels gives nu, and k50 then rs."""
    nus = np.geomspace(0.2, 20.0, 48)
    x = np.geomspace(1e-3, 80.0, 4000)
    x50, x15 = [], []
    for nu in nus:
        f = moffat_ft_x(x, nu)[::-1]
        x50.append(np.interp(0.5, f, x[::-1]))
        x15.append(np.interp(0.15, f, x[::-1]))
    x50, x15 = np.array(x50), np.array(x15)
    return nus, x50, x15 / x50


def _start(kr, vr):
    """The LM's starting (log rs, log nu): from the wavenumbers where the ring averages fall to 0.5 and 0.15
    (:func:`_start_table`), which puts it within a few steps of the fit; where they do not fall that far
    within the band, from the half-power wavenumber of a Gaussian of similar width, with nu = 2."""
    v = np.minimum.accumulate(vr)                 # falling, for the crossings
    if v.size >= 3 and v[0] > 0.5 and v[-1] < 0.15 and np.all(np.isfinite(v)):
        k50 = float(np.interp(0.5, v[::-1], kr[::-1]))
        k15 = float(np.interp(0.15, v[::-1], kr[::-1]))
        nus, x50, ratio = _start_table()
        if k50 > 0 and k15 > k50:
            nu = float(np.interp(k15 / k50, ratio[::-1], nus[::-1]))
            return np.array([np.log(float(np.interp(nu, nus, x50)) / k50), np.log(nu)])
    khalf = kr[np.argmin(np.abs(vr - 0.5))] if np.any(vr < 0.5) else 0.5
    return np.array([np.log(1.2 / khalf), np.log(2.0)])


def _starts(kr, VR, use_kernel=True):
    """:func:`_start` of each row of VR, as rows of an array. The compiled kernel (``moffat_start``) finds what each
    start is the logarithm of, and numpy takes the logarithms: the same numbers as the lines of :func:`_start`
    (a test checks they agree to the bit)."""
    if use_kernel and USE_KERNEL:
        args = np.empty((VR.shape[0], 2))
        nus, x50, ratio = _start_table()
        KERNEL.moffat_start(np.ascontiguousarray(kr, dtype=float), np.ascontiguousarray(VR, dtype=float), nus, x50,
                            ratio, args)
        return np.log(args)
    return np.array([_start(kr, vr) for vr in VR]).reshape(-1, 2)


def _load_bessel():
    """Give the compiled Levenberg-Marquardt scipy.special's kv and gamma (their cython_special C entry points,
    double versions); False where they cannot be found (the numpy lines below are used then)."""
    if KERNEL is None:
        return False
    for c1 in special_capsules("kv"):
        for c2 in special_capsules("gamma"):
            try:
                KERNEL.set_bessel(c1, c2)
                return True
            except ValueError:
                continue
    return False   # pragma: no cover


#: the compiled Moffat fit and table (the kernel's ``moffat_lm``, ``moffat_table``), where scipy's kv and gamma
#: could be handed to them
USE_KERNEL_BESSEL = _load_bessel()


def _levenberg_marquardt(kr, VR, P, free, max_iter, ftol, xtol, use_kernel=True):
    """Least squares of the Moffat transform at kr against each row of VR in p = (log rs, log(beta - 1)) (the
    rows of P, the parameters marked ``free`` varied, the others held), every row its own Levenberg-Marquardt
    (its own damping, steps and stop) in one set of array operations. Returns the fitted P.

    The compiled kernel (``moffat_lm``) runs the same iterations row after row, with scipy's kv and gamma: the
    same fit to rounding (a test checks they agree), without the array operations' overhead per iteration,
    most of these fits' cost where every exposure of every object has its own PSF."""
    free = np.asarray(free)
    P = np.array(P, dtype=float)
    if use_kernel and USE_KERNEL_BESSEL:
        P = np.ascontiguousarray(P.reshape(-1, 2))
        KERNEL.moffat_lm(np.ascontiguousarray(kr, dtype=float), np.ascontiguousarray(VR, dtype=float), P,
                         int(bool(free[0])), int(bool(free[1])), int(max_iter), float(ftol), float(xtol))
        return P
    m = P.shape[0]
    lam = np.full(m, 1e-3)

    def evaluate(Q):
        # a trial step can reach orders where gamma and x^nu overflow: its cost is then not finite and the
        # step is refused
        with np.errstate(over="ignore", invalid="ignore"):
            f0, d_rs, d_nu = moffat_ft_dlogs(kr[None, :] * np.exp(Q[:, :1]), np.exp(Q[:, 1:]))
        r = f0 - VR[rows]
        return r, np.einsum("ij,ij->i", r, r), np.stack([d_rs, d_nu], axis=2)[:, :, free]

    rows = np.arange(m)
    R, cost, J = evaluate(P)
    active = np.ones(m, bool)
    for _ in range(max_iter):
        rows = np.nonzero(active)[0]
        if rows.size == 0:
            break
        Ja, Ra = J[rows], R[rows]
        JtJ = np.einsum("mki,mkj->mij", Ja, Ja)
        g = np.einsum("mki,mk->mi", Ja, Ra)
        d = np.einsum("mii->mi", JtJ)
        A = JtJ + (lam[rows, None] * (d + 1e-30))[:, :, None] * np.eye(d.shape[1])[None]
        try:
            step = -np.linalg.solve(A, g[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            step = _safe_solve(A, g)
        bad = ~np.all(np.isfinite(step), axis=1)
        Q = P[rows].copy()
        Q[:, free] += np.clip(np.where(bad[:, None], 0.0, step), -2.0, 2.0)
        tiny = np.all(np.abs(Q - P[rows]) <= xtol * (np.abs(P[rows]) + xtol), axis=1)
        active[rows[bad | tiny]] = False   # a singular system, or a step shrunk below the tolerance: stop there
        keep = ~(bad | tiny)
        rows, Q = rows[keep], Q[keep]
        if rows.size == 0:
            continue
        Rq, cq, Jq = evaluate(Q)
        accept = np.isfinite(cq) & (cq <= cost[rows])
        converged = accept & ((cost[rows] - cq <= ftol * cost[rows])
                              | np.all(np.abs(Q - P[rows]) <= xtol * (np.abs(P[rows]) + xtol), axis=1))
        ok = rows[accept]
        P[ok], R[ok], cost[ok], J[ok] = Q[accept], Rq[accept], cq[accept], Jq[accept]
        lam[rows] = np.where(accept, np.maximum(lam[rows] / 3.0, 1e-12), lam[rows] * 4.0)
        active[rows[converged | (~accept & (lam[rows] > 1e12))]] = False
    return P


def _safe_solve(A, g):
    """The steps -A^-1 g of a stack of systems one by one, NaN where A is singular (the fit stops there)."""
    out = np.full(g.shape, np.nan)
    for i in range(A.shape[0]):
        try:
            out[i] = np.linalg.solve(A[i], g[i])
        except np.linalg.LinAlgError:
            pass
    return -out
