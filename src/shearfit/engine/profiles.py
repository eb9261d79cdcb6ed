"""Fourier transforms of the truncated circular galaxy profiles of the model.

The lensfit model (Miller et al. 2013) is a sum of a truncated exponential
disk and a truncated de Vaucouleurs bulge, sheared, convolved with the PSF and
evaluated in Fourier space. Shearing a circular profile only changes the
wavevector at which its transform is read, so everything the likelihood needs
from a profile is one radial function: its Hankel transform

    R(k) = 2 pi int_0^T I(r) J0(k r) r dr / (2 pi int_0^T I(r) r dr),

with k in radians per unit of the profile's scale (the disk's scalelength, the
half-light radius of the other profiles) and R(0) = 1. The engine evaluates
R about 10^7 times per batch of galaxies, at ``rho2 = k**2`` (it comes out of a
quadratic form, and a square root per element would cost as much as the
look-up), so :class:`RadialProfile` tabulates R once on a grid in ``rho2``
and evaluates it by linear interpolation (``np.interp``).

How the table is computed
-------------------------
The integrand oscillates about ``k T / pi`` times over ``[0, T]``; the table
needs R out to k ~ 10^4 (the de Vaucouleurs cusp makes R fall only like
k^-2.25), where a real-axis quadrature would need ~10^5 Bessel evaluations
per k. Instead, for ``k T >= 45`` the integral is moved into the complex
plane (the numerical steepest-descent method). With the Hankel function
``H0 = J0 + i Y0`` and ``g(r) = r I(r)`` real on the real axis,
``int_0^T g J0(k r) dr = Re int_0^T g H0(k r) dr``; ``H0(k z)`` decays like
``exp(-k Im z)`` in the upper half-plane and ``g`` is analytic in the right
half-plane (the Sersic profile's branch point sits at r = 0), so the
segment ``[0, T]`` can be replaced by two rays going up from its endpoints:

* from r = 0 up the imaginary axis, where ``H0(i x) = (2 / (i pi)) K0(x)``
  is not oscillatory. This ray carries the cusp at the centre, i.e. the
  smooth power-law tail ``~ k^(-2-1/n)`` of R. Double-exponential (exp-sinh)
  quadrature copes with the log singularity of K0 and the ``x^(1/n)`` branch
  point at its start.
* from r = T straight up, where ``H0(k (T + i s)) ~ exp(i k T) exp(-k s)``:
  Gauss-Laguerre quadrature in ``k s`` with the large-argument expansion of
  H0. This ray carries the truncation edge, i.e. the oscillating part of R
  (period ``2 pi / T`` in k, amplitude ~ k^-1.5).

Both cost under 100 function evaluations whatever k is, and agree with a
brute-force real-axis quadrature to 1e-12 (T = 4.5; 3e-10 at worst over the
tested 1 <= T <= 40). For ``k T < 45`` (and small k, where the
imaginary-axis integrand would itself oscillate) a real-axis composite
Gauss-Legendre quadrature is used instead, in the variable ``t = r^(1/n)``
that turns the Sersic cusp ``exp(-b r^(1/n))`` into ``exp(-b t)``. For n < 1
the profile grows along the imaginary axis, so both rays are tilted to the
angle ``0.4 n pi``.

Splitting R into the two ray contributions also gives the envelopes of its
smooth and oscillating parts separately, which is how the table decides where
it has to resolve the oscillations and where R has become negligible.

The table
---------
``rho_max`` is where the envelope of |R| falls below 5e-7 for good (but at
least 400): ~1180 for the disk, ~11300 for the bulge. The start grid is
uniform in k with two nodes per oscillation period ``2 pi / T`` up to where
the oscillations' envelope falls below 1e-7, geometric (5%) beyond. Every
interval is then bisected in rho2 until the linear interpolant is within
4e-7 of the quadrature at the interval's midpoint and quarter points. The
result has ~10^4 nodes (spacing down to ~0.001 in k for 0.5 < k < 5, where R
curves most as a function of rho2) and interpolates to within ~4.3e-7.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.polynomial.laguerre import laggauss
from numpy.polynomial.legendre import leggauss
from scipy import special

from ..errors import ShearfitValueError
from .kernel import KERNEL, USE_KERNEL

__all__ = ["RadialProfile", "exponential_disk", "de_vaucouleurs", "sersic"]

DEFAULT_TRUNCATION = 4.5

# |R| stays below this beyond rho_max, where ft_rho2 returns 0.
_NEGLIGIBLE_FT = 5e-7
_MIN_RHO_MAX = 400.0
# Largest allowed error of the linear interpolant at the midpoint and quarter
# points (in rho2) of every table interval; the error elsewhere is no larger
# to within ~10%, leaving a factor 4 margin to the 2e-6 promised.
_TABLE_TOL = 4e-7
# Oscillations of R smaller than this need not be resolved by the table: a
# linear interpolant straddling them is off by at most twice their amplitude.
_NEGLIGIBLE_OSCILLATION = 1e-7

# The contour quadrature needs k T at least this large: the large-argument
# series for H0 on the edge ray and the Gauss-Laguerre rule there converge
# with the distance k T from the ray's start to the singularity at z = 0.
_MIN_KT_CONTOUR = 45.0
_HANKEL_TERMS = 16  # terms of the H0 series; the next one is < 1e-17 for |z| >= 45
_LAGUERRE_NODES = 32
# The origin-ray integrand exp(-b (i x / k)^(1/n)) K0(x) must not turn by more
# than _ORIGIN_RAY_PHASE radians over the x < _ORIGIN_RAY_X where K0 matters,
# or the exp-sinh rule below cannot follow it.
_ORIGIN_RAY_X = 30.0
_ORIGIN_RAY_PHASE = 10.0
# exp-sinh steps. On the tilted ray (n < 1) H0(x e^{i theta}) oscillates as
# well as decays, which needs the finer step and k >= _MIN_K_TILTED. With
# these, above the switch the contour agrees with an independent real-axis
# quadrature to < 3e-10 (< 1e-12 for T = 4.5), 0.3 <= n <= 6.2, 1 <= T <= 40.
_DE_STEP = 0.1
_DE_STEP_TILTED = 0.0125
_MIN_K_TILTED = 2.0
_DE_RANGE = 4.0
# Real-axis composite Gauss-Legendre (agrees with 4x as many nodes to 1e-14).
_GL_ORDER = 16
_GL_RADIANS_PER_PANEL = 1.5  # J0 phase change across one panel at k = k_switch
_GL_GRADING_LEVELS = 14  # panels halving towards r = 0 for the cusp
_CHUNK = 4096  # rows of k per vectorised block, bounds temporary memory

_MIN_SERSIC_N = 0.3
_MAX_SERSIC_N = 6.2


def _sersic_b(n):
    """b_n such that r = 1 is the half-light radius of the untruncated Sersic(n)."""
    return float(special.gammaincinv(2.0 * n, 0.5))


@functools.lru_cache(maxsize=None)
def _hankel_coefficients():
    """i^m a_m(0) of Hankel's expansion (DLMF 10.17.1), m = 0 .. _HANKEL_TERMS-1."""
    coeffs = [1.0 + 0j]
    for m in range(1, _HANKEL_TERMS):
        coeffs.append(coeffs[-1] * 1j * (-(2 * m - 1) ** 2) / (8.0 * m))
    return tuple(coeffs)


def _hankel1_0_scaled(z):
    """H0^(1)(z) exp(-i z) for |z| >= 26, Re z > 0, from Hankel's expansion.

    The factor exp(i z) is left out so that the caller can fold its modulus
    into the Gauss-Laguerre weight and keep its phase exp(i Re z) apart.
    """
    coeffs = _hankel_coefficients()
    w = 1.0 / z
    series = np.full_like(z, coeffs[-1])
    for c in coeffs[-2::-1]:
        series = series * w + c
    return np.sqrt(2.0 / (np.pi * z)) * np.exp(-0.25j * np.pi) * series


class RadialProfile:
    """A truncated circular Sersic profile and its tabulated Fourier transform.

    Built by :func:`exponential_disk`, :func:`de_vaucouleurs` and
    :func:`sersic`, which memoise it: instances are shared and must be
    treated as immutable.

    The unnormalised profile is ``exp(-b r^(1/n))`` for ``r < truncation``
    and 0 beyond, in units of its scale: the scalelength for the exponential
    disk (n = 1, b = 1), the half-light radius of the *untruncated* profile
    otherwise (``b = gammaincinv(2n, 1/2)``). It is normalised to unit flux
    after truncation, so ``ft(0) == 1``.

    Parameters
    ----------
    name : str
        Label, e.g. ``"exponential"``.
    sersic_n : float
        Sersic index n.
    b : float
        Coefficient b of ``exp(-b r^(1/n))``.
    truncation : float
        Truncation radius T, in units of the profile's scale.

    Attributes
    ----------
    name : str
    sersic_n : float
    b : float
    truncation : float
    rho_max : float
        Largest k of the table; ``ft_rho2`` returns 0 beyond it, where
        ``|R| < 5e-7``. At least 400.
    rho2_nodes : ndarray
        The table's abscissae ``k^2`` (read-only, strictly increasing, first
        0, last ``rho_max**2``).
    ft_nodes : ndarray
        R at those nodes (read-only).
    """

    _kind = None  # set by the factories; selects the recipe pickle ships

    def __init__(self, name, sersic_n, b, truncation):
        self.name = str(name)
        self.sersic_n = float(sersic_n)
        self.b = float(b)
        self.truncation = float(truncation)
        n, T = self.sersic_n, self.truncation
        # int_0^T exp(-b r^(1/n)) r dr, by u = b r^(1/n).
        self._norm = math.exp(math.log(n) + special.gammaln(2 * n) - 2 * n * math.log(self.b)) * float(
            special.gammainc(2 * n, self.b * T ** (1 / n))
        )
        # The rays leave the real axis at angle theta; for n < 1 the profile
        # grows along the imaginary axis (Re z^(1/n) < 0 there) and the rays
        # must stay inside |arg z| < n pi / 2.
        self._theta = 0.5 * np.pi if n >= 1 else 0.4 * n * np.pi
        # Below k_switch the imaginary-axis integrand exp(-b (i x / k)^(1/n))
        # oscillates too fast in x for the fixed exp-sinh rule, or k T is too
        # small for the edge ray; the real axis is cheap there instead.
        if n >= 1:
            phase_rate = self.b * math.sin(0.5 * np.pi / n)
            k_origin = _ORIGIN_RAY_X * (phase_rate / _ORIGIN_RAY_PHASE) ** n
        else:
            k_origin = _MIN_K_TILTED
        self._k_switch = max(_MIN_KT_CONTOUR / T, k_origin)
        with np.errstate(under="ignore"):
            self._setup_real_axis()
            self._setup_contour()
            self._build_table()

    # ------------------------------------------------------------------
    # quadratures

    def _setup_real_axis(self):
        """Composite Gauss-Legendre nodes in t = r^(1/m), sized for k <= k_switch."""
        n, T = self.sersic_n, self.truncation
        # r = t^m with m = n makes the Sersic exponent b t linear and the
        # Jacobian m t^(2m-1) polynomial for half-integer n; n < 1 is smooth
        # enough in r itself.
        m = max(n, 1.0)
        t_max = T ** (1.0 / m)
        # Panels of equal J0 phase (uniform in r), plus enough for the profile's
        # own decay, plus geometric grading towards the cusp at t = 0.
        n_phase = math.ceil(self._k_switch * T / _GL_RADIANS_PER_PANEL)
        n_decay = math.ceil(self.b * T ** (1.0 / n) / 2.0)
        n_pan = max(n_phase, n_decay, 8)
        edges_r = np.linspace(0.0, T, n_pan + 1)
        edges = np.unique(np.concatenate([
            edges_r ** (1.0 / m),
            edges_r[1] ** (1.0 / m) * 0.5 ** np.arange(1, _GL_GRADING_LEVELS + 1),
            [0.0, t_max],
        ]))
        x, w = leggauss(_GL_ORDER)
        a, c = edges[:-1, None], edges[1:, None]
        t = (0.5 * (c - a) * x + 0.5 * (a + c)).ravel()
        wt = (0.5 * (c - a) * w).ravel()
        r = t ** m
        self._gl_r = r
        self._gl_w = m * t ** (2 * m - 1) * np.exp(-self.b * r ** (1.0 / n)) * wt / self._norm

    def _setup_contour(self):
        """Nodes and k-independent factors of the two complex rays."""
        theta = self._theta
        sin_t = math.sin(theta)
        self._ray = complex(math.cos(theta), sin_t)
        # Origin ray z = x e^{i theta} / k: exp-sinh nodes in x, trimmed where
        # H0 has underflowed (|H0(x e^{i theta})| ~ exp(-x sin theta)).
        step = _DE_STEP if theta == 0.5 * np.pi else _DE_STEP_TILTED
        u = np.arange(-_DE_RANGE, _DE_RANGE + 0.5 * step, step)
        x = np.exp(0.5 * np.pi * np.sinh(u))
        wx = x * 0.5 * np.pi * np.cosh(u) * step
        # Beyond x sin(theta) = 60, |H0| < 1e-26; below x = 1e-12 the
        # integrand ~ x log x contributes < 1e-22.
        keep = (x * sin_t < 60.0) & (x > 1e-12)
        x, wx = x[keep], wx[keep]
        self._o_x = x
        if theta == 0.5 * np.pi:
            # e^{i pi/2} H0(i x) = (2/pi) K0(x) is real, so the real part of
            # the ray integral needs only real arithmetic (see _contour_parts).
            self._o_wh = wx * (2.0 / np.pi) * special.k0(x)
            phi = 0.5 * np.pi / self.sersic_n
            self._o_a = self.b * math.cos(phi)
            self._o_b = self.b * math.sin(phi)
        else:
            self._o_wh = wx * self._ray * special.hankel1(0, x * self._ray)
        # Edge ray z = T + y e^{i theta} / (k sin theta): Gauss-Laguerre in y.
        y, wy = laggauss(_LAGUERRE_NODES)
        self._e_y = y
        self._e_w = wy
        self._e_step = self._ray / sin_t  # dz per unit y, times k
        self._e_cot = math.cos(theta) / sin_t

    def _root(self, z):
        """z^(1/n) on the principal branch (sqrt is much faster than pow)."""
        n = self.sersic_n
        if n == 1.0:
            return z
        if n == 2.0:
            return np.sqrt(z)
        if n == 4.0:
            return np.sqrt(np.sqrt(z))
        return z ** (1.0 / n)

    def _g(self, z):
        """g(z) = z exp(-b z^(1/n)), the integrand r I(r) continued off the real axis."""
        return z * np.exp(-self.b * self._root(z))

    def _contour_parts(self, k):
        """Origin-ray (real part) and edge-ray (without its phase) integrals, normalised.

        ``R(k) = origin + Re(edge * exp(i k T))`` for k above the switch;
        ``|edge|`` is the envelope of R's oscillating part and ``|origin|``
        its smooth part.
        """
        k = np.asarray(k, dtype=np.float64).ravel()
        origin = np.empty(k.size)
        edge = np.empty(k.size, dtype=np.complex128)
        T = self.truncation
        for lo in range(0, k.size, _CHUNK):
            kk = k[lo:lo + _CHUNK, None]
            # (e^{i theta}/k) int g(x e^{i theta}/k) H0(x e^{i theta}) dx
            if self._theta == 0.5 * np.pi:
                # Re g(i s) = s exp(-A s^(1/n)) sin(B s^(1/n)), A + iB = b e^{i pi/(2n)}
                s = self._o_x / kk
                p = self._root(s)
                re_g = s * np.exp(-self._o_a * p) * np.sin(self._o_b * p)
                origin[lo:lo + _CHUNK] = (re_g @ self._o_wh) / kk[:, 0]
            else:
                zo = self._o_x * self._ray / kk
                origin[lo:lo + _CHUNK] = (self._g(zo) @ self._o_wh).real / kk[:, 0]
            # -(e^{i theta}/(k sin theta)) int g(z) H0(k z) dy, z = T + y e^{i theta}/(k sin theta),
            # where H0(k z) = e^{i k T} e^{i y cot(theta)} e^{-y} _hankel1_0_scaled(k z).
            kz = kk * T + self._e_y * self._e_step
            ze = T + self._e_y * self._e_step / kk
            f = self._g(ze) * _hankel1_0_scaled(kz)
            if self._e_cot != 0.0:
                f = f * np.exp(1j * self._e_cot * self._e_y)
            edge[lo:lo + _CHUNK] = -(self._e_step / kk[:, 0]) * (f @ self._e_w)
        return origin / self._norm, edge / self._norm

    def _ft_contour(self, k):
        origin, edge = self._contour_parts(k)
        phase = np.exp(1j * self.truncation * np.asarray(k, dtype=np.float64).ravel())
        return origin + (edge * phase).real

    def _ft_real_axis(self, k):
        k = np.asarray(k, dtype=np.float64).ravel()
        out = np.empty(k.size)
        rows = max(1, (1 << 21) // self._gl_r.size)
        for lo in range(0, k.size, rows):
            out[lo:lo + rows] = special.j0(np.outer(k[lo:lo + rows], self._gl_r)) @ self._gl_w
        return out

    def ft_quadrature(self, k):
        """R(k) by direct quadrature (slow reference; accurate to ~1e-10 or better).

        Real-axis Gauss-Legendre for ``k < k_switch``, the complex-plane rays
        above (see the module docstring).

        Parameters
        ----------
        k : array_like
            Wavenumbers (any shape; the sign is irrelevant).

        Returns
        -------
        ndarray
            R(k), float64, same shape as ``k``.
        """
        k = np.abs(np.asarray(k, dtype=np.float64))
        flat = k.ravel()
        out = np.empty(flat.size)
        low = flat < self._k_switch
        with np.errstate(under="ignore"):
            if low.any():
                out[low] = self._ft_real_axis(flat[low])
            if (~low).any():
                out[~low] = self._ft_contour(flat[~low])
        return out.reshape(k.shape)

    # ------------------------------------------------------------------
    # table

    def _envelopes(self, k):
        """Upper envelopes of |R| and of its oscillating part (k >= k_switch)."""
        origin, edge = self._contour_parts(k)
        return np.abs(origin) + np.abs(edge), np.abs(edge)

    def _build_table(self):
        T = self.truncation
        # Both envelopes are smooth and eventually monotone, so a geometric
        # scan finds where R and its oscillations become negligible.
        scan = self._k_switch * 1.02 ** np.arange(1200)
        total, osc = self._envelopes(scan)
        big = np.nonzero(total >= _NEGLIGIBLE_FT)[0]
        if big.size and big[-1] + 1 >= scan.size:  # pragma: no cover - n <= 6.2 never gets here
            raise ShearfitValueError(f"profile {self.name}: FT not negligible by k = {scan[-1]:.3g}")
        rho_max = max(_MIN_RHO_MAX, scan[big[-1] + 1] if big.size else scan[0])
        big = np.nonzero(osc >= _NEGLIGIBLE_OSCILLATION)[0]
        k_osc = scan[big[-1] + 1] if big.size else self._k_switch

        # Start grid: 2 nodes per oscillation period where the oscillations
        # matter, so that the test below (3 points per interval, 8 per
        # period) cannot alias them: R is the cosine transform of the
        # profile's projection, band-limited to "frequency" T in k, so
        # nothing in it varies faster than period 2 pi / T. Geometric beyond,
        # where only the smooth power-law tail is left.
        h0 = np.pi / T
        k_uni = min(max(k_osc, 20.0 * h0), rho_max)
        k_grid = np.linspace(0.0, k_uni, math.ceil(k_uni / h0) + 1)
        if k_uni < rho_max:
            n_geo = math.ceil(math.log(rho_max / k_uni) / math.log(1.05))
            k_grid = np.concatenate([k_grid, k_uni * (rho_max / k_uni) ** (np.arange(1, n_geo + 1) / n_geo)])
        k_grid[-1] = rho_max
        vals = self.ft_quadrature(k_grid)

        # Bisect (in rho2) every interval on which the interpolant is off by
        # more than the tolerance at its midpoint or quarter points. The
        # midpoint alone is not enough: where R has an inflection inside an
        # interval the error is S-shaped and vanishes mid-interval. A
        # bisected interval's quarter points are its halves' midpoints, so
        # each check costs two new quadratures.
        rho2 = k_grid ** 2
        lo, hi = rho2[:-1], rho2[1:]
        v_lo, v_hi = vals[:-1], vals[1:]
        mid = 0.5 * (lo + hi)
        v_mid = self.ft_quadrature(np.sqrt(mid))
        new_r, new_v = [rho2], [vals]
        for _ in range(60):
            if lo.size == 0:
                break
            q1, q3 = 0.5 * (lo + mid), 0.5 * (mid + hi)
            v_q = self.ft_quadrature(np.sqrt(np.concatenate([q1, q3])))
            v_q1, v_q3 = v_q[:lo.size], v_q[lo.size:]
            err = np.maximum.reduce([
                np.abs(v_mid - 0.5 * (v_lo + v_hi)),
                np.abs(v_q1 - 0.75 * v_lo - 0.25 * v_hi),
                np.abs(v_q3 - 0.25 * v_lo - 0.75 * v_hi),
            ])
            bad = err > _TABLE_TOL
            new_r.append(mid[bad])
            new_v.append(v_mid[bad])
            lo, mid, hi = (np.concatenate([lo[bad], mid[bad]]), np.concatenate([q1[bad], q3[bad]]),
                           np.concatenate([mid[bad], hi[bad]]))
            v_lo, v_mid, v_hi = (np.concatenate([v_lo[bad], v_mid[bad]]), np.concatenate([v_q1[bad], v_q3[bad]]),
                                 np.concatenate([v_mid[bad], v_hi[bad]]))
        else:  # pragma: no cover
            raise ShearfitValueError(f"profile {self.name}: table refinement did not converge")
        rho2 = np.concatenate(new_r)
        vals = np.concatenate(new_v)
        order = np.argsort(rho2)
        rho2, vals = rho2[order], vals[order]
        rho2[0] = 0.0
        vals[0] = 1.0  # exactly, by the normalisation
        rho2.setflags(write=False)
        vals.setflags(write=False)
        self.rho_max = float(rho_max)
        self.rho2_nodes = rho2
        self.ft_nodes = vals

    # ------------------------------------------------------------------
    # public evaluation

    def ft_rho2(self, rho2):
        """R at k = sqrt(rho2), by linear interpolation in the rho2 table.

        Parameters
        ----------
        rho2 : array_like
            Squared wavenumbers k^2, any shape. Values beyond ``rho_max**2``
            give 0; (round-off) negative values give 1.

        Returns
        -------
        ndarray
            float64, same shape as ``rho2``; within 2e-6 of the exact
            transform.
        """
        x = np.asarray(rho2, dtype=float)
        if USE_KERNEL and x.size >= 64:
            out = np.empty(x.shape)
            KERNEL.table_interp(np.ascontiguousarray(x), self.rho2_nodes, self.ft_nodes, *self._buckets(), 0.0, out)
            return out
        return np.interp(x, self.rho2_nodes, self.ft_nodes, right=0.0)

    def _buckets(self):
        """The compiled lookup's index of the rho2 table (``KERNEL.table_interp``: np.interp's numbers, its
        node found from x's bit pattern instead of by bisection): per bucket of 2^shift bit patterns from
        rho2_nodes[1]'s, the last node at or below its start; about 2 buckets per node (a small index: x's are
        looked up in no order)."""
        made = self.__dict__.get("_bucket_index")
        if made is None:
            xp = self.rho2_nodes
            base = int(xp[1:2].view(np.int64)[0])
            top = int(xp[-1:].view(np.int64)[0])
            shift = max(0, int(np.ceil(np.log2(max(top - base, 1) / (2.0 * xp.size)))))
            starts = (base + (np.arange(((top - base) >> shift) + 1, dtype=np.int64) << shift)).view(np.float64)
            index = np.ascontiguousarray(np.searchsorted(xp, starts, side="right") - 1, dtype=np.int32)
            made = self._bucket_index = (index, base, shift)
        return made

    def ft(self, k):
        """R at wavenumber k (convenience wrapper of :meth:`ft_rho2`).

        Parameters
        ----------
        k : array_like
            Wavenumbers in radians per unit of the profile's scale.

        Returns
        -------
        ndarray
            float64, same shape as ``k``.
        """
        k = np.asarray(k, dtype=np.float64)
        return self.ft_rho2(k * k)

    def surface_brightness(self, r):
        """I(r), normalised so that 2 pi int_0^T I(r) r dr = 1.

        Parameters
        ----------
        r : array_like
            Radii in units of the profile's scale (the sign is ignored).

        Returns
        -------
        ndarray
            float64, same shape as ``r``; 0 at and beyond the truncation.
        """
        r = np.abs(np.asarray(r, dtype=np.float64))
        with np.errstate(under="ignore"):
            val = np.exp(-self.b * r ** (1.0 / self.sersic_n)) / (2.0 * np.pi * self._norm)
        return np.where(r < self.truncation, val, 0.0)

    def half_light_radius(self):
        """Radius enclosing half the flux of the truncated profile.

        Inverts the enclosed-flux fraction ``P(2n, b r^(1/n)) / P(2n, b T^(1/n))``
        (P the regularised lower incomplete gamma function).

        Returns
        -------
        float
            In units of the profile's scale.
        """
        n, b = self.sersic_n, self.b
        p_t = special.gammainc(2 * n, b * self.truncation ** (1 / n))
        return float((special.gammaincinv(2 * n, 0.5 * p_t) / b) ** n)

    def __repr__(self):
        return (f"RadialProfile(name={self.name!r}, truncation={self.truncation:g}, "
                f"rho_max={self.rho_max:.1f}, nodes={self.rho2_nodes.size})")

    def __reduce_ex__(self, protocol):
        # Ship the recipe, not the table: the receiving process builds (or
        # finds in its cache) the same shared instance.
        if self._kind is None:
            return super().__reduce_ex__(protocol)
        return _rebuild, (self._kind, self.sersic_n, self.truncation)


def _rebuild(kind, n, truncation):
    if kind == "exponential":
        return exponential_disk(truncation)
    if kind == "devaucouleurs":
        return de_vaucouleurs(truncation)
    return sersic(n, truncation)


def _check_truncation(truncation):
    try:
        t = float(truncation)
    except (TypeError, ValueError):
        raise ShearfitValueError(f"truncation must be a number, got {truncation!r}") from None
    if not (math.isfinite(t) and t > 0):
        raise ShearfitValueError(f"truncation must be finite and > 0, got {truncation!r}")
    return t


@functools.lru_cache(maxsize=None)
def _exponential_disk(truncation):
    prof = RadialProfile("exponential", 1.0, 1.0, truncation)
    prof._kind = "exponential"
    return prof


@functools.lru_cache(maxsize=None)
def _de_vaucouleurs(truncation):
    prof = RadialProfile("devaucouleurs", 4.0, _sersic_b(4.0), truncation)
    prof._kind = "devaucouleurs"
    return prof


@functools.lru_cache(maxsize=None)
def _sersic(n, truncation):
    prof = RadialProfile(f"sersic{n:g}", n, _sersic_b(n), truncation)
    prof._kind = "sersic"
    return prof


def exponential_disk(truncation=DEFAULT_TRUNCATION):
    """The truncated exponential disk exp(-r), r in units of its scalelength.

    Memoised: one table per truncation per process.

    Parameters
    ----------
    truncation : float, optional
        Truncation radius in scalelengths (default 4.5).

    Returns
    -------
    RadialProfile
    """
    return _exponential_disk(_check_truncation(truncation))


def de_vaucouleurs(truncation=DEFAULT_TRUNCATION):
    """The truncated de Vaucouleurs bulge exp(-b r^(1/4)), b = 7.66925.

    r is in units of the half-light radius of the *untruncated* profile (the
    paper's convention). Memoised: one table per truncation per process.

    Parameters
    ----------
    truncation : float, optional
        Truncation radius in half-light radii (default 4.5).

    Returns
    -------
    RadialProfile
    """
    return _de_vaucouleurs(_check_truncation(truncation))


def sersic(n, truncation=DEFAULT_TRUNCATION):
    """A truncated Sersic profile exp(-b_n r^(1/n)), b_n = gammaincinv(2n, 1/2).

    r is in units of the half-light radius of the untruncated profile, so
    ``sersic(1)`` is an exponential with scalelength 1 / 1.678, unlike
    :func:`exponential_disk`. Memoised per (n, truncation).

    Parameters
    ----------
    n : float
        Sersic index, 0.3 <= n <= 6.2 (GalSim's range).
    truncation : float, optional
        Truncation radius in half-light radii (default 4.5).

    Returns
    -------
    RadialProfile
    """
    try:
        nn = float(n)
    except (TypeError, ValueError):
        raise ShearfitValueError(f"Sersic index must be a number, got {n!r}") from None
    if not (_MIN_SERSIC_N <= nn <= _MAX_SERSIC_N):
        raise ShearfitValueError(f"Sersic index must be in [{_MIN_SERSIC_N}, {_MAX_SERSIC_N}], got {n!r}")
    return _sersic(nn, _check_truncation(truncation))


for _public, _cached in ((exponential_disk, _exponential_disk), (de_vaucouleurs, _de_vaucouleurs),
                         (sersic, _sersic)):
    # Expose the caches as lru_cache would on the public functions themselves.
    _public.cache_info = _cached.cache_info
    _public.cache_clear = _cached.cache_clear
del _public, _cached


class FastRadial:
    """A profile's transform on a grid uniform in ``u = sqrt(c^2 + rho^2) - c``, for the inner loop.

    ``u`` is quadratic in rho near 0, where the transform is smooth in
    rho^2, and linear at large rho, where the truncation edge makes it
    oscillate with a fixed period in rho: one uniform grid serves both, so a
    lookup is an index computation and two gathers instead of a binary
    search (about 7 times faster than ``np.interp`` on these tables). Linear
    interpolation on it is accurate to about 3e-6 of the total flux (the
    exact tables are good to 4e-7; tests check both).
    """

    C = 0.5

    #: beyond rho = U_MAX the transforms are taken as 0: the PSF is negligible at the wavenumbers
    #: (|K| > U_MAX / r) where a galaxy of any fitted size would reach it.
    U_MAX = 256.0

    #: the log tables (:meth:`log_table`) start at log2(rho^2) = LOG_START, below which every transform is
    #: flat (1 - O(rho^2), 1e-12 from its value at 0) ...
    LOG_START = -40.0
    #: ... and have at least this many points per factor of 2 in rho^2: linear interpolation on them is then
    #: within 7e-7 of the profiles' transforms (1.7e-6 at 256, 3e-6 for the u grid), tests check it
    LOG_PER_OCTAVE = 512

    def __init__(self, profiles, du=0.004, u_max=None):
        self.du = float(du)
        u_max = self.U_MAX if u_max is None else u_max
        rho_max = min(min(p.rho_max for p in profiles), u_max)
        self.profiles = list(profiles)
        self.rho_max = rho_max
        self._log_tables = {}
        n = int(np.ceil(rho_max / self.du)) + 2
        u = np.arange(n) * self.du
        rho2 = (u + self.C) ** 2 - self.C ** 2
        self.n = n
        self.tables = []
        for p in profiles:
            # float64 values: the likelihood sums thousands of modes, float32 would not do
            t = p.ft_rho2(rho2)
            t[-1] = 0.0
            s = np.append(np.diff(t), 0.0)
            self.tables.append((t, s))
        # for the compiled kernel: value and slope of every profile side by side, in float32, so that
        # one cache line serves one lookup (float32 rounding, 6e-8, is far below the 3e-6 interpolation error)
        self.packed32 = np.ascontiguousarray(
            np.stack([a for t_s in self.tables for a in t_s], axis=1).astype(np.float32))

    def index(self, rho2):
        """Grid index and fraction for rho^2 (any shape)."""
        u = np.sqrt(rho2 + self.C * self.C, dtype=np.float32)
        u -= np.float32(self.C)
        u *= np.float32(1.0 / self.du)
        np.minimum(u, np.float32(self.n - 1), out=u)
        i = u.astype(np.int32)
        u -= i
        return i, u

    def lookup(self, which, i, frac):
        t, s = self.tables[which]
        out = np.take(s, i)
        out *= frac
        out += np.take(t, i)
        return out

    def __call__(self, which, rho2):
        i, f = self.index(rho2)
        return self.lookup(which, i, f)

    def log_table(self, bins_per_octave):
        """The transforms on a grid uniform in log2(rho^2), for the binned model sums (cached).

        The grid has ``P = bins_per_octave * M`` points per factor of 2 (``M`` the smallest giving at least
        :attr:`LOG_PER_OCTAVE`), so that the bins of log K^T C K (``bins_per_octave`` per octave) of a
        model of any size fall every ``M`` points, all at one fraction of a step. Point ``i`` is at
        log2(rho^2) = ``LOG_START + i / P``; beyond ``rho_max`` the transforms are 0, as on the u grid.
        Each profile's table is laid out by phase: row ``s`` (0 .. M) holds points s, s + M, s + 2M, ...,
        so a model's bins read two contiguous rows.

        Returns a :class:`LogTable`.
        """
        nb = int(bins_per_octave)
        tab = self._log_tables.get(nb)
        if tab is None:
            m = max(1, -(-self.LOG_PER_OCTAVE // nb))
            per = nb * m
            n = int(np.ceil((2 * np.log2(self.rho_max) - self.LOG_START) * per)) + 1
            rho2 = 2.0 ** (self.LOG_START + np.arange(n) / per)
            n_col = -(-n // m) + 2
            rows = []
            for p in self.profiles:
                g = np.zeros((n_col + 1) * m)
                g[:n] = np.where(rho2 <= self.rho_max ** 2, p.ft_rho2(rho2), 0.0)
                rows.append(np.ascontiguousarray(np.stack([g[s:s + n_col * m:m] for s in range(m + 1)])))
            tab = LogTable(rows=rows, m=m, n_col=n_col, start=self.LOG_START, per_octave=float(per),
                           low=[float(r[0, 0]) for r in rows], zero=[float(t[0]) for t, _ in self.tables])
            self._log_tables[nb] = tab
        return tab


@dataclass(frozen=True)
class LogTable:
    """:meth:`FastRadial.log_table`: per profile, the table's ``m + 1`` phase rows of ``n_col`` points,
    its value below the grid (``low``) and at rho = 0 (``zero``)."""

    rows: list
    m: int
    n_col: int
    start: float
    per_octave: float
    low: list
    zero: list


@functools.lru_cache(maxsize=8)
def fast_pair(truncation=DEFAULT_TRUNCATION):
    """The disk and bulge transforms of the paper's models on one fast grid."""
    return FastRadial([exponential_disk(truncation), de_vaucouleurs(truncation)])
