"""Size marginalisation, ellipticity sampling and the estimator (sec. 3.2-3.5).

:class:`EllipticityLikelihood` turns an object's joint Fourier modes into the
likelihood of ellipticity alone: at each (e1, e2) it evaluates the models on
a grid of scalelengths, each already marginalised over bulge fraction,
position and flux (:mod:`shearfit.engine.likelihood`), fits a cubic spline to
log L(r) and integrates it against the size prior. The scalelength grid
follows the object: it is centred, per ellipticity, on the size that keeps
the area of the best round model (the semi-major axis grows as 1/sqrt(q)),
and its width comes from a first look at the round model's size posterior.

:func:`adaptive_samples` is the paper's adaptive grid (0.16, halved around
the maximum until 30 samples lie above 5 % of it or the step is 0.02);
:func:`two_pass_samples` first finds the maximum, then maps its surroundings.
:func:`estimate` forms the likelihood mean over samples whose posterior
exceeds 1 % of its maximum, the 1D variance and the weight of eq. (weight).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields

import numpy as np

from . import priors
from ..config import FitConfig
from .kernel import KERNEL, USE_KERNEL
from .likelihood import (Marginal, bins_context, bins_context_rest, column_buffer, grow_column_buffer, linear_vectors,
                         flux_position_marginal, marginal_context, mode_bins, mode_bins_versions, model_sums,
                         node_matrices, packed_bins, polar_args, polar_grid, polar_pays, polar_setting,
                         seed_polar_grid, shares_bins_geometry, versions_channels, versions_polar_grid,
                         versions_polar_subset)

__all__ = ["EllipticityLikelihood", "VersionLikelihoods", "Samples", "adaptive_samples", "two_pass_samples",
           "replay_samples", "replay_versions", "adaptive_versions",
           "estimate", "lensing_weight"]


def lensing_weight(e_var, cfg: FitConfig):
    """Inverse-variance weight, eq. (weight).

    ``w = [sigma_e^2 e_max^2 / (e_max^2 - 2 sigma_e^2) + sigma_pop^2]^-1``; zero
    where ``2 sigma_e^2 >= e_max^2`` (a likelihood as broad as a uniform one
    within e_max carries no shape information).
    """
    e_var = np.asarray(e_var, float)
    em2 = cfg.weight_e_max ** 2
    denom = em2 - 2 * e_var
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1.0 / (e_var * em2 / denom + cfg.sigma_pop ** 2)
    return np.where((denom > 0) & np.isfinite(e_var), w, 0.0)


def e_key(e1, e2):
    """Hashable keys of ellipticities (to 1e-9), for per-sample records."""
    return list(zip(np.rint(np.asarray(e1) * 1e9).astype(np.int64).tolist(),
                    np.rint(np.asarray(e2) * 1e9).astype(np.int64).tolist()))


def _pack(k1, k2):
    """:func:`e_key`'s two integers (|k| <= 2^31 for |e| <= 2) as one int64 each, in the same order as the pairs."""
    return ((k1 + (1 << 31)) << 32) + (k2 + (1 << 31))


def _packed_keys(e1, e2):
    """:func:`_pack` of the ellipticities' :func:`e_key` integers."""
    return _pack(np.rint(np.asarray(e1, float) * 1e9).astype(np.int64),
                 np.rint(np.asarray(e2, float) * 1e9).astype(np.int64))


def log_population_weights(cfg: FitConfig):
    """log(1 - f_B) and log f_B: the disk and bulge populations' weights (sec. 3.1)."""
    fB = cfg.bulge_population_fraction
    return np.log(max(1 - fB, 1e-300)), np.log(max(fB, 1e-300))


def _logsumexp_rows(a):
    m = np.max(a, axis=1)
    m = np.where(np.isfinite(m), m, 0.0)
    return m + np.log(np.sum(np.exp(a - m[:, None]), axis=1))


class SizeCentres(Mapping):
    """The size centre used at each ellipticity, keyed by :func:`e_key`: added as arrays (:meth:`add`), made a
    dict at the first look (only metacal's replays look: a plain fit's hundreds of keys were 5 % of its sampler's
    own time)."""

    def __init__(self):
        self._d = {}
        self._pending = []
        self._sorted = None   # (packed keys sorted, their centres): lookup's, made at its first call after an add

    def add(self, e1, e2, rc):
        self._pending.append((np.array(e1, float), np.array(e2, float), np.array(rc, float)))
        self._sorted = None

    def _dict(self):
        if self._pending:
            for e1, e2, rc in self._pending:
                self._d.update(zip(e_key(e1, e2), rc.tolist()))
            self._pending = []
        return self._d

    def lookup(self, e1, e2):
        """The centres at (e1, e2) (arrays), NaN where none was added: ``[self.get(k, nan) for k in e_key(e1,
        e2)]`` as one search of the sorted keys (a replay's chunk looks up a hundred at a time)."""
        if self._sorted is None:
            # the dict's entries, then the pending arrays in the order added (a key added again: its last centre)
            k = np.array(list(self._d.keys()), np.int64).reshape(-1, 2)
            parts = [(_pack(k[:, 0], k[:, 1]), np.array(list(self._d.values()), float))]
            parts += [(_packed_keys(a, b), rc) for a, b, rc in self._pending]
            packed = np.concatenate([p[0] for p in parts])
            vals = np.concatenate([p[1] for p in parts])
            order = np.argsort(packed, kind="stable")
            packed, vals = packed[order], vals[order]
            last = np.append(packed[1:] != packed[:-1], True)
            self._sorted = (packed[last], vals[last])
        keys, vals = self._sorted
        q = _packed_keys(e1, e2)
        if keys.size == 0:
            return np.full(q.shape, np.nan)
        i = np.minimum(np.searchsorted(keys, q), keys.size - 1)
        return np.where(keys[i] == q, vals[i], np.nan)

    def __getitem__(self, key):
        return self._dict()[key]

    def __iter__(self):
        return iter(self._dict())

    def __len__(self):
        return len(self._dict())

    def get(self, key, default=None):
        return self._dict().get(key, default)

    def keys(self):
        return self._dict().keys()

    def values(self):
        return self._dict().values()

    def items(self):
        return self._dict().items()

    def __eq__(self, other):
        return self._dict() == (other._dict() if isinstance(other, SizeCentres) else other)

    __hash__ = None


@dataclass
class EPoint:
    """Per-ellipticity results, arrays over the sampled points."""

    logl_disk: np.ndarray
    logl_bulge: np.ndarray
    mean_r: np.ndarray
    mean_b: np.ndarray
    mean_flux: np.ndarray


#: The largest growth of the predicted best size over the round model's (:meth:`EllipticityLikelihood.centre`).
CENTRE_GROWTH_MAX = 2.0


class EllipticityLikelihood:
    """log L(e1, e2) of one object, marginalised over everything else."""

    N_FINE = 49   # points of the fine ln r grid the spline is integrated on
    _SEG_U = np.linspace(0.0, 1.0, 9)   # u = (r / r_min)^2 of the segment from r = 0 to the first node
    _SEG_HALF_LOG_U = 0.5 * np.log(np.maximum(_SEG_U, 1e-300))   # ln(r / r_min) there

    def __init__(self, jm, cfg: FitConfig, mag, fast, size_grid_x, r_center, chunk=256, locate_widths=None,
                 locate_from=None):
        self.jm = jm
        self.cfg = cfg
        self.mag = mag
        self.fast = fast
        self.x = np.asarray(size_grid_x, float)   # r = r_peak(e) * exp(x)
        self.r_center = float(r_center)
        # half-widths (ln r) of the passes that locate, per ellipticity, the peak in ln r (None: not needed)
        self.locate_widths = locate_widths
        # the round size the locating passes start from, carried to each e as r_center is (None: r_center)
        self.locate_ratio = 1.0 if locate_from is None else float(locate_from) / self.r_center
        # located size peaks so far, as ln(peak / centre(e)), for neighbours to reuse
        self._loc_e = np.zeros((0, 2))
        self._loc_x = np.zeros(0)
        self._peak_max = -np.inf   # the highest last-pass peak so far (see _located_centres)
        self._lin = None
        # ellipticities evaluated together (their bins made in one call, their models' sums in one): 256 took 3 %
        # less time than 64 on benchmarks/speed.py's galaxies, the same estimates to the bit (benchmarks/README.md)
        self.chunk = chunk
        # r = 0, the point source: one model shared by every ellipticity; the size integral runs
        # from it to the first node (sec. 3.2: "the set of r values included a point source")
        s0 = model_sums(jm, [0.0], [0.0], [0.0], fast, cfg.bulge_size_ratio, lin=self._lin_numpy(),
                          bins_per_octave=cfg.mode_bins_per_octave)
        self.zero = flux_position_marginal(s0, cfg, jm.pixel_scale)
        # sum over the modes of |unit-flux point source|^2 / sigma^2: a flux F's SNR were it unresolved is
        # F sqrt(point_ff)
        self.point_ff = float(s0.ff[0])
        self.n_models = 1
        self.chi2_star = None
        self.best_chi2_gal = np.inf
        self.best_snr = 0.0
        # the size centre used at each ellipticity, keyed by ``e_key``: a fit of another version of the
        # same object (metacal's) replays them instead of locating its own (``fixed_centres``)
        self.centres = SizeCentres()
        self.fixed_centres = None

    @property
    def lin(self):
        """The modes' six linear vectors (:func:`linear_vectors`), made at first use."""
        if self._lin is None:
            self._lin = linear_vectors(self.jm)
        return self._lin

    def _lin_numpy(self):
        """What model_sums takes as ``lin``: only the numpy lines read it (the compiled sums make their own
        weights), so the kernel's fits do not make it (a (6, modes) stack a version: 4 % of metacal's replays'
        setup)."""
        return None if USE_KERNEL else self.lin

    @property
    def ln_a(self):
        """ln of the size prior's scale a at this object's magnitude (made once)."""
        v = self.__dict__.get("_ln_a")
        if v is None:
            v = self._ln_a = math.log(float(priors.size_prior_scale(self.mag, self.cfg)))
        return v

    def centre(self, e1, e2):
        """Predicted best scalelength at ellipticity e from the round model's.

        The semi-major axis of the best-fitting model grows with e. Keeping the
        area (1/sqrt(q)) overshoots by up to 55 % at |e| = 0.74, keeping the
        second-moment trace undershoots by 15 %; q^(-1/3) is within +-15 %
        of the best size over the cases measured (noise-free GalSim galaxies,
        r = 0.12-1 arcsec, |e| = 0.47-0.74). ``locate_widths`` make up the rest.
        Above |e| 0.78 the growth is held at CENTRE_GROWTH_MAX: the best size
        levels off there (1.5-1.7 times the round disk's at |e| 0.8-0.95 for
        r = 0.1-0.4", 2.7-2.9 for pure bulges), and q^(-1/3) (3.4 at 0.95) put
        it beyond the passes' reach, 9-56 nats low (session 74).
        """
        e = np.hypot(e1, e2)
        q = (1 - e) / (1 + e)
        return self.r_center * np.minimum(q ** (-1.0 / 3.0), CENTRE_GROWTH_MAX)

    def replayed_centres(self, e1, e2, keys=None):
        """The size centres of ``fixed_centres`` at (e1, e2) (``keys``: their :func:`e_key`, made here if None). An
        ellipticity the replayed fit never sampled (a version's own ellipticity grid, :func:`adaptive_versions`) gets
        its nearest sampled neighbour's ratio to the predicted centre, as a fit reuses a located neighbour's
        (``_located_centres``)."""
        fc = self.fixed_centres
        rc = (fc.lookup(e1, e2) if isinstance(fc, SizeCentres) else
              np.array([fc.get(k, np.nan) for k in (e_key(e1, e2) if keys is None else keys)], float))
        miss = np.isnan(rc)
        if np.any(miss):
            ke = np.array(list(fc.keys()), float) * 1e-9
            kr = np.array(list(fc.values()), float)
            d2 = (e1[miss, None] - ke[None, :, 0]) ** 2 + (e2[miss, None] - ke[None, :, 1]) ** 2
            nn = np.argmin(d2, axis=1)
            rc[miss] = self.centre(e1[miss], e2[miss]) * kr[nn] / self.centre(ke[nn, 0], ke[nn, 1])
        return rc

    def _located_centres(self, e1, e2, rc, bins=None):
        """Size peaks at each e, located by the passes of ``locate_widths``.

        A sample within ``FitConfig.size_reuse_distance`` of one already
        located starts from that neighbour's offset from the predicted centre
        (the peak moves smoothly with e) and needs only the last, narrowest
        pass; the others run every pass.

        Returns the centres, which samples are far in the tail, and their
        crude values (an EPoint over them in order, or None): a sample that runs every
        pass and whose last pass peaks more than ``FitConfig.tail_skip`` below
        the highest last-pass peak so far gets that pass's size integral
        (``_locate``, ``detail``) instead of its size nodes'. It is located by
        every pass, so that the samples that reuse its size peak are the same
        with and without the shortcut. (The first pass's peak, which decided
        this before session 74, is a parabola through nodes 0.3 apart in ln r:
        where the size posterior is narrower than that, at high SNR, it fell
        tens of nats short of the peak, and samples at the posterior's peak
        were taken for the tail.)
        """
        x = np.zeros(e1.size)
        near = np.zeros(e1.size, bool)
        if self._loc_x.size and self.cfg.size_reuse_distance > 0:
            d2 = (e1[:, None] - self._loc_e[None, :, 0]) ** 2 + (e2[:, None] - self._loc_e[None, :, 1]) ** 2
            nn = np.argmin(d2, axis=1)
            near = d2[np.arange(e1.size), nn] <= self.cfg.size_reuse_distance ** 2
            x[near] = self._loc_x[nn[near]]
        r = rc * np.where(near, np.exp(x), self.locate_ratio)
        tail = np.zeros(e1.size, bool)
        tail_point = None
        widths = list(self.locate_widths)
        for k, width in enumerate(widths):
            last = k == len(widths) - 1
            sel = np.ones(e1.size, bool) if last else ~near
            if not np.any(sel):
                continue
            if last and self.cfg.tail_skip > 0:
                r[sel], peak, point = self._locate(e1[sel], e2[sel], r[sel], width, bins, np.nonzero(sel)[0],
                                                   detail=True)
                self._peak_max = max(self._peak_max, float(np.max(peak)))
                # only samples that ran every pass (a reused neighbour's peak is not checked)
                far = (peak < self._peak_max - self.cfg.tail_skip) & ~near[sel]
                if np.any(far):
                    tail[np.nonzero(sel)[0][far]] = True
                    tail_point = EPoint(*[getattr(point, f)[far] for f in EPoint.__dataclass_fields__])
                continue
            r[sel] = self._locate(e1[sel], e2[sel], r[sel], width, bins, np.nonzero(sel)[0])
        self._loc_e = np.concatenate([self._loc_e, np.stack([e1, e2], axis=1)])
        self._loc_x = np.concatenate([self._loc_x, np.log(r / rc)])
        return r, tail, tail_point

    def _sums(self, e1, e2, r, bins, index):
        """Model sums of (e1, e2, r); with ``bins`` (the chunk's), ``index`` is each model's e in them."""
        return model_sums(self.jm, e1, e2, r, self.fast, self.cfg.bulge_size_ratio, lin=self._lin_numpy(),
                          bins_per_octave=self.cfg.mode_bins_per_octave, bins=bins, bin_index=index)

    def _locate(self, e1, e2, rc, half_width, bins=None, index=None, detail=False, use_kernel=True):
        """Peak of the size posterior at each e: 5 nodes and, for each population (disk, pure bulge), a parabola
        through its best three; the peak is that of the population whose parabola peaks higher.

        The two populations' size peaks lie apart (a pure bulge's 1.5-2.3 times a disk's of the same image), and
        a parabola through the mixture's best three nodes could straddle both and land on the one that does not
        count: a 0.2" pure bulge at |e| 0.5, SNR 200, had samples at its posterior's peak 6-7 nats low with the
        passes started between the two (session 74).

        With ``detail``: also that parabola's peak value (log L + log p(r) r of the population, with its weight)
        and an EPoint of the crude size integral over the 5 nodes (the populations mixed).

        With the bins, the compiled kernel (``KERNEL.locate_pass``: binned sums, marginalisation, prior, parabolas
        and crude integral in one call) does what the lines below do, to rounding (its exp and log are the C
        library's, not numpy's)."""
        cfg = self.cfg
        xs = _locate_nodes(float(half_width))
        marg = marginal_context(cfg, self.jm.pixel_scale) if use_kernel and bins is not None else None
        if marg is not None:
            return self._locate_kernel(e1, e2, rc, float(half_width), bins, index, detail, marg)
        R = rc[:, None] * np.exp(xs)[None, :]
        n = xs.size
        sums = self._sums(np.repeat(e1, n), np.repeat(e2, n), R.ravel(), bins,
                          None if index is None else np.repeat(index, n))
        self.n_models += R.size
        mg = flux_position_marginal(sums, cfg, self.jm.pixel_scale)
        ld0, lb0 = log_population_weights(cfg)
        shift = _prior_axis_shift(e1, e2, cfg)
        lpr = priors.log_size_prior_per_lnr(np.log(R) + (0.0 if shift is None else shift[:, None]), self.mag, cfg,
                                            ln_a=self.ln_a)
        h = xs[1] - xs[0]
        peak, xpk = self._parabola_peaks(mg, ld0, lb0, lpr, xs, R.shape)
        r_peak = rc * np.exp(xpk)
        if not detail:
            return r_peak
        # a crude size integral over the 5 nodes (trapezoid in ln r) with posterior means over them, for samples
        # far below the others (see _located_centres)
        y = np.logaddexp(ld0 + mg.logl_disk, lb0 + mg.logl_bulge).reshape(R.shape) + lpr
        y = np.where(np.isfinite(y), y, -1e300)
        ld = np.where(np.isfinite(mg.logl_disk), mg.logl_disk, -1e300).reshape(R.shape) + lpr + np.log(h)
        lb = np.where(np.isfinite(mg.logl_bulge), mg.logl_bulge, -1e300).reshape(R.shape) + lpr + np.log(h)
        w = np.exp(y - np.max(y, axis=1, keepdims=True))
        w /= np.sum(w, axis=1, keepdims=True)
        point = EPoint(logl_disk=_logsumexp_rows(ld), logl_bulge=_logsumexp_rows(lb),
                       mean_r=np.sum(w * R, axis=1),
                       mean_b=np.sum(w * np.nan_to_num(mg.mean_b_disk.reshape(R.shape)), axis=1),
                       mean_flux=np.sum(w * np.nan_to_num(mg.mean_flux_disk.reshape(R.shape)), axis=1))
        return r_peak, peak, point

    def _locate_kernel(self, e1, e2, rc, half_width, bins, index, detail, marg):
        cfg = self.cfg
        ne = e1.size
        xs = _locate_nodes(half_width)
        self.n_models += ne * xs.size
        shift = _prior_axis_shift(e1, e2, cfg)
        r_peak, top = np.empty(ne), np.empty(ne)
        point = np.empty((5, ne)) if detail else np.empty(0)
        _, _, prior, logmix = self._node_constants()
        KERNEL.locate_pass(bins_context(self.jm, bins, self.fast, cfg.bulge_size_ratio), marg,
                           np.ascontiguousarray(index, dtype=np.int64), np.ascontiguousarray(rc, dtype=float),
                           _locate_exp(half_width), xs, prior,
                           b"" if shift is None else np.ascontiguousarray(shift, dtype=float), logmix,
                           int(bool(detail)), r_peak, top, point)
        if not detail:
            return r_peak
        return r_peak, top, EPoint(logl_disk=point[0], logl_bulge=point[1], mean_r=point[2], mean_b=point[3],
                                   mean_flux=point[4])

    @staticmethod
    def _parabola_peaks(mg, ld0, lb0, lpr, xs, shape, use_kernel=True):
        """The size peaks of :meth:`_locate`: per sample (a row of ``shape``, its nodes ``xs``), for each
        population a parabola through its best three nodes (log L with the population's weight, plus ``lpr``);
        (the higher parabola's peak value, its offset in ln r). The compiled kernel (``locate_parabola``) makes the
        numpy lines' numbers to the bit."""
        n = xs.size
        if use_kernel and USE_KERNEL and 3 <= n <= 64:
            top, xpk = np.empty(shape[0]), np.empty(shape[0])
            c = np.ascontiguousarray
            KERNEL.locate_parabola(c(mg.logl_disk, dtype=float), c(mg.logl_bulge, dtype=float), c(lpr, dtype=float),
                                   np.array([ld0, lb0], float), c(xs, dtype=float), top, xpk)
            return top, xpk
        h = xs[1] - xs[0]
        rows = np.arange(shape[0])
        best = None
        for w0, logl in ((ld0, mg.logl_disk), (lb0, mg.logl_bulge)):
            yp_ = np.where(np.isfinite(logl), w0 + logl, -1e300).reshape(shape) + lpr
            # (np.minimum/np.maximum: np.clip's numbers, at a fifth of its overhead on arrays this small)
            k = np.minimum(np.maximum(np.argmax(yp_, axis=1), 1), n - 2)
            ym, y0, yp = yp_[rows, k - 1], yp_[rows, k], yp_[rows, k + 1]
            den = ym - 2 * y0 + yp
            with np.errstate(invalid="ignore", divide="ignore"):
                d = np.where(den < 0, 0.5 * h * (ym - yp) / den, 0.0)
            d = np.minimum(np.maximum(np.where(d == d, d, 0.0), -h), h)   # NaN -> 0, then within +-h
            # the parabola's value at its peak
            top = np.maximum(y0, y0 + 0.5 * (yp - ym) / h * d + 0.5 * den / h ** 2 * d * d)
            if best is None:
                best = (top, xs[k] + d)
            else:
                other = top > best[0]
                best = (np.where(other, top, best[0]), np.where(other, xs[k] + d, best[1]))
        return best

    def __call__(self, e1, e2) -> EPoint:
        e1 = np.atleast_1d(np.asarray(e1, float))
        e2 = np.atleast_1d(np.asarray(e2, float))
        out = [self._chunk(e1[i:i + self.chunk], e2[i:i + self.chunk]) for i in range(0, e1.size, self.chunk)]
        return EPoint(*[np.concatenate([getattr(o, f) for o in out]) for f in
                        ("logl_disk", "logl_bulge", "mean_r", "mean_b", "mean_flux")])

    def _chunk(self, e1, e2, use_kernel=True) -> EPoint:
        cfg = self.cfg
        ne = e1.size
        fused = self._chunk_args() if use_kernel else None
        if fused is not None:
            return self._chunk_kernel(e1, e2, fused)
        # the chunk's modes binned once per ellipticity, for the size-locating passes and the nodes
        bins = mode_bins(self.jm, e1, e2, cfg.mode_bins_per_octave, polar=polar_setting(cfg), reuse=True) if (
            USE_KERNEL and cfg.mode_bins_per_octave > 0) else None
        tail, tail_point = np.zeros(ne, bool), None
        if self.fixed_centres is not None:
            rc = self.replayed_centres(e1, e2)
        else:
            rc = self.centre(e1, e2)
            if self.locate_widths is not None:
                rc, tail, tail_point = self._located_centres(e1, e2, rc, bins)
        self.centres.add(e1, e2, rc)
        if np.any(tail):
            # the size nodes of the samples far in the tail are not evaluated: their crude values stand
            full = np.nonzero(~tail)[0]
            out = EPoint(*[np.empty(ne) for _ in EPoint.__dataclass_fields__])
            for f in EPoint.__dataclass_fields__:
                getattr(out, f)[tail] = getattr(tail_point, f)
            if full.size:
                rest = self._nodes(e1[full], e2[full], rc[full], bins, full)
                for f in EPoint.__dataclass_fields__:
                    getattr(out, f)[full] = getattr(rest, f)
            return out
        return self._nodes(e1, e2, rc, bins, np.arange(ne))

    def _chunk_args(self):
        """What KERNEL.sample_chunk takes of the object alone (made once), or None where the lines of
        :meth:`_chunk` run instead: no compiled kernel or binning, replayed size centres, or size peaks reused
        from neighbours (``size_reuse_distance``)."""
        v = self.__dict__.get("_chunk_consts", False)
        if v is not False:
            return v
        cfg = self.cfg
        v = None
        marg = marginal_context(cfg, self.jm.pixel_scale) if USE_KERNEL and cfg.mode_bins_per_octave > 0 else None
        if (marg is not None and self.fixed_centres is None and self.x.size <= 512
                and (self.locate_widths is None or cfg.size_reuse_distance <= 0)):
            nb = int(cfg.mode_bins_per_octave)
            polar = polar_setting(cfg)
            b3, c8 = packed_bins(self.jm)[:2]
            pargs = (polar_args(polar_grid(self.jm, nb, polar[0]), polar)
                          if polar is not None and polar_pays(self.jm, nb, polar[0]) else None)
            widths = [] if self.locate_widths is None else [float(w) for w in self.locate_widths]
            lxs = np.array([_locate_nodes(w) for w in widths], float).reshape(-1, 5)
            lex = np.array([_locate_exp(w) for w in widths], float).reshape(-1, 5)
            xf, interp_w, spl = self._fine_grid()
            expx, l0, prior, logmix = self._node_constants()
            # bins_context's items after the bins themselves (bins_per_octave on), without a chunk's bins
            rest = (nb,) + bins_context_rest(self.jm, self.fast, nb, cfg.bulge_size_ratio)
            v = (rest, marg, (b3, c8, nb, pargs), lxs, lex, self.locate_ratio, float(cfg.tail_skip), expx,
                 float(self.x[0]), xf, np.ascontiguousarray(interp_w, dtype=float),
                 np.ascontiguousarray(spl, dtype=float), self._SEG_U, self._SEG_HALF_LOG_U, l0, logmix, prior)
        self._chunk_consts = v
        return v

    def _chunk_kernel(self, e1, e2, fused):
        """:meth:`_chunk` in one compiled call (``KERNEL.sample_chunk``: the bins, the size-locating passes, the
        tail's shortcut and the size nodes), the same numbers as its lines (tests/test_kernel.py)."""
        ne = e1.size
        shift = _prior_axis_shift(e1, e2, self.cfg)
        out = np.empty((5, ne))
        rc = self.centre(e1, e2)
        rc_out = np.empty(ne)
        state = self._state()
        need = KERNEL.sample_chunk(self._kernel_args(fused), np.ascontiguousarray(e1, dtype=float),
                                   np.ascontiguousarray(e2, dtype=float), rc,
                                   b"" if shift is None else np.ascontiguousarray(shift, dtype=float), out, rc_out,
                                   state)
        if need:
            grow_column_buffer(need)
        self._set_state(state)
        self.centres.add(e1, e2, rc_out)
        return EPoint(logl_disk=out[0], logl_bulge=out[1], mean_r=out[2], mean_b=out[3], mean_flux=out[4])

    @staticmethod
    def _kernel_args(fused):
        """:meth:`_chunk_args` as KERNEL.sample_chunk and KERNEL.adaptive_samples take it: make_bins' arguments
        with this thread's column buffer (:func:`shearfit.engine.likelihood.column_buffer`)."""
        return fused[:2] + (fused[2] + (column_buffer(),),) + fused[3:]

    def _state(self):
        """What the compiled chunks read and update of the fit so far: the highest last-pass peak, the best
        single-component chi^2 and its SNR, and a count of the models evaluated (0)."""
        return np.array([self._peak_max, self.best_chi2_gal, self.best_snr, 0.0])

    def _set_state(self, state):
        self._peak_max = float(state[0])
        self.best_chi2_gal, self.best_snr = float(state[1]), float(state[2])
        self.n_models += int(state[3])

    def _nodes(self, e1, e2, rc, bins, index, use_kernel=True):
        """The size nodes of the samples (their bins at ``index``), marginalised, and the size integral. With the
        bins, the compiled kernel (``KERNEL.size_nodes``: binned sums, marginalisation and size integral in one
        call) does what the lines below do, to rounding (its exp and log are the C library's, not numpy's)."""
        if use_kernel and bins is not None and self.x.size <= 512:
            marg = marginal_context(self.cfg, self.jm.pixel_scale)
            if marg is not None:
                return self._nodes_kernel(e1, e2, rc, bins, index, marg)
        R = rc[:, None] * np.exp(self.x)[None, :]
        nr = self.x.size
        sums = self._sums(np.repeat(e1, nr), np.repeat(e2, nr), R.ravel(), bins, np.repeat(index, nr))
        return self._size_integral(e1, e2, R, flux_position_marginal(sums, self.cfg, self.jm.pixel_scale))

    def _nodes_kernel(self, e1, e2, rc, bins, index, marg):
        cfg = self.cfg
        ne = e1.size
        self.n_models += ne * self.x.size
        xf, interp_w, spl = self._fine_grid()
        shift = _prior_axis_shift(e1, e2, cfg)
        out = np.empty((5, ne))
        best = np.array([self.best_chi2_gal, self.best_snr])
        expx, l0, prior, logmix = self._node_constants()
        KERNEL.size_nodes(bins_context(self.jm, bins, self.fast, cfg.bulge_size_ratio), marg,
                          np.ascontiguousarray(index, dtype=np.int64), np.ascontiguousarray(rc, dtype=float),
                          expx, float(self.x[0]), xf, interp_w, spl, self._SEG_U, self._SEG_HALF_LOG_U,
                          l0, logmix, prior,
                          b"" if shift is None else np.ascontiguousarray(shift, dtype=float), out, best)
        self.best_chi2_gal, self.best_snr = float(best[0]), float(best[1])
        return EPoint(logl_disk=out[0], logl_bulge=out[1], mean_r=out[2], mean_b=out[3], mean_flux=out[4])

    def _node_constants(self):
        """What KERNEL.size_nodes and KERNEL.locate_pass take of the object alone (made once): exp of the size
        nodes' offsets; log L of the point source (r = 0), disk and bulge; the size prior per ln r as
        ln[alpha / Gamma(2 / alpha)], ln a, alpha; the populations' log weights (disk, bulge)."""
        v = getattr(self, "_node_consts", None)
        if v is None:
            alpha = float(self.cfg.size_alpha)
            v = self._node_consts = (np.exp(self.x),
                                     np.array([float(self.zero.logl_disk[0]), float(self.zero.logl_bulge[0])]),
                                     np.array([math.log(alpha / math.gamma(2.0 / alpha)), self.ln_a, alpha]),
                                     np.array(log_population_weights(self.cfg)))
        return v

    def _size_integral(self, e1, e2, R, mg):
        """The size integral of the samples from their size nodes ``R`` (n_e, n_nodes) marginalised (``mg``,
        the nodes row after row)."""
        cfg = self.cfg
        ne = e1.size
        nr = self.x.size
        self.n_models += ne * nr
        # best single-component fit among galaxies (r > 0), for the star/galaxy test
        chi2 = np.minimum(mg.chi2_disk, mg.chi2_bulge)
        i = int(np.argmin(chi2))
        if chi2[i] < self.best_chi2_gal:
            self.best_chi2_gal = float(chi2[i])
            self.best_snr = float(max(mg.snr_disk[i], mg.snr_bulge[i]))
        shape = (ne, nr)
        return self._size_marginal(R, mg.logl_disk.reshape(shape), mg.logl_bulge.reshape(shape),
                                   mg.mean_flux_disk.reshape(shape), mg.mean_flux_bulge.reshape(shape),
                                   mg.mean_b_disk.reshape(shape), prior_shift=_prior_axis_shift(e1, e2, cfg))

    def _fine_grid(self):
        """The fine ln r grid of the size integral, the node->grid interpolation matrix and the spline
        matrix (made once per object: the nodes x are fixed)."""
        if getattr(self, "_fine", None) is None:
            xf = np.linspace(self.x[0], self.x[-1], self.N_FINE)
            self._fine = (xf,) + node_matrices(self.x, xf)
        return self._fine   # xf, (n_nodes, n_fine), (n_nodes, n_fine)

    def _size_marginal(self, rnodes, ld, lb, fd, fb, bd, use_kernel=True, prior_shift=None):
        """Spline log L over ln r and integrate against the size prior (dr = r d ln r).

        The disk (index 0) and bulge (1) populations are done together, stacked on a first axis. The
        compiled kernel (``KERNEL.size_marginal``) does the same arithmetic as the numpy path here.
        """
        cfg = self.cfg
        x = self.x
        xf, interp_w, spl = self._fine_grid()
        lnrf = (np.log(rnodes[:, :1]) - x[0]) + xf[None, :]
        rf = np.exp(lnrf)
        # the size prior at the scalelength of size_prior_axis (ln r + prior_shift per sample; 0: the semi-major)
        sh = 0.0 if prior_shift is None else prior_shift[:, None]
        logprior = priors.log_size_prior_per_lnr(lnrf + sh, self.mag, cfg, ln_a=self.ln_a)
        # from r = 0 to the first node (r = r_min sqrt(u)): p(r) dr = [p(r)/r] (r_min^2 / 2) du, smooth
        # down to r = 0, where p(r) ~ r; log L there is linear in r^2 between the point source and the node
        u = self._SEG_U
        lnr0 = np.maximum(lnrf[:, :1] + self._SEG_HALF_LOG_U[None, :], np.log(1e-12))
        lsegprior = priors.log_size_prior_per_lnr(lnr0 + sh, self.mag, cfg, ln_a=self.ln_a) - 2 * lnr0
        l0 = np.array([float(self.zero.logl_disk[0]), float(self.zero.logl_bulge[0])])
        logmix = np.array(log_population_weights(cfg))
        if USE_KERNEL and use_kernel and KERNEL is not None and x.size <= 512:
            out = np.empty((5, rf.shape[0]))
            c = np.ascontiguousarray
            KERNEL.size_marginal(c(ld, dtype=float), c(lb, dtype=float), c(fd, dtype=float), c(fb, dtype=float),
                                   c(bd, dtype=float), c(logprior), c(lsegprior), spl,
                                   c(interp_w), c(xf), u, c(rf), l0, logmix, out)
            return EPoint(logl_disk=out[0], logl_bulge=out[1], mean_r=out[2], mean_b=out[3], mean_flux=out[4])
        logl = np.stack([ld, lb])                                  # (2, n_e, n_nodes)
        finite = np.isfinite(logl)
        rowmax = np.max(np.where(finite, logl, -np.inf), axis=2, keepdims=True)
        good = np.isfinite(rowmax[..., 0])
        floor = np.where(good[..., None], rowmax - 40.0, 0.0)
        lv = np.where(finite, np.maximum(logl, floor), floor)
        vf = lv @ spl + logprior[None]
        l0 = np.where(np.isfinite(l0), l0, -np.inf)[:, None, None]
        with np.errstate(invalid="ignore"):
            lseg = np.where(np.isfinite(l0), (1 - u) * np.maximum(l0, -1e300) + u * lv[..., :1],
                            lv[..., :1] - 1e3 * (1 - u))
        lseg = lseg + lsegprior[None]
        m = np.maximum(np.max(vf, axis=2, keepdims=True), np.max(lseg, axis=2, keepdims=True))
        w = np.exp(vf - m)
        integ = np.trapezoid(w, xf, axis=2) + np.trapezoid(np.exp(lseg - m), u, axis=2) * 0.5 * rf[:, 0] ** 2
        lm = np.where(good, m[..., 0] + np.log(integ), -np.inf)
        # posterior means over r, with flux and B interpolated from the nodes (one matrix product)
        wsum = np.maximum(w.sum(axis=2), 1e-300)
        mean_r = np.sum(w * rf, axis=2) / wsum
        mean_f = np.sum(w * (np.stack([fd, fb]) @ interp_w), axis=2) / wsum
        mean_b_d = np.sum(w[0] * (bd @ interp_w), axis=1) / wsum[0]
        # mix the two populations by their marginal likelihoods
        la = logmix[0] + lm[0]
        lbb = logmix[1] + lm[1]
        mx = np.maximum(la, lbb)
        mx = np.where(np.isfinite(mx), mx, 0.0)
        pa, pb = np.exp(la - mx), np.exp(lbb - mx)
        tot = np.maximum(pa + pb, 1e-300)
        return EPoint(logl_disk=lm[0], logl_bulge=lm[1],
                      mean_r=(pa * mean_r[0] + pb * mean_r[1]) / tot,
                      mean_b=(pa * mean_b_d + pb * 1.0) / tot,
                      mean_flux=(pa * mean_f[0] + pb * mean_f[1]) / tot)


class VersionLikelihoods:
    """The likelihoods of versions of one object, evaluated together where they can be.

    Versions on the same Fourier modes (:meth:`shearfit.engine.likelihood.JointModes.with_data`: metacal's
    sheared versions of a noshear fit) whose likelihoods take their size centres from one fit
    (``fixed_centres``, the replays of :func:`replay_samples`) are binned together
    (:func:`shearfit.engine.likelihood.mode_bins_versions`: each ellipticity's bins found once), and every
    version's size nodes summed, marginalised and integrated in one compiled call (``KERNEL.size_nodes_versions``):
    the models' quadratic sums (ff, gg, fg: the modes' weights and the fold groups' pairs, which are the modes', not
    the data's) made once for all the versions, each version's linear sums and marginals its own. Per version the
    same numbers, to the bit, as its own ``like(e1, e2)``, which is what the others get.
    """

    def __init__(self, likes):
        self.likes = list(likes)
        l0 = self.likes[0]
        self.joint = (len(self.likes) > 1 and USE_KERNEL and l0.cfg.mode_bins_per_octave > 0
                      and l0.fixed_centres is not None and l0.locate_widths is None
                      and all(lk.fixed_centres is l0.fixed_centres and lk.locate_widths is None and lk.cfg == l0.cfg
                              and lk.fast is l0.fast and lk.mag == l0.mag and lk.chunk == l0.chunk
                              and np.array_equal(lk.x, l0.x) and lk.jm.pixel_scale == l0.jm.pixel_scale
                              and lk.jm.pair_skip == l0.jm.pair_skip
                              for lk in self.likes[1:])
                      and shares_bins_geometry([lk.jm for lk in self.likes]))
        self.channels = versions_channels([lk.jm for lk in self.likes]) if self.joint else None
        self.polar = polar_setting(l0.cfg) if self.joint else None
        self.grid = None   # the versions' polar grid, made at the first call

    def __call__(self, e1, e2, versions=None, need=None) -> list:
        """``[like(e1, e2) for like in likes]``, over the likelihoods ``versions`` (indices; None: all). ``need``
        (bool, one row per ellipticity, one column per version called): each version evaluated only at the
        ellipticities it needs, its EPoint NaN elsewhere (its numbers there its own like's, to rounding: other
        batches of models; only the models marginalised counted; its best fit still over every model), the bins
        of all placed once."""
        if need is not None:
            need = np.asarray(need, bool)
            need = None if need.all() else need.reshape(np.size(e1), -1)   # (all, or no ellipticity: every one)
        if versions is not None and list(versions) != list(range(len(self.likes))):
            sub = VersionLikelihoods([self.likes[v] for v in versions])
            if self.grid is not None and (sub.joint or len(sub.likes) == 1):
                # their blocks of this grid: the grid they would make (one version's own likelihood bins from its
                # modes' grid)
                part = versions_polar_subset(self.grid, versions, len(self.likes))
                if sub.joint:
                    sub.grid = part
                else:
                    seed_polar_grid(sub.likes[0].jm, self.likes[0].cfg.mode_bins_per_octave, self.polar[0], part)
            return sub(e1, e2, need=need)
        e1 = np.atleast_1d(np.asarray(e1, float))
        e2 = np.atleast_1d(np.asarray(e2, float))
        if not self.joint:
            if need is None:
                return [like(e1, e2) for like in self.likes]
            return [_at_needed(like, e1, e2, need[:, v]) for v, like in enumerate(self.likes)]
        step = self.likes[0].chunk
        out = [self._chunk(e1[i:i + step], e2[i:i + step], None if need is None else need[i:i + step])
               for i in range(0, e1.size, step)]
        if len(out) == 1:   # (the chunk's own arrays: nothing to join)
            return out[0]
        return [EPoint(*[np.concatenate([getattr(o[v], f) for o in out]) for f in EPoint.__dataclass_fields__])
                for v in range(len(self.likes))]

    def _chunk(self, e1, e2, need=None):
        likes = self.likes
        l0 = likes[0]
        nv, ne, nr = len(likes), e1.size, l0.x.size
        jms = [lk.jm for lk in likes]
        # the versions' grid made once (mode_bins_versions bins every mode where it does not pay)
        if self.grid is None and self.polar is not None and polar_pays(jms[0], l0.cfg.mode_bins_per_octave,
                                                                       self.polar[0]):
            self.grid = versions_polar_grid(jms, self.channels, l0.cfg.mode_bins_per_octave, self.polar[0])
        bins = mode_bins_versions(jms, e1, e2, l0.cfg.mode_bins_per_octave, channels=self.channels,
                                  polar=self.polar, grid=self.grid, reuse=True)
        rc = l0.replayed_centres(e1, e2)
        for lk in likes:
            lk.centres.add(e1, e2, rc)
        marg = marginal_context(l0.cfg, l0.jm.pixel_scale) if l0.x.size <= 512 else None
        if marg is not None:
            # every version's size nodes in one compiled call (KERNEL.size_nodes_versions: each version's numbers
            # those of its own like's KERNEL.size_nodes, the quadratic sums made once): its bins at ellipticity i are
            # entry i * nv + v
            return self._nodes_versions(e1, e2, rc, bins, np.arange(ne, dtype=np.int64) * nv, marg, need)
        R = rc[:, None] * np.exp(l0.x)[None, :]
        m = ne * nr
        # the models version after version; version v's bins at ellipticity i are entry i * nv + v
        index = (np.repeat(np.arange(ne), nr)[None, :] * nv + np.arange(nv)[:, None]).ravel()
        sums = l0._sums(np.tile(np.repeat(e1, nr), nv), np.tile(np.repeat(e2, nr), nv), np.tile(R.ravel(), nv),
                        bins, index)
        mg = flux_position_marginal(sums, l0.cfg, l0.jm.pixel_scale)
        out = [lk._size_integral(e1, e2, R, Marginal(*[getattr(mg, f.name)[v * m:(v + 1) * m]
                                                       for f in fields(Marginal)]))
               for v, lk in enumerate(likes)]
        # (every version evaluated everywhere on this path, which only very many size nodes take: the samples a
        # version does not need are set aside as the compiled path leaves them)
        return out if need is None else [_not_needed_nan(p, need[:, v]) for v, p in enumerate(out)]


    def _nodes_versions(self, e1, e2, rc, bins, base, marg, need=None):
        """:meth:`EllipticityLikelihood._nodes_kernel` of every version in one call (version v's bins at ellipticity
        i: entry base[i] + v); one EPoint per version (``need``: as :meth:`__call__`'s)."""
        likes = self.likes
        l0 = likes[0]
        nv, ne = len(likes), e1.size
        xf, interp_w, spl = l0._fine_grid()
        shift = _prior_axis_shift(e1, e2, l0.cfg)
        consts = [lk._node_constants() for lk in likes]
        expx, _, prior, logmix = consts[0]
        out = np.empty((nv, 5, ne))
        best = np.array([[lk.best_chi2_gal, lk.best_snr] for lk in likes], float)
        KERNEL.size_nodes_versions(bins_context(l0.jm, bins, l0.fast, l0.cfg.bulge_size_ratio), marg,
                                   np.ascontiguousarray(base, dtype=np.int64), nv, np.ascontiguousarray(rc, dtype=float),
                                   expx, float(l0.x[0]), xf, interp_w, spl, l0._SEG_U, l0._SEG_HALF_LOG_U,
                                   np.ascontiguousarray([c[1] for c in consts], dtype=float), logmix, prior,
                                   b"" if shift is None else np.ascontiguousarray(shift, dtype=float), out, best,
                                   b"" if need is None else np.ascontiguousarray(need, dtype=np.uint8))
        points = []
        for v, lk in enumerate(likes):
            lk.n_models += (ne if need is None else int(np.count_nonzero(need[:, v]))) * lk.x.size
            lk.best_chi2_gal, lk.best_snr = float(best[v, 0]), float(best[v, 1])
            o = out[v]
            points.append(EPoint(logl_disk=o[0], logl_bulge=o[1], mean_r=o[2], mean_b=o[3], mean_flux=o[4]))
        return points


def _not_needed_nan(point, need):
    """``point`` with NaN where ``need`` is False (a version's values at the samples it was not asked for)."""
    return EPoint(*[np.where(need, getattr(point, f), np.nan) for f in EPoint.__dataclass_fields__])


def _at_needed(like, e1, e2, need):
    """``like`` evaluated where ``need`` (one version's column of :meth:`VersionLikelihoods.__call__`'s), NaN
    elsewhere."""
    out = EPoint(*[np.full(e1.size, np.nan) for _ in EPoint.__dataclass_fields__])
    if np.any(need):
        pt = like(e1[need], e2[need])
        for f in EPoint.__dataclass_fields__:
            getattr(out, f)[need] = getattr(pt, f)
    return out


@dataclass
class Samples:
    """Ellipticity samples of one object."""

    e1: np.ndarray
    e2: np.ndarray
    area: np.ndarray        # area of the grid cell each sample stands for
    logl: np.ndarray        # log likelihood (populations mixed, no ellipticity prior)
    logpost: np.ndarray     # log posterior (likelihood x ellipticity prior, per population)
    point: EPoint = field(repr=False)
    evaluated: np.ndarray = field(default=None, repr=False)   # replays only: the samples evaluated


def _mix(point: EPoint, e1, e2, cfg, log_priors=None):
    """log L and log posterior of the samples, the two populations mixed; ``log_priors``: the disk's and the
    bulge's log ellipticity priors at (e1, e2) where already known (:func:`_lattice_log_priors`)."""
    ld0, lb0 = log_population_weights(cfg)
    la = ld0 + point.logl_disk
    lb = lb0 + point.logl_bulge
    logl = np.logaddexp(la, lb)
    if log_priors is None:
        log_priors = _log_e_priors(e1, e2, cfg)
    pd, pb = log_priors
    logpost = np.logaddexp(la + pd, lb + pb)
    return logl, logpost


def _log_e_priors(e1, e2, cfg):
    with np.errstate(divide="ignore"):
        return np.log(priors.disk_e_density(e1, e2, cfg)), np.log(priors.bulge_e_density(e1, e2, cfg))


def _known_log_e_priors(e1, e2, cfg):
    """:func:`_log_e_priors` at samples of the sampler's lattice (a fit's, which its replays evaluate again) from
    :func:`_lattice_log_priors`' table, where every sample is exactly a lattice point (i unit, j unit) within it: the
    same numbers; computed otherwise."""
    unit, half = float(cfg.e_grid_min), _lattice_half(cfg)
    i, j = np.rint(e1 / unit), np.rint(e2 / unit)
    if e1.size and np.array_equal(i * unit, e1) and np.array_equal(j * unit, e2) and \
            max(np.abs(i).max(), np.abs(j).max()) <= half:
        pd, pb = _lattice_log_priors(cfg, unit, half)
        i, j = i.astype(np.int64) + half, j.astype(np.int64) + half
        return pd[i, j], pb[i, j]
    return _log_e_priors(e1, e2, cfg)


def _lattice_log_priors(cfg, unit, half):
    """The log ellipticity priors (disk, bulge) at every point (i, j) unit of the lattice [-half, half]^2, as
    two arrays indexed [i + half, j + half]: the same numbers as at those points' e1, e2 (made once per set of
    the priors' settings; every fit samples the same lattice)."""
    return _lattice_log_priors_cached(cfg.disk_e_max, cfg.disk_e0, cfg.disk_e_a, cfg.bulge_e_b, cfg.bulge_e_c,
                                      unit, half)


@functools.lru_cache(maxsize=8)
def _lattice_log_priors_cached(disk_e_max, disk_e0, disk_e_a, bulge_e_b, bulge_e_c, unit, half):
    cfg = FitConfig(disk_e_max=disk_e_max, disk_e0=disk_e0, disk_e_a=disk_e_a, bulge_e_b=bulge_e_b,
                    bulge_e_c=bulge_e_c)
    e = np.arange(-half, half + 1, dtype=float) * unit
    E1, E2 = np.meshgrid(e, e, indexing="ij")
    out = _log_e_priors(E1, E2, cfg)
    for a in out:
        a.setflags(write=False)
    return out


def _prior_axis_shift(e1, e2, cfg):
    """ln of the size prior's scalelength over the semi-major one at each e (``size_prior_axis``): None for
    'major', (1/2) ln q for 'area', ln q for 'minor' (q = (1 - |e|) / (1 + |e|))."""
    k = {"major": 0.0, "area": 0.5, "minor": 1.0}[cfg.size_prior_axis]
    if k == 0.0:
        return None
    em = np.minimum(np.hypot(e1, e2), 0.999)
    return k * np.log((1.0 - em) / (1.0 + em))


@functools.lru_cache(maxsize=32)
def _locate_exp(half_width):
    """exp of the 5 ln r offsets of a size-locating pass (read-only, shared)."""
    v = np.exp(_locate_nodes(half_width))
    v.setflags(write=False)
    return v


@functools.lru_cache(maxsize=32)
def _locate_nodes(half_width):
    """The 5 ln r offsets of a size-locating pass over +-half_width (read-only, shared)."""
    xs = np.linspace(-half_width, half_width, 5)
    xs.setflags(write=False)
    return xs


class _Store:
    """Samples on the integer lattice of the finest step (0.02 by default).

    Each sampled region is kept as its step and a mask over a box of the lattice (``regions``): a sample
    stands for a cell of the finest region that contains it.
    """

    def __init__(self, like, cfg):
        self.like = like
        self.cfg = cfg
        self.unit = cfg.e_grid_min
        self.keys = {}
        self.points = []
        # the samples' e1, e2, log L and log posterior, one array per add() (the properties below join them)
        self._cols = ([], [], [], [])
        self._joined = None
        self.n = 0
        self.half = _lattice_half(cfg)
        # (step, i0, j0, mask): the region is mask's True entries, entry (a, b) the lattice point (i0 + a, j0 + b).
        # Masks cover only their region's box: over the whole lattice (then 917 x 917 entries at metacal's 0.005
        # step, a margin of four coarsest steps around |e| < 1 that no box needs), their allocation and search were
        # 6 % of its fits
        self.regions = []

    def add(self, ij):
        new = [k for k in ij if k not in self.keys]
        if not new:
            return
        ij = np.array(new)
        arr = ij.astype(float) * self.unit
        pt = self.like(arr[:, 0], arr[:, 1])
        lp = None
        if np.all(np.abs(ij) <= self.half):   # (every sampler's points are: _box clips to the lattice)
            pd, pb = _lattice_log_priors(self.cfg, self.unit, self.half)
            i, j = ij[:, 0] + self.half, ij[:, 1] + self.half
            lp = (pd[i, j], pb[i, j])
        logl, logpost = _mix(pt, arr[:, 0], arr[:, 1], self.cfg, log_priors=lp)
        self.keys.update(zip(new, range(self.n, self.n + len(new))))
        self.n += len(new)
        for col, v in zip(self._cols, (arr[:, 0], arr[:, 1], logl, logpost)):
            col.append(np.array(v, float))
        self._joined = None
        self.points.append(pt)

    def _column(self, c):
        """Column c (0: e1, 1: e2, 2: log L, 3: log posterior) of every sample so far, one array (read-only: made
        once per add())."""
        if self._joined is None:
            self._joined = [np.concatenate(col) if col else np.zeros(0) for col in self._cols]
            for a in self._joined:
                a.setflags(write=False)
        return self._joined[c]

    e1 = property(lambda self: self._column(0))
    e2 = property(lambda self: self._column(1))
    logl = property(lambda self: self._column(2))
    logpost = property(lambda self: self._column(3))

    def _points(self, step, i0, j0, mask):
        """The step's lattice points in the region (mask over the box from (i0, j0)) with |e| below the model
        limit, row after row; records the region."""
        # only the step's rows and columns of the box are looked at (a coarse step's are few: the whole box at
        # the finest unit cost the pre-pass and its refinements some 2 ms a fit, at metacal's 0.005)
        a = np.arange((-i0) % step, mask.shape[0], step)
        b = np.arange((-j0) % step, mask.shape[1], step)
        I, J = i0 + a, j0 + b
        limit = self.cfg.model_e_limit / self.unit
        on = mask[np.ix_(a, b)] & (I[:, None] ** 2 + J[None, :] ** 2 < limit * limit)
        ii, jj = np.nonzero(on)
        self.regions.append((step, i0, j0, mask))
        return list(zip(I[ii].tolist(), J[jj].tolist()))

    def _box(self, imin, imax, jmin, jmax):
        """The box's corner and an empty mask over it, clipped to the lattice [-half, half]^2 (None if empty)."""
        h = self.half
        imin, jmin = max(imin, -h), max(jmin, -h)
        imax, jmax = min(imax, h), min(jmax, h)
        if imax < imin or jmax < jmin:
            return None
        return imin, jmin, np.zeros((imax - imin + 1, jmax - jmin + 1), bool)

    def lattice_box(self, step, imin, imax, jmin, jmax):
        box = self._box(imin, imax, jmin, jmax)
        if box is None:
            return []
        i0, j0, mask = box
        mask[:, :] = True
        return self._points(step, i0, j0, mask)

    def lattice_around(self, step, i, j, reach):
        """The step's lattice points within ``reach`` (Chebyshev, lattice units) of the points (i, j)."""
        i = np.asarray(i).tolist()
        j = np.asarray(j).tolist()
        if not i:
            return []
        box = self._box(min(i) - reach, max(i) + reach, min(j) - reach, max(j) + reach)
        if box is None:
            return []
        i0, j0, mask = box
        for a, b in zip(i, j):
            mask[max(a - reach - i0, 0):a + reach - i0 + 1, max(b - reach - j0, 0):b + reach - j0 + 1] = True
        return self._points(step, i0, j0, mask)

    def result(self) -> Samples:
        e1 = np.array(self.e1)
        e2 = np.array(self.e2)
        i = np.rint(e1 / self.unit).astype(int)
        j = np.rint(e2 / self.unit).astype(int)
        # the finest region containing a sample tiles the plane there: the sample stands for one of its
        # cells if it lies on that region's lattice, and for nothing otherwise (a two-pass first-pass
        # point, or a coarser-lattice point inside a finer region)
        step = np.full(e1.size, np.iinfo(np.int64).max)
        for (s, i0, j0, mask) in self.regions:
            a, b = i - i0, j - j0
            inside = (a >= 0) & (a < mask.shape[0]) & (b >= 0) & (b < mask.shape[1])
            inside[inside] = mask[a[inside], b[inside]]
            step = np.where(inside, np.minimum(step, s), step)
        covered = step < np.iinfo(np.int64).max
        st = np.where(covered, step, 1)
        on = covered & (i % st == 0) & (j % st == 0)
        area = np.where(on, (st * self.unit) ** 2, 0.0)
        pts = self.points
        point = EPoint(*[np.concatenate([getattr(p, f) for p in pts]) for f in
                         ("logl_disk", "logl_bulge", "mean_r", "mean_b", "mean_flux")])
        return Samples(e1=e1, e2=e2, area=area, logl=np.array(self.logl), logpost=np.array(self.logpost),
                       point=point)

    def above(self, fraction):
        return self.above_log(np.log(fraction))

    def above_log(self, log_fraction):
        """Which samples have a posterior above exp(log_fraction) of the largest."""
        lp = self.logpost
        if not np.any(np.isfinite(lp)):
            return np.zeros(lp.size, bool)
        return lp > np.max(lp) + log_fraction


def adaptive_samples(like: EllipticityLikelihood, cfg: FitConfig, use_kernel=True) -> Samples:
    """The paper's adaptive grid (sec. 3.3).

    Start on a 0.16 grid; while fewer than 30 samples lie above 5 % of the
    maximum posterior and the step is above 0.02, halve the step over the
    region within one old step (in e1 and in e2) of the samples above the
    posterior cut. (Until session 10 the region was their bounding box plus
    one old step: its corners, far below the cut, changed no estimate.)

    With ``e_grid_prepass`` (0.32 by default), the 0.16 grid is not sampled
    everywhere: a grid that coarse comes first over the whole disk, and the
    step halves down to 0.16 within one coarse step of the coarse samples
    less than ``e_grid_prepass_margin`` nats below the posterior cut. The
    0.16 samples left out lie between coarse samples all that far below the
    cut: below it themselves unless the posterior has a feature narrower
    than the coarse step there, and then neither the estimator (which uses
    only samples above the cut) nor the refinement (which starts from them)
    would have used them. The estimates move by at most 2.2e-7 (59 galaxies
    of SNR 7-60, ``benchmarks/speed.py --check --check-each``).

    Where the likelihood's chunks are compiled (:meth:`EllipticityLikelihood._chunk_args`), the whole loop is
    one compiled call (``KERNEL.adaptive_samples``: the lattice, its regions and the refinement, the chunks
    evaluated as ``KERNEL.sample_chunk`` does), the same samples and numbers as the lines below
    (``use_kernel=False``, which stay as the reference; tests/test_measure.py).
    """
    step = int(round(cfg.e_grid_start / cfg.e_grid_min))
    pre = int(round(cfg.e_grid_prepass / cfg.e_grid_min)) if cfg.e_grid_prepass > 0 else step
    n = int(cfg.model_e_limit / cfg.e_grid_min) + max(step, pre)
    if use_kernel:
        got = _adaptive_kernel(like, cfg, step, pre, n)
        if got is not None:
            return got
    st = _Store(like, cfg)
    st.add(st.lattice_box(pre, -n, n, -n, n))
    while pre > step:
        sel = st.above_log(np.log(cfg.posterior_cut) - cfg.e_grid_prepass_margin)
        i = np.rint(st.e1[sel] / cfg.e_grid_min).astype(int)
        j = np.rint(st.e2[sel] / cfg.e_grid_min).astype(int)
        new = max(pre // 2, step)
        st.add(st.lattice_around(new, i, j, pre))
        pre = new
    while True:
        sel = st.above(cfg.above_fraction)
        if sel.sum() >= cfg.n_above or step <= 1:
            break
        # refine over every sample the estimator will use (posterior above the cut), not only
        # those above the counting threshold: otherwise high-likelihood, low-prior samples near
        # the cut keep coarse cells and the estimate jumps when the region's edge moves
        sel = st.above(min(cfg.posterior_cut, cfg.above_fraction))
        e1 = st.e1[sel]
        e2 = st.e2[sel]
        i = np.rint(e1 / cfg.e_grid_min).astype(int)
        j = np.rint(e2 / cfg.e_grid_min).astype(int)
        new = max(step // 2, 1)
        st.add(st.lattice_around(new, i, j, step))
        step = new
    return st.result()


def _lattice_half(cfg):
    """The half-width of the sampler's lattice (:class:`_Store`): every |e| < 1, which holds every sample (|e| below
    model_e_limit < 1; the boxes are clipped to the lattice)."""
    return int(np.ceil(1.0 / cfg.e_grid_min)) + 2


@functools.lru_cache(maxsize=8)
def _lattice_growth(unit, half):
    """:meth:`EllipticityLikelihood.centre` over r_center at every point of the lattice (as
    :func:`_lattice_log_priors`): the same numbers as at those points' e1, e2 (NaN beyond |e| = 1, which no sample
    reaches). Read-only."""
    e = np.arange(-half, half + 1, dtype=float) * unit
    E1, E2 = np.meshgrid(e, e, indexing="ij")
    ee = np.hypot(E1, E2)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (1 - ee) / (1 + ee)
        out = np.minimum(q ** (-1.0 / 3.0), CENTRE_GROWTH_MAX)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=8)
def _lattice_shift(axis, unit, half):
    """:func:`_prior_axis_shift` at every point of the lattice, or None for the semi-major axis. Read-only."""
    e = np.arange(-half, half + 1, dtype=float) * unit
    E1, E2 = np.meshgrid(e, e, indexing="ij")
    out = _prior_axis_shift(E1, E2, FitConfig(size_prior_axis=axis))
    if out is not None:
        out = np.ascontiguousarray(out)
        out.setflags(write=False)
    return out


def _adaptive_kernel(like, cfg, step, pre, n):
    """adaptive_samples in one compiled call (``KERNEL.adaptive_samples``), or None where the likelihood's chunks
    are not compiled."""
    if not (USE_KERNEL and isinstance(like, EllipticityLikelihood)):
        return None
    fused = like._chunk_args()
    if fused is None:
        return None
    unit = float(cfg.e_grid_min)
    half = _lattice_half(cfg)
    pd, pb = _lattice_log_priors(cfg, unit, half)
    shift = _lattice_shift(cfg.size_prior_axis, unit, half)
    ld0, lb0 = log_population_weights(cfg)
    ints = np.array([half, step, pre, n, cfg.n_above, like.chunk], np.int64)
    params = np.array([unit, cfg.model_e_limit, np.log(cfg.posterior_cut) - cfg.e_grid_prepass_margin,
                       np.log(cfg.above_fraction), np.log(min(cfg.posterior_cut, cfg.above_fraction)), ld0, lb0,
                       like.r_center, 0.0, 0.0], float)
    state = like._state()
    out, ns, need = KERNEL.adaptive_samples(like._kernel_args(fused), pd, pb, _lattice_growth(unit, half),
                                            b"" if shift is None else shift, ints, params, state)
    if need:
        grow_column_buffer(need)
    like._set_state(state)
    cols = np.frombuffer(out, float).reshape(11, ns).copy()
    e1, e2 = cols[0], cols[1]
    like.centres.add(e1, e2, cols[10])
    return Samples(e1=e1, e2=e2, area=cols[2], logl=cols[3], logpost=cols[4], point=EPoint(*cols[5:10]))


def two_pass_samples(like: EllipticityLikelihood, cfg: FitConfig) -> Samples:
    """Two passes (sec. 3.3's later improvement): find the maximum, then map around it.

    Pass 1 samples a grid twice as coarse as the adaptive one's and refines
    only the 5x5 neighbourhood of the current maximum, halving the step down
    to the finest. Pass 2 measures the posterior's width at the maximum from
    the likelihood-weighted spread of the samples, then maps a box of
    +-(3 widths + a step) at about half a width per step (at most 13 steps
    across), enlarging the box while any sample on its edge is above the
    posterior cut.
    """
    st = _Store(like, cfg)
    unit = cfg.e_grid_min
    finest = 1
    coarsest = int(round(cfg.e_grid_start / unit))
    step = 2 * coarsest
    n = int(cfg.model_e_limit / unit) + step
    st.add(st.lattice_box(step, -n, n, -n, n))
    while step > finest:
        step = max(step // 2, finest)
        k = int(np.argmax(st.logpost))
        i0, j0 = int(round(st.e1[k] / unit)), int(round(st.e2[k] / unit))
        st.add(st.lattice_box(step, i0 - 2 * step, i0 + 2 * step, j0 - 2 * step, j0 + 2 * step))
    # pass 2's grid defines the cells near the maximum, pass 1's coarse grid the rest; pass 1's
    # refinements only guided the search
    st.regions = st.regions[:1]
    e1 = np.array(st.e1)
    e2 = np.array(st.e2)
    lp = np.array(st.logpost)
    k = int(np.argmax(lp))
    w = np.exp(lp - lp[k])
    sel = w > cfg.posterior_cut
    sig = np.sqrt(max(np.average((e1[sel] - e1[k]) ** 2 + (e2[sel] - e2[k]) ** 2, weights=w[sel]) / 2,
                      (unit / 2) ** 2))
    limit = int(cfg.model_e_limit / unit) + 1
    half = int(np.ceil((3 * sig) / unit)) + 1
    i0, j0 = int(round(e1[k] / unit)), int(round(e2[k] / unit))
    while True:
        step = int(np.clip(max(round(sig / 2 / unit), int(np.ceil(2 * half / 12))), finest, coarsest))
        half = int(np.ceil(half / step)) * step
        box = (i0 - half, i0 + half, j0 - half, j0 + half)
        st.add(st.lattice_box(step, *box))
        lp = np.array(st.logpost)
        ii = np.rint(np.array(st.e1) / unit).astype(int)
        jj = np.rint(np.array(st.e2) / unit).astype(int)
        on_edge = (((np.abs(ii - i0) == half) & (np.abs(jj - j0) <= half)) |
                   ((np.abs(jj - j0) == half) & (np.abs(ii - i0) <= half)))
        hot = on_edge & (lp > lp.max() + np.log(cfg.posterior_cut))
        if not np.any(hot) or half >= 2 * limit:
            break
        half = int(half * 1.5) + step
    return st.result()


def replay_samples(like: EllipticityLikelihood, ref: Samples, cfg: FitConfig, margin: float,
                   first_margin: float = None) -> Samples:
    """The ellipticity samples of a reference fit, evaluated on another version of the same object.

    The estimator then follows the data smoothly from one version to the
    other: no sample, cell or size node moves with the small change between
    them (an adaptive grid re-chosen per version moves discretely, which
    differences of estimates 2 delta apart would read as response). Only
    samples whose reference posterior lies above the posterior cut less
    ``margin`` nats are evaluated (and only those that stand for a cell);
    the rest get log L = -inf, which the estimator leaves out anyway unless
    the version's posterior differs from the reference's by more than
    ``margin`` there.

    With ``first_margin`` (< ``margin``), the samples above the reference's cut are evaluated first, and of the
    rest within ``margin`` only those the version could lift to within ``first_margin`` of its own cut
    (:func:`_evaluate_near_cut`): the version's change of the posterior from the reference's, smooth in e (a small
    shear moves the posterior), is fitted over the first samples and predicts it at the others. The samples left
    out stay below the version's cut, and the estimate is the one with ``margin`` alone, to rounding.
    """
    return replay_versions(VersionLikelihoods([like]), ref, cfg, margin, first_margin)[0]


def replay_versions(likes: VersionLikelihoods, ref: Samples, cfg: FitConfig, margin: float,
                    first_margin: float = None) -> list:
    """:func:`replay_samples` of every version of ``likes``, their likelihoods evaluated together (the same
    numbers, one Samples per version)."""
    ok = np.isfinite(ref.logpost) & (ref.area > 0)
    n = ref.e1.size
    nv = len(likes.likes)
    fields_ = ("logl_disk", "logl_bulge", "mean_r", "mean_b", "mean_flux")
    logl = [np.full(n, -np.inf) for _ in range(nv)]
    logpost = [np.full(n, -np.inf) for _ in range(nv)]
    cols = [{f: np.full(n, np.nan) for f in fields_} for _ in range(nv)]

    def evaluate(which, versions, need=None):
        e1, e2 = ref.e1[which], ref.e2[which]
        priors_ = _known_log_e_priors(e1, e2, cfg)   # (the same for every version)
        rows = np.flatnonzero(which)
        for j, (v, pt) in enumerate(zip(versions, likes(e1, e2, versions=versions, need=need))):
            if need is None:
                at, p, pr = rows, pt, priors_
            else:   # (the version's own samples: its values elsewhere were not made)
                k = need[:, j]
                at, p, pr = rows[k], EPoint(**{f: getattr(pt, f)[k] for f in fields_}), (priors_[0][k], priors_[1][k])
            logl[v][at], logpost[v][at] = _mix(p, ref.e1[at], ref.e2[at], cfg, pr)
            for f in fields_:
                cols[v][f][at] = getattr(p, f)

    sel = _evaluate_near_cut(ref, ok, cfg, margin, first_margin, nv, evaluate, lambda v, which: logpost[v][which])
    return [Samples(e1=ref.e1, e2=ref.e2, area=ref.area, logl=logl[v], logpost=logpost[v],
                    point=EPoint(**cols[v]), evaluated=sel[v]) for v in range(nv)]


#: :func:`_evaluate_near_cut` predicts a version's change of the posterior from at least this many samples (else
#: it evaluates every sample within the margin)
PREDICT_MIN_SAMPLES = 12


def _change_design(e1, e2):
    """The terms of the quadratic in (e1, e2) that :func:`_evaluate_near_cut` fits a version's change with."""
    return np.stack([np.ones_like(e1), e1, e2, e1 * e1, e1 * e2, e2 * e2], axis=1)


def _evaluate_near_cut(ref, ok, cfg, margin, first_margin, nv, evaluate, logpost_of):
    """Which of the reference's samples (``ok``) each of ``nv`` versions evaluates: those within ``margin`` nats
    of the reference's posterior cut (``evaluate(which, versions)``). With ``first_margin`` (< ``margin``) the
    samples above the reference's cut first (every version's estimate is mostly theirs); then, per version, its
    change of the log posterior from the reference's (``logpost_of(v, which)``: version v's log posterior there)
    fitted over them by a quadratic in (e1, e2), and of the other samples within ``margin`` only those whose
    predicted log posterior lies within ``first_margin`` nats, plus three times the fit's largest residual, of the
    version's own cut (each version evaluated at the samples it needs alone, all in one call: their bins placed
    once, ``evaluate(which, versions, need)`` with ``need`` one column per version over ``which``'s samples). Where
    a sample a version needs differs from its prediction by more than half ``first_margin`` plus that allowance, or
    where fewer than ``PREDICT_MIN_SAMPLES`` samples lie above the cut, the version evaluates every sample within
    ``margin`` (those it has not yet, for all such versions in one call, each its own).
    The samples left out lie below the version's cut by more than the prediction's error seen: its estimate is
    the one with ``margin`` alone. Returns one mask per version."""
    sel = [np.zeros(ref.e1.size, bool) for _ in range(nv)]
    if not np.any(ok):
        return sel
    lnc = np.log(cfg.posterior_cut)
    cut = np.max(ref.logpost[ok]) + lnc
    full = ok & (ref.logpost > cut - margin)
    if first_margin is None or first_margin >= margin:
        evaluate(full, list(range(nv)))
        return [full] * nv
    above = ok & (ref.logpost > cut)
    evaluate(above, list(range(nv)))
    rest = full & ~above
    if not np.any(rest):
        return [above] * nv
    ia, ir = np.nonzero(above)[0], np.nonzero(rest)[0]
    xa, xr = _change_design(ref.e1[ia], ref.e2[ia]), _change_design(ref.e1[ir], ref.e2[ir])
    whole, fits = [], {}
    lps = [logpost_of(v, above) for v in range(nv)]
    goods = [np.isfinite(lp) for lp in lps]
    betas = {}
    every = [v for v in range(nv) if goods[v].all()]
    if len(every) > 1 and ia.size >= PREDICT_MIN_SAMPLES:
        # the versions finite at every sample fitted in one least-squares call (one factorisation of the design)
        d = np.stack([lps[v] for v in every], axis=1) - ref.logpost[ia][:, None]
        betas = dict(zip(every, np.linalg.lstsq(xa, d, rcond=None)[0].T))
    for v in range(nv):
        lp, good = lps[v], goods[v]
        if np.count_nonzero(good) < PREDICT_MIN_SAMPLES:
            whole.append(v)
            continue
        d = lp[good] - ref.logpost[ia[good]]
        beta = betas[v] if v in betas else np.linalg.lstsq(xa[good], d, rcond=None)[0]
        slack = first_margin + 3.0 * float(np.max(np.abs(d - xa[good] @ beta)))
        pred = ref.logpost[ir] + xr @ beta
        need = pred > np.max(lp[good]) + lnc - slack
        if np.any(need):
            fits[v] = (pred, slack, need)
    # the samples each version needs, evaluated for those versions together (their bins placed once, each
    # version's models only at its own)
    own = {}
    for v, (_, _, need) in fits.items():
        own[v] = np.zeros(ref.e1.size, bool)
        own[v][ir[need]] = True
    some = list(fits)
    if some:
        near = np.logical_or.reduce([own[v] for v in some])
        evaluate(near, some, np.stack([own[v][near] for v in some], axis=1))
        for v in some:
            # the prediction checked where the version needs it
            pred, slack, need = fits[v]
            got = logpost_of(v, own[v])
            fin = np.isfinite(got)
            if np.any(fin) and np.max(np.abs(got[fin] - pred[need][fin])) > slack - 0.5 * first_margin:
                whole.append(v)
    for v in range(nv):
        sel[v] = above | own[v] if v in fits else above.copy()
    # the versions that evaluate every sample within the margin: those they have not evaluated yet
    if whole:
        others = {v: rest & ~sel[v] for v in whole}
        union = np.logical_or.reduce(list(others.values()))
        if np.any(union):
            evaluate(union, whole, np.stack([others[v][union] for v in whole], axis=1))
            for v in whole:
                sel[v] = sel[v] | others[v]
    return sel


def adaptive_versions(likes: VersionLikelihoods, ref: Samples, cfg: FitConfig, margin: float,
                      first_margin: float = None) -> list:
    """Each version's own adaptive grid (:func:`adaptive_samples`), its likelihood evaluated where it matters.

    A replay (:func:`replay_versions`) keeps the reference fit's samples and cells, so its estimate at a
    small shear is that of a grid fixed from the noshear pixels; a version's own grid moves with its pixels as
    the noshear fit's moves with a true shear, and the differences between versions then see that too. Here
    every version runs the adaptive grid on its own likelihood, but of the samples the reference had, only
    those within ``margin`` nats of the reference's posterior cut are evaluated (for all versions together),
    and the others carry the reference's values: they lie below any version's cut unless its posterior
    moved by more than ``margin`` there (the replays' assumption), and below it they only decide where the
    coarse pre-pass is refined, far from any sample the estimator uses (they are moved by the difference of the
    version's and the reference's maxima, so that they stand as far below the version's maximum). With
    ``first_margin`` (< ``margin``) the samples above the reference's cut are evaluated first, and of the rest
    within ``margin`` only those the version's predicted change could lift to within ``first_margin`` of its cut
    (as :func:`replay_versions` decides, :func:`_evaluate_near_cut`). A sample the reference never had (a
    version refining where it did not) is evaluated for that version alone, its size centre carried from the
    nearest replayed one (:meth:`EllipticityLikelihood.replayed_centres`). Every version must replay the
    reference's size nodes and centres (``fixed_centres``).
    """
    fields_ = tuple(EPoint.__dataclass_fields__)
    unit = cfg.e_grid_min
    n = ref.e1.size
    nv = len(likes.likes)
    def key_of(e1, e2):
        # a lattice point (|e| <= 1, so |e / unit| < 2^20) as one integer
        return (np.rint(np.asarray(e1) / unit).astype(np.int64) << 21) + np.rint(np.asarray(e2) / unit).astype(np.int64)
    ref_keys = key_of(ref.e1, ref.e2)
    order = np.argsort(ref_keys, kind="stable")
    sorted_keys = ref_keys[order]

    def rows_of(e1, e2):
        """The reference's sample at each (e1, e2), -1 where it had none."""
        k = key_of(e1, e2)
        if n == 0:
            return np.full(k.shape, -1)
        i = np.minimum(np.searchsorted(sorted_keys, k), n - 1)
        return np.where(sorted_keys[i] == k, order[i], -1)
    # every version's values at the reference's samples: the reference's, until evaluated
    cols = [{f: np.array(getattr(ref.point, f), float) for f in fields_} for _ in range(nv)]

    def evaluate(which, versions, need=None):
        rows = np.flatnonzero(which)
        for j, (v, pt) in enumerate(zip(versions, likes(ref.e1[which], ref.e2[which], versions=versions, need=need))):
            at = slice(None) if need is None else need[:, j]
            for f in fields_:
                cols[v][f][rows[at]] = getattr(pt, f)[at]

    def logpost_of(v, which):
        return _mix(EPoint(**{f: cols[v][f][which] for f in fields_}), ref.e1[which], ref.e2[which], cfg)[1]

    ok = np.isfinite(ref.logpost)
    done = _evaluate_near_cut(ref, ok, cfg, margin, first_margin, nv, evaluate, logpost_of)
    for v in range(nv):
        # the reference's values a version carries are put on its own scale: moved by the difference of the
        # two maxima over the samples evaluated (a version's log L differs from the reference's by its noise's)
        d = done[v] & ok
        lp = logpost_of(v, d)
        if np.any(np.isfinite(lp)):
            shift = float(np.max(lp[np.isfinite(lp)]) - np.max(ref.logpost[d]))
            for f in ("logl_disk", "logl_bulge"):
                cols[v][f][~done[v]] += shift
    out = []
    for v, like in enumerate(likes.likes):
        def lookup(e1, e2, v=v, like=like):
            r = rows_of(e1, e2)
            have = r >= 0
            got = {f: np.where(have, cols[v][f][np.maximum(r, 0)], np.nan) for f in fields_}
            fresh = np.nonzero(~have)[0]
            if fresh.size:
                pt = like(e1[fresh], e2[fresh])
                for f in fields_:
                    got[f][fresh] = getattr(pt, f)
            return EPoint(**got)
        s = adaptive_samples(lookup, cfg)
        r = rows_of(s.e1, s.e2)
        s.evaluated = (r < 0) | done[v][np.maximum(r, 0)]
        out.append(s)
    return out


@dataclass
class Estimate:
    e1: float
    e2: float
    e_var: float
    weight: float
    scalelength: float
    bulge_fraction: float
    model_flux: float
    n_used: int
    round_scalelength: float = np.nan


def estimate(s: Samples, cfg: FitConfig) -> Estimate:
    """Likelihood mean over samples above the posterior cut (sec. 3.4), variance, weight (3.5)."""
    ok = np.isfinite(s.logpost) & np.isfinite(s.logl) & (s.area > 0)
    if not ok.any():
        return Estimate(np.nan, np.nan, np.nan, 0.0, np.nan, np.nan, np.nan, 0)
    # (the samples kept as indices, each column gathered once: the same numbers)
    keep = np.flatnonzero(ok & (s.logpost > s.logpost[ok].max() + np.log(cfg.posterior_cut)))
    lw = s.logl[keep]
    w = np.exp(lw - lw.max()) * s.area[keep]
    w /= w.sum()
    e1k, e2k = s.e1[keep], s.e2[keep]
    e1 = float((w * e1k).sum())
    e2 = float((w * e2k).sum())
    var = float(0.5 * (w * ((e1k - e1) ** 2 + (e2k - e2) ** 2)).sum())
    p = s.point
    rk = p.mean_r[keep]
    # the round scalelength of each sample's model, of the same area: r sqrt(q), q = (1 - |e|) / (1 + |e|)
    ae = np.minimum(np.hypot(e1k, e2k), 1.0)
    return Estimate(e1=e1, e2=e2, e_var=var, weight=float(lensing_weight(var, cfg)),
                    scalelength=float((w * rk).sum()),
                    bulge_fraction=float((w * p.mean_b[keep]).sum()),
                    model_flux=float((w * p.mean_flux[keep]).sum()), n_used=int(keep.size),
                    round_scalelength=float((w * rk * np.sqrt((1 - ae) / (1 + ae))).sum()))
