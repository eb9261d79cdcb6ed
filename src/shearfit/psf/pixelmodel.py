"""Pixel PSF models from stars (sec. 5), native or oversampled.

The model of one exposure is a set of pixel images, one per term of a
polynomial in field position (u, v): every pixel of the PSF is
``sum_t c_t(ccd, u, v) image_t``. The terms are the monomials of order 2
to ``order`` over the whole field of view, plus a constant and the two
linear terms free per CCD (the paper's choice: PSF jumps between CCDs are
taken up by the per-CCD terms). With one CCD it is a plain polynomial.

The fit is done in Fourier space, one stamp frequency at a time. A star
whose centre lies ``delta`` (pixels) from its stamp's centre pixel has, at
stamp frequency j (integer, per axis, over an n-pixel stamp)::

    S(j) = flux * sum_m P(j + n m) exp(-2 pi i (j + n m) . delta / n)

where P is the transform of the pixel-convolved PSF, continuous in j, and
the sum over m runs over the aliases above the Nyquist frequency. With
``oversampling = 1`` only m = 0 is kept: the star is then shifted onto the
pixel grid by the phase, which is the paper's sinc interpolation, and the
fit is one weighted least-squares problem shared by every pixel. With
``oversampling = k`` (odd) the aliases m in [-(k-1)/2, (k-1)/2]^2 are
unknowns too: stars at many sub-pixel phases separate them, and the model
is the PSF sampled every 1/k pixel (beyond the paper, which names this as
the next step in its sec. 5 and App. A). The alias components vary over
the field as a global polynomial of order ``alias_order``. The native
model is fitted first; a circular Moffat fitted to it (as the likelihood's
App. A correction) predicts each alias component, and that prediction is
the mean of a Gaussian prior (width half of itself) weighed against the
stars' residual variance at each frequency: components that the stars'
phases constrain follow the stars, the others fall back on the Moffat
extrapolation instead of on noise.

Stars are centred iteratively by cross-correlation with the current model
(Newton steps on the band-limited cross-correlation), then moved by the
model's own Gaussian-weighted centroid at their position, so that the model
is centred on its centroid and the star offsets are real astrometric
offsets (used for the registration, sec. 4).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import ShearfitValueError

__all__ = ["StarSet", "PixelPSF", "fit_pixel_psf", "monomials", "gaussian_centroid"]


def monomials(order: int, min_degree: int = 0):
    """Exponents (a, b) of u^a v^b with min_degree <= a + b <= order."""
    return [(a, d - a) for d in range(min_degree, order + 1) for a in range(d, -1, -1)]


@dataclass
class StarSet:
    """Stars of one exposure, as stamps centred on their nearest pixel.

    Attributes
    ----------
    image : (n_s, n, n) counts, n odd
    ivar : (n_s, n, n) inverse variance (all positive for a usable star)
    delta : (n_s, 2) star centre minus stamp centre pixel, (dx, dy) pixels
    ccd : (n_s,) CCD index
    u, v : (n_s,) field position, scaled to about [-1, 1] over the field
    x, y : (n_s,) pixel position on the CCD (for the registration)
    snr : (n_s,) integrated signal-to-noise ratio
    """

    image: np.ndarray
    ivar: np.ndarray
    delta: np.ndarray
    ccd: np.ndarray
    u: np.ndarray
    v: np.ndarray
    x: np.ndarray
    y: np.ndarray
    snr: np.ndarray

    def __len__(self):
        return int(self.image.shape[0])

    def subset(self, sel) -> "StarSet":
        return StarSet(*(getattr(self, f)[sel] for f in
                         ("image", "ivar", "delta", "ccd", "u", "v", "x", "y", "snr")))

    @property
    def weight(self) -> np.ndarray:
        """The paper's star weight nu^2 / (nu^2 + 50^2)."""
        s2 = self.snr ** 2
        return s2 / (s2 + 50.0 ** 2)


def _signed_freq(n):
    return np.rint(np.fft.fftfreq(n) * n).astype(int)


def gaussian_centroid(img, step=1.0, sigma=2.0, n_iter=4):
    """Centroid (dx, dy) of images (..., N, N) from their centre, weighted by a Gaussian that follows it.

    ``step`` is the array's spacing in pixels, ``sigma`` the weight's width in pixels.
    """
    img = np.asarray(img, float)
    lead = img.shape[:-2]
    im = img.reshape((-1,) + img.shape[-2:])
    c = np.arange(im.shape[-1]) * step - (im.shape[-1] // 2) * step
    cx = np.zeros(im.shape[0])
    cy = np.zeros(im.shape[0])
    for _ in range(n_iter):
        wx = np.exp(-0.5 * ((c[None, :] - cx[:, None]) / sigma) ** 2)
        wy = np.exp(-0.5 * ((c[None, :] - cy[:, None]) / sigma) ** 2)
        # the weight is a product of one in x and one in y: sum over x by a matrix product, then over y
        rows = im @ np.stack([wx, wx * c[None, :]], axis=2)               # (n, N, 2)
        tot = np.einsum("sy,sy->s", wy, rows[:, :, 0])
        tot = np.where(tot != 0, tot, 1.0)
        cx = np.einsum("sy,sy->s", wy, rows[:, :, 1]) / tot
        cy = np.einsum("sy,sy->s", wy * c[None, :], rows[:, :, 0]) / tot
    return cx.reshape(lead), cy.reshape(lead)


@dataclass
class PixelPSF:
    """A fitted pixel PSF model of one exposure (see the module doc).

    ``spectra[t, my, mx, jy, jx]`` is term t's transform at the frequency
    j + n m (j in numpy's FFT order over the n-pixel stamp, m the alias
    index shifted to 0..k-1); ``kind[t]`` is 0 for a global term, 1 for a
    per-CCD term (of CCD ``term_ccd[t]``), 2 for an alias term;
    ``powers[t]`` its exponents (a, b) of u^a v^b.
    """

    size: int
    oversampling: int
    order: int
    n_ccd: int
    kind: np.ndarray
    term_ccd: np.ndarray
    powers: np.ndarray
    spectra: np.ndarray
    ccd_used: np.ndarray
    frame: dict = field(default_factory=dict)            # how (u, v) were made: ra0, dec0, scale
    registration: Optional[np.ndarray] = None            # (n_ccd, 2, n_reg) polynomial coefficients
    registration_order: int = 1
    alias_order: int = 0
    ccd_shape: Optional[np.ndarray] = None               # (n_ccd, 2) ny, nx for the registration's scaling
    _images: Optional[np.ndarray] = field(default=None, repr=False)

    # -- terms ---------------------------------------------------------------------------------
    def coefficients(self, ccd, u, v) -> np.ndarray:
        """Term values c_t at positions (arrays): shape (n, n_terms)."""
        ccd = np.atleast_1d(np.asarray(ccd, int))
        u = np.atleast_1d(np.asarray(u, float))
        v = np.atleast_1d(np.asarray(v, float))
        a = self.powers[:, 0][None, :]
        b = self.powers[:, 1][None, :]
        val = u[:, None] ** a * v[:, None] ** b
        on = (self.kind[None, :] != 1) | (self.term_ccd[None, :] == ccd[:, None])
        return np.where(on, val, 0.0)

    @property
    def images(self) -> np.ndarray:
        """Real-space images of the terms, (n_terms, k n, k n), sampled every 1/k pixel."""
        if self._images is None:
            fine = _fold_to_fine(self.spectra, self.size, self.oversampling)
            self._images = np.fft.fftshift(np.fft.ifft2(fine), axes=(-2, -1)).real
        return self._images

    def image(self, ccd, u, v) -> np.ndarray:
        """The PSF at one position: (k n, k n), unit sum, centred on index (kn // 2, kn // 2)."""
        if not self.ccd_used[int(ccd)]:
            raise ShearfitValueError(f"the PSF model has no stars on CCD {int(ccd)}")
        img = np.tensordot(self.coefficients(ccd, u, v)[0], self.images, axes=1)
        s = img.sum()
        return img / s if s != 0 else img

    def images_at(self, ccd, u, v) -> np.ndarray:
        """The PSF at many positions (arrays) of one CCD: (n, k n, k n), each as :meth:`image` would make it
        (one matrix product for all of them)."""
        if not self.ccd_used[int(ccd)]:
            raise ShearfitValueError(f"the PSF model has no stars on CCD {int(ccd)}")
        u = np.atleast_1d(np.asarray(u, float))
        imgs = self.images
        c = self.coefficients(np.full(u.size, int(ccd)), u, v)
        out = (c @ imgs.reshape(imgs.shape[0], -1)).reshape((u.size,) + imgs.shape[1:])
        s = out.sum(axis=(1, 2))
        return out / np.where(s != 0, s, 1.0)[:, None, None]

    # -- per-star transforms ---------------------------------------------------------------------
    def star_spectra(self, ccd, u, v) -> np.ndarray:
        """Each star's model transform over all aliases, (n_s, k, k, n, n)."""
        c = self.coefficients(ccd, u, v)
        return np.tensordot(c, self.spectra, axes=1)

    def native_dft(self, ccd, u, v, delta, P=None) -> np.ndarray:
        """Model DFTs of unit-flux stars at offsets ``delta`` (n_s, 2) on the n-pixel stamp: (n_s, n, n)
        (``P``: their :meth:`star_spectra`, if already made)."""
        if P is None:
            P = self.star_spectra(ccd, u, v)
        py, px = _axis_phases(self.size, self.oversampling, np.atleast_2d(delta))   # (n_s, k, n) each
        # the phase is a product of one in x and one in y: the aliases summed along x, then along y
        M = np.einsum("smyx,smy->syx", np.sum(P * px[:, None, :, None, :], axis=2), py)
        tot = M[:, 0, 0].real
        return M / np.where(tot != 0, tot, 1.0)[:, None, None]

    # -- registration ---------------------------------------------------------------------------
    def registration_shifts(self, ccd, x, y) -> np.ndarray:
        """:meth:`registration_shift` at many CCD pixels (arrays) of one CCD: (n, 2)."""
        return _registration_shifts(self, ccd, x, y)

    def registration_shift(self, ccd, x, y):
        """Astrometric offset (dx, dy), pixels, of a source at CCD pixel (x, y): true minus WCS position."""
        if self.registration is None:
            return 0.0, 0.0
        ny, nx = self.ccd_shape[int(ccd)]
        t = _reg_terms(np.atleast_1d(x) / nx - 0.5, np.atleast_1d(y) / ny - 0.5, self.registration_order)
        d = t @ self.registration[int(ccd)].T
        return float(d[0, 0]), float(d[0, 1])


def _registration_shifts(model, ccd, x, y) -> np.ndarray:
    """:meth:`PixelPSF.registration_shift` at many CCD pixels (arrays): (n, 2)."""
    x = np.atleast_1d(np.asarray(x, float))
    if model.registration is None:
        return np.zeros((x.size, 2))
    ny, nx = model.ccd_shape[int(ccd)]
    t = _reg_terms(x / nx - 0.5, np.atleast_1d(np.asarray(y, float)) / ny - 0.5, model.registration_order)
    return t @ model.registration[int(ccd)].T


def _reg_terms(xs, ys, order):
    return np.stack([xs ** a * ys ** b for a, b in monomials(order)], axis=-1)


def _fine_freqs(n, k):
    """Signed fine frequencies j + n m, shape (k, n) (m = -h..h along axis 0)."""
    h = (k - 1) // 2
    return _signed_freq(n)[None, :] + n * np.arange(-h, h + 1)[:, None]


def _axis_phases(n, k, delta):
    """The factors of :func:`_phases` in y and in x: exp(-2 pi i (j + n m) delta_y / n) and the same in
    delta_x, each (n_s, k, n)."""
    f = _fine_freqs(n, k)                                      # (k, n)
    px = np.exp(-2j * np.pi * f[None] * delta[:, 0, None, None] / n)   # (n_s, k, n)
    py = np.exp(-2j * np.pi * f[None] * delta[:, 1, None, None] / n)
    return py, px


def _phases(n, k, delta):
    """exp(-2 pi i (j + n m) . delta / n) per star: (n_s, k, k, n, n)."""
    py, px = _axis_phases(n, k, delta)
    return py[:, :, None, :, None] * px[:, None, :, None, :]


def _term_table(order, n_ccd, ccd_terms, ccd_used, k, alias_order):
    kind, tccd, powers = [], [], []
    if ccd_terms:
        for a, b in monomials(order, min_degree=2):
            kind.append(0), tccd.append(-1), powers.append((a, b))
        for c in range(n_ccd):
            if ccd_used[c]:
                for a, b in monomials(1):
                    kind.append(1), tccd.append(c), powers.append((a, b))
    else:
        for a, b in monomials(order):
            kind.append(0), tccd.append(-1), powers.append((a, b))
    if k > 1:
        for a, b in monomials(alias_order):
            kind.append(2), tccd.append(-1), powers.append((a, b))
    return np.array(kind), np.array(tccd), np.array(powers, int).reshape(-1, 2)


def _as_real(z):
    """A complex matrix (m, n) as the real one (m, 2 n) of its interleaved real and imaginary parts."""
    return np.ascontiguousarray(z, complex).view(float)


def _as_complex(x):
    """The inverse of :func:`_as_real`."""
    return np.ascontiguousarray(x).view(complex)


def _solve_modes(model: PixelPSF, D, stars: StarSet, flux, prior=None):
    """Least-squares spectra of every term, given star DFTs D (n_s, n, n), offsets and fluxes.

    With oversampling, ``prior`` = (mu, tau, s2): the alias unknowns get a
    Gaussian prior of mean ``mu`` and width ``tau`` (arrays like the alias
    terms' spectra), weighed against the data with ``s2`` (n, n), the
    residual variance per unit star weight at each stamp frequency. Native
    (k = 1), ``prior`` = (mu (T, n, n), tau (n, n), s2) puts such a prior on
    every term (:func:`_native_prior`).
    """
    n, k = model.size, model.oversampling
    w = stars.weight
    C = model.coefficients(stars.ccd, stars.u, stars.v)           # (n_s, T)
    base = model.kind != 2
    alias = model.kind == 2
    Y = D / flux[:, None, None]
    T = C.shape[1]
    spectra = np.zeros((T, k, k, n, n), complex)
    h = (k - 1) // 2
    if k == 1:
        # one design matrix for every frequency: shift the stars onto the grid (sinc), then fit
        ph = _phases(n, 1, stars.delta)[:, 0, 0]
        Yc = (Y * np.conj(ph)).reshape(len(stars), -1)
        sw = np.sqrt(w)[:, None]
        X = sw * C
        # with the Gaussian prior of _native_prior, frequency by frequency: (N + lam_j) c_j = X^T W y_j + lam_j mu_j,
        # N = X^T W X shared by every frequency (its eigenvectors once), lam_j = s2_j / tau_j^2; plain least
        # squares where lam_j = 0 (no prior, or stars without noise there)
        lam = np.zeros(n * n) if prior is None else (prior[2] / prior[1] ** 2).ravel()
        on = lam > 0
        coef = np.zeros((T, n * n), complex)
        # X is real: the complex right-hand sides are solved as their real and imaginary parts side by side
        # (real products, half the multiplications of complex ones with a zero imaginary part)
        if not np.all(on):
            coef[:, ~on] = _as_complex(np.linalg.lstsq(X, _as_real(sw * Yc[:, ~on]), rcond=None)[0])
        if np.any(on):
            e, V = np.linalg.eigh(X.T @ X)
            e = np.maximum(e, 0.0)
            R = V.T @ (_as_complex(X.T @ _as_real(sw * Yc[:, on])) + lam[on][None, :] * prior[0].reshape(T, -1)[:, on])
            coef[:, on] = V @ (R / (e[:, None] + lam[on][None, :]))
        spectra[:, 0, 0] = coef.reshape(T, n, n)
        return spectra
    mu, tau, s2 = prior
    ph = _phases(n, k, stars.delta)                                # (n_s, k, k, n, n)
    Cb, Ca = C[:, base], C[:, alias]
    nb, na = Cb.shape[1], Ca.shape[1]
    others = [(my, mx) for my in range(k) for mx in range(k) if (my, mx) != (h, h)]
    U = nb + na * len(others)
    for jy in range(n):
        for jx in range(n):
            cols = [Cb * ph[:, h, h, jy, jx, None]]
            for my, mx in others:
                cols.append(Ca * ph[:, my, mx, jy, jx, None])
            X = np.concatenate(cols, axis=1)
            XW = np.conj(X).T * w[None, :]
            N = XW @ X
            rhs = XW @ Y[:, jy, jx]
            # prior precision s2 / tau^2 on the alias unknowns (none on the base terms)
            m0 = np.concatenate([mu[:, my, mx, jy, jx] for my, mx in others])
            t0 = np.concatenate([tau[:, my, mx, jy, jx] for my, mx in others])
            lam = np.zeros(U)
            lam[nb:] = s2[jy, jx] / t0 ** 2
            rhs[nb:] += lam[nb:] * m0
            sol = np.linalg.solve(N + np.diag(lam), rhs)
            spectra[base, h, h, jy, jx] = sol[:nb]
            for q, (my, mx) in enumerate(others):
                spectra[alias, my, mx, jy, jx] = sol[nb + q * na: nb + (q + 1) * na]
    return spectra


def _residual_variance(model: PixelPSF, D, stars: StarSet, flux, M):
    """Per stamp frequency, the weighted residual variance per unit star weight, (n, n).

    ``M`` is the model's DFT at the stars (``_star_fluxes`` returns it with the fluxes).
    """
    r = D / flux[:, None, None] - M
    w = stars.weight
    dof = max(len(stars) - int(np.sum(model.kind != 2)), 1)
    return np.sum(w[:, None, None] * np.abs(r) ** 2, axis=0) / dof


def _model_moffat(native: PixelPSF, stars: StarSet, k):
    """The native model's mean transform over the stars P0 (n, n; P0(0) = 1) and the circular Moffat times the
    pixel response fitted to it (as the likelihood's App. A correction) at the fine frequencies j + n m,
    G (k, k, n, n)."""
    from ..engine.moffat import fit_moffat, moffat_ft

    n = native.size
    # the mean of the stars' transforms: the terms' spectra at the stars' mean coefficients
    cbar = np.mean(native.coefficients(stars.ccd, stars.u, stars.v), axis=0)
    P0 = np.tensordot(cbar, native.spectra[:, 0, 0], axes=1)                             # (n, n)
    P0 = P0 / P0[0, 0].real
    rs, beta = fit_moffat(P0[:, : n // 2 + 1], 2 * np.pi * np.fft.fftfreq(n), 2 * np.pi * np.fft.rfftfreq(n))
    f = _fine_freqs(n, k)                                   # (k, n) signed fine frequencies per axis
    kf = 2 * np.pi * f / n
    pix = np.sinc(f / n)
    kk = np.hypot(kf[:, None, :, None], kf[None, :, None, :])          # (k, k, n, n)
    return P0, moffat_ft(kk, rs, beta) * pix[:, None, :, None] * pix[None, :, None, :]


def _alias_prior(native: PixelPSF, stars: StarSet, k, model: PixelPSF, rel_width=0.5, floor=1e-5):
    """Prior mean and width of the above-Nyquist components: the native model extrapolated by a Moffat.

    The mean of the native model over the stars is fitted with a circular
    Moffat times the pixel response (as the likelihood's alias correction,
    App. A); alias m of stamp frequency j is expected at
    ``P(j) G(j + n m) / G(j)``, give or take ``rel_width`` of itself (plus a
    small floor), so that components the stars' sub-pixel phases constrain
    follow the stars and the others fall back on the Moffat extrapolation.
    """
    n = native.size
    P0, G = _model_moffat(native, stars, k)
    h = (k - 1) // 2
    g0 = G[h, h]
    ratio = np.where(np.abs(g0) > 1e-12, G / np.where(np.abs(g0) > 1e-12, g0, 1.0), 0.0)
    alias = model.kind == 2
    const = alias & (model.powers[:, 0] == 0) & (model.powers[:, 1] == 0)
    mu = np.zeros((int(alias.sum()), k, k, n, n), complex)
    mu[const[alias]] = ratio * P0[None, None]
    tau = np.broadcast_to(rel_width * np.abs(ratio * P0[None, None]) + floor, mu.shape).copy()
    return mu, tau


def _native_prior(model: PixelPSF, stars: StarSet, rel_width, floor=1e-5):
    """Prior mean and width of a native model's spectra where the stars do not constrain them.

    A circular Moffat times the pixel response is fitted to the mean of the model over the stars (as the
    likelihood's App. A correction); each CCD's constant term is expected at its transform, give or take
    ``rel_width`` of it (plus a small floor), and every other term at zero, give or take the same. Where the
    stars measure a frequency well (their residual variance small against the width) the prior does not
    move it; where the PSF's transform is far below the stars' noise (the highest frequencies of a PSF a few
    pixels wide) the model takes the Moffat's instead of fitting the noise. Returns (mu (T, n, n), tau (n, n)).
    """
    n = model.size
    G = _model_moffat(model, stars, 1)[1][0, 0]
    const = (model.kind != 2) & (model.powers[:, 0] == 0) & (model.powers[:, 1] == 0)
    mu = np.zeros((model.kind.size, n, n), complex)
    mu[const] = G
    return mu, rel_width * np.abs(G) + floor


def _centre_by_xcorr(model: PixelPSF, D, stars: StarSet, n_newton=6, max_step=0.5, P=None):
    """Offsets maximising each star's band-limited cross-correlation with the model (``P``: the stars'
    :meth:`PixelPSF.star_spectra`, if already made)."""
    n, k = model.size, model.oversampling
    if P is None:
        P = model.star_spectra(stars.ccd, stars.u, stars.v)      # (n_s, k, k, n, n)
    ns, K = P.shape[0], k * n
    # conj(D) P with rows (m_y, j_y) and columns (m_x, j_x): the phases exp(-i kappa . delta) are a product
    # of one along the rows and one along the columns, so that the sums of E = base x phases (and of its
    # products with the modes' kappa_x, kappa_y) are matrix products over the columns, then over the rows
    B = (np.conj(D)[:, None, None, :, :] * P).transpose(0, 1, 3, 2, 4).reshape(ns, K, K)
    kap = (2 * np.pi / n) * _fine_freqs(n, k).ravel()             # (K,), (m, j) order on both axes
    kap2 = kap * kap
    delta = stars.delta.copy()
    for _ in range(n_newton):
        px = np.exp(-1j * kap[None, :] * delta[:, 0, None])       # (n_s, K)
        py = np.exp(-1j * kap[None, :] * delta[:, 1, None])
        Q = B @ np.stack([px, px * kap, px * kap2], axis=2)        # (n_s, K, 3): sum over x of E, kx E, kx^2 E
        sx = np.einsum("sy,sy->s", py, Q[:, :, 1])                # sum kx E
        sy = np.einsum("sy,sy->s", py * kap, Q[:, :, 0])          # sum ky E
        sxx = np.einsum("sy,sy->s", py, Q[:, :, 2])
        sxy = np.einsum("sy,sy->s", py * kap, Q[:, :, 1])
        syy = np.einsum("sy,sy->s", py * kap2, Q[:, :, 0])
        # the gradient and Hessian of sum Re(E) over the modes: Re(-i kappa E) = Im(kappa E),
        # Re(-kappa kappa' E) = -Re(kappa kappa' E)
        g = np.stack([sx.imag, sy.imag], axis=1)
        hxx, hxy, hyy = -sxx.real, -sxy.real, -syy.real
        det = hxx * hyy - hxy * hxy
        ok = (hxx < 0) & (det > 0)
        dx = np.where(ok, -(hyy * g[:, 0] - hxy * g[:, 1]) / np.where(ok, det, 1.0), 0.0)
        dy = np.where(ok, -(-hxy * g[:, 0] + hxx * g[:, 1]) / np.where(ok, det, 1.0), 0.0)
        step = np.stack([dx, dy], axis=1)
        norm = np.hypot(step[:, 0], step[:, 1])
        step *= np.minimum(1.0, max_step / np.maximum(norm, 1e-12))[:, None]
        delta = delta + step
    return delta


def _star_fluxes(model: PixelPSF, D, stars: StarSet, P=None):
    M = model.native_dft(stars.ccd, stars.u, stars.v, stars.delta, P=P)
    num = np.sum((np.conj(M) * D).real, axis=(1, 2))
    den = np.sum(np.abs(M) ** 2, axis=(1, 2))
    return num / np.where(den > 0, den, 1.0), M


def residual_images(model: PixelPSF, stars: StarSet, flux=None):
    """Flux-normalised star minus model at each star, native pixels (n_s, n, n), centred stamps."""
    D = np.fft.fft2(np.fft.ifftshift(stars.image, axes=(-2, -1)))
    f, M = _star_fluxes(model, D, stars)
    if flux is not None:
        f = flux
    r = np.fft.fftshift(np.fft.ifft2(D / f[:, None, None] - M), axes=(-2, -1)).real
    return r, f


def fit_pixel_psf(stars: StarSet, n_ccd: int, order: int = 3, oversampling: int = 1, ccd_terms: bool = True,
                  alias_order: int = 0, iterations: int = 2, alias_width: float = 0.5, clip: float = 5.0,
                  centroid_sigma: float = 2.0, registration_order: int = 1, ccd_shape=None,
                  centre: bool = True, frame=None, native_width: float = 1.0) -> tuple:
    """Fit the pixel PSF model of one exposure to its stars.

    Parameters
    ----------
    stars : StarSet
        Usable stars (the selection cuts already applied), stamps of odd size n.
    n_ccd : int
        CCDs of the exposure (indices in ``stars.ccd``).
    order : int
        Polynomial order over the field (the paper's 3).
    oversampling : int
        1 (the paper: native pixels, sinc-centred stars) or an odd k > 1.
    ccd_terms : bool
        Constant and linear terms free per CCD (the paper's choice).
    alias_order : int
        Polynomial order of the above-Nyquist components (oversampling > 1).
    iterations : int
        Centring / fitting rounds after the first fit. Two: a third changes the models by about 1e-4 of their
        peak (at most 1.1e-4 on the seven exposures of ``benchmarks/pipeline_profile.py``'s field), and
        ``benchmarks/psf_model_test.py``'s residuals against the true PSF not at all in their printed digits
        (native and 3x models).
    alias_width : float
        With oversampling, the relative width of the prior on the
        above-Nyquist components around the native model's Moffat
        extrapolation (see ``_alias_prior``); the native model is fitted
        first and gives the stars' starting centres.
    native_width : float
        The relative width of the prior on the native model's spectra (``_native_prior``): the
        frequencies the stars cannot measure (the PSF's transform below their noise) follow a Moffat
        fitted to the model instead of the noise, from the second fit on. 0: plain least squares at
        every frequency (the paper's fit).
    clip : float
        Stars whose reduced chi^2 exceeds the median by ``clip`` robust
        sigmas are dropped (binaries, galaxies, cosmic rays) before the last fit.
    centre : bool
        Centre the stars (cross-correlation with the model) and the model
        (on its Gaussian-weighted centroid); False keeps ``stars.delta``.

    Returns
    -------
    (PixelPSF, StarSet, dict)
        The model, the stars used (with their fitted offsets), and
        per-star results: ``flux``, ``chi2`` (reduced), ``offset`` (fitted
        minus initial position, pixels), ``kept`` (mask over the input stars).
    """
    n = stars.image.shape[-1]
    if n % 2 == 0 or stars.image.shape[-2] != n:
        raise ShearfitValueError(f"PSF stamps must be square with an odd side, got {stars.image.shape[1:]}")
    k = int(oversampling)
    if k < 1 or k % 2 == 0:
        raise ShearfitValueError(f"setting psf_oversampling={k} must be 1 or an odd number (3, 5)")
    ccd_used = np.zeros(n_ccd, bool)
    ccd_used[np.unique(stars.ccd)] = True
    kind, tccd, powers = _term_table(order, n_ccd, ccd_terms, ccd_used, k, alias_order)
    n_base = int(np.sum(kind != 2))
    if len(stars) < n_base + 1:
        raise ShearfitValueError(f"{len(stars)} stars cannot constrain a PSF model with {n_base} terms")
    model = PixelPSF(size=n, oversampling=k, order=order, n_ccd=n_ccd, kind=kind, term_ccd=tccd, powers=powers,
                     spectra=np.zeros((kind.size, k, k, n, n), complex), ccd_used=ccd_used, frame=dict(frame or {}),
                     registration_order=registration_order, alias_order=alias_order,
                     ccd_shape=None if ccd_shape is None else np.asarray(ccd_shape))
    initial = stars.delta.copy()
    prior = None
    if k > 1:
        # the native model first: the stars' centres, fluxes and outlier cut, and the prior above Nyquist
        native, st, nat = fit_pixel_psf(stars, n_ccd, order=order, oversampling=1, ccd_terms=ccd_terms,
                                        iterations=iterations, clip=clip, centroid_sigma=centroid_sigma,
                                        centre=centre, frame=frame, native_width=native_width)
        kept = nat["kept"].copy()
        D = np.fft.fft2(np.fft.ifftshift(st.image, axes=(-2, -1)))
        flux, M = _star_fluxes(native, D, st)
        mu, tau = _alias_prior(native, st, k, model, rel_width=alias_width)
        prior = (mu, tau, _residual_variance(native, D, st, flux, M))
        clip = 0.0
    else:
        st = stars.subset(np.arange(len(stars)))
        # starting point: Gaussian-weighted centroids and stamp sums
        if centre:
            cx, cy = gaussian_centroid(st.image, 1.0, centroid_sigma)
            st.delta = np.stack([cx, cy], axis=1)
        D = np.fft.fft2(np.fft.ifftshift(st.image, axes=(-2, -1)))
        flux = D[:, 0, 0].real.copy()
        kept = np.ones(len(stars), bool)
    for it in range(iterations + 1):
        model.spectra = _solve_modes(model, D, st, flux, prior)
        model._images = None
        if it == iterations:
            break
        P = model.star_spectra(st.ccd, st.u, st.v)     # the model at the stars, for this round's steps
        if centre:
            st.delta = _centre_by_xcorr(model, D, st, P=P)
            # the model centred on its own centroid: move each star by the model's centroid there
            fine = _fold_to_fine(P, n, k)
            imgs = np.fft.fftshift(np.fft.ifft2(fine), axes=(-2, -1)).real
            mx, my = gaussian_centroid(imgs, 1.0 / k, centroid_sigma)
            st.delta = st.delta + np.stack([mx, my], axis=1)
        flux, M = _star_fluxes(model, D, st, P=P)
        if k > 1:
            prior = (prior[0], prior[1], _residual_variance(model, D, st, flux, M))
        elif native_width > 0:
            prior = _native_prior(model, st, native_width) + (_residual_variance(model, D, st, flux, M),)
        if it == iterations - 1 and clip > 0:
            chi2 = _reduced_chi2(st, D, flux, M)
            med = np.median(chi2)
            mad = 1.4826 * np.median(np.abs(chi2 - med))
            good = chi2 <= med + clip * max(mad, 1e-3 * med)
            if np.sum(good) > n_base and not np.all(good):
                idx = np.nonzero(kept)[0]
                kept[idx[~good]] = False
                st = st.subset(good)
                D, flux = D[good], flux[good]
    flux, M = _star_fluxes(model, D, st)
    if k == 1 and native_width > 0 and iterations == 0:
        # a single fit (no rounds to carry the prior): the prior from its residuals, then the fit again
        prior = _native_prior(model, st, native_width) + (_residual_variance(model, D, st, flux, M),)
        model.spectra = _solve_modes(model, D, st, flux, prior)
        model._images = None
        flux, M = _star_fluxes(model, D, st)
    chi2 = _reduced_chi2(st, D, flux, M)
    offset = st.delta - initial[kept]
    if ccd_shape is not None:
        model.registration = fit_registration(st, offset, n_ccd, registration_order, model.ccd_shape)
    return model, st, dict(flux=flux, chi2=chi2, offset=offset, kept=kept)


def _fold_to_fine(P, n, k):
    """Spectra (m, k, k, n, n) (per star or per term) on the fine FFT grid (m, kn, kn), FFT order, times k^2.

    Its inverse FFT is the model sampled every 1/k pixel (origin at index 0).
    """
    K = k * n
    if k == 1:   # the native grid: the fine frequencies are the stamp's own, in FFT order
        return P[:, 0, 0].copy()
    f = _fine_freqs(n, k) % K
    out = np.zeros(P.shape[:1] + (K, K), complex)
    out[:, f[:, None, :, None], f[None, :, None, :]] = P
    return out * k * k


def _reduced_chi2(st, D, flux, M):
    r = np.fft.ifft2(D - flux[:, None, None] * M).real
    r = np.fft.fftshift(r, axes=(-2, -1))
    npix = st.image.shape[-1] * st.image.shape[-2]
    return np.sum(r * r * st.ivar, axis=(1, 2)) / npix


def fit_registration(st: StarSet, offset, n_ccd, order, ccd_shape):
    """Per-CCD polynomial of the star offsets in CCD pixel position (weighted least squares)."""
    nt = len(monomials(order))
    coef = np.zeros((n_ccd, 2, nt))
    w = st.weight
    for c in range(n_ccd):
        sel = st.ccd == c
        if not np.any(sel):
            continue
        ny, nx = ccd_shape[c]
        t = _reg_terms(st.x[sel] / nx - 0.5, st.y[sel] / ny - 0.5, order)
        use = min(nt, int(sel.sum()))
        sw = np.sqrt(w[sel])[:, None]
        sol, *_ = np.linalg.lstsq(sw * t[:, :use], sw * offset[sel], rcond=None)
        coef[c, :, :use] = sol.T
    return coef
