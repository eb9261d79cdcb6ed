#!/usr/bin/env python
"""Metacalibration's symmetrising noise: does a version's noise carry the shear step?

Metacal's sheared images shear the image's noise with the galaxy; the noise field added to every version (drawn
with the stamp's variance, turned by 90 degrees, put through the same operations and turned back) is there so
that the noise of the 1p and 1m versions has the same covariance to first order in the step. If it does, the
mean of any estimator over the noise is the same function of the galaxy's image in every version, and the
ensemble response <R> is the true shear response of the noshear estimate to O(delta^2), whatever the estimator
(its choices included, as long as every version makes its own). If it did not, R would carry the estimator's
response to the sheared noise, which for lensfit at SNR 10-14 is most of R (``ring_test.py
--metacal-unsymmetrised``, benchmarks/README.md, session 51).

The exposures are those ``ring_test.py`` draws (elliptical Moffat PSFs of their own, each exposure's pixel grid
rotated, its stamp size). For each, the statistic is the versions' noise power spectrum in the sky frame, through
its spin-2 moments

    q1 = sum P(K) (Ku^2 - Kv^2) / sum P(K) |K|^2,   q2 = sum P(K) 2 Ku Kv / sum P(K) |K|^2

over every wavevector and under a low-pass filter exp(-|K|^2 (0.4")^2) (where a galaxy's signal lies), and the
finite differences dq_i / dg_i = (q_i[ip] - q_i[im]) / (2 delta), with the symmetrising noise (as shipped) and
without it (the processed stamp noise alone, whose shear they measure). Two ways:

- expected: the operations are linear and, on their periodic grid, shift-invariant, so a version's noise power
  is the stamp's variance times |H(K)|^2 + |H'(K)|^2, H and H' the impulse responses of the stamp's path and of
  the added field's (each put through metacal alone): exact, without noise, up to the stamp's edges;
- pure noise: Gaussian noise at each exposure's weight through metacal_observations (a Hann window over the inner
  pixels), edges and all, with Monte Carlo errors.

    python benchmarks/metacal_noise_symmetry.py --n-objects 400
    python benchmarks/metacal_noise_symmetry.py --n-objects 400 --metacal-psf round
    python benchmarks/metacal_noise_symmetry.py --n-objects 100 --stamp-size 128 --size-range 0.85 2
    python benchmarks/metacal_noise_symmetry.py --n-objects 1000 --stamp-size 48 --population paper --no-monte-carlo
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from shearfit.calib.metacal import metacal_observations  # noqa: E402
from shearfit.observation import Observation  # noqa: E402
from shearfit.simulate import ring_set  # noqa: E402
from shearfit.simulate.outside import outside_population, outside_profile  # noqa: E402

#: the low-pass filter's scale, arcsec
LOW_PASS = 0.4
#: pixels left out at each edge of a pure-noise stamp (metacal's versions weigh its outermost pixels zero)
EDGE = 4
#: the statistics' columns: [with, without the symmetrising noise] x [every wavevector, low-pass] x
#: [dq1/dg1, dq2/dg2, dq2/dg1, dq1/dg2]
SHAPE = (2, 2, 4)
VERSIONS = ("1p", "1m", "2p", "2m")


class FixedDraw:
    """Stands for metacal's generator: its ``normal`` returns the given field (zeros: no symmetrising noise; an
    impulse: the added field's impulse response)."""

    def __init__(self, field=None):
        self.field = field

    def normal(self, loc=0.0, scale=1.0, size=None):
        return np.zeros(size) if self.field is None else np.array(self.field, float)


def sky_frame(shape, J):
    """For power spectra of ``shape`` (numpy's FFT layout) on pixels of Jacobian ``J``: the sky wavevectors'
    (Ku^2 - Kv^2, 2 Ku Kv, |K|^2) and the low-pass filter, made once for an exposure's versions."""
    ky, kx = np.meshgrid(2 * np.pi * np.fft.fftfreq(shape[0]), 2 * np.pi * np.fft.fftfreq(shape[1]), indexing="ij")
    jit = np.linalg.inv(np.asarray(J, float)).T     # pixel wavevectors to the sky's: K = J^-T k
    ku, kv = jit[0, 0] * kx + jit[0, 1] * ky, jit[1, 0] * kx + jit[1, 1] * ky
    k2 = ku * ku + kv * kv
    return ku * ku - kv * kv, 2 * ku * kv, k2, np.exp(-k2 * LOW_PASS ** 2)


def spin2_moments(power, frame):
    """(q1, q2) of a power spectrum over every wavevector and under the low-pass filter, in the sky frame
    ``frame`` (:func:`sky_frame`'s): shape (2, 2)."""
    c1, c2, k2, low = frame
    out = []
    for w in (power, power * low):
        norm = np.sum(w * k2)
        out.append([np.sum(w * c1) / norm, np.sum(w * c2) / norm])
    return np.array(out)


def _responses(q, delta):
    """SHAPE[1:] from the versions' (q1, q2) moments ``q[version]`` (each of shape (2, 2)), 2 delta apart."""
    d1 = (q["1p"] - q["1m"]) / (2 * delta)
    d2 = (q["2p"] - q["2m"]) / (2 * delta)
    return np.stack([d1[:, 0], d2[:, 1], d1[:, 1], d2[:, 0]], axis=1)


def _noise_obs(obs, image, weight=None):
    """``obs``'s PSF, Jacobian and stamp with other pixels (and unit weights unless given), and a Moffat of its
    own (metacal's images do not depend on it)."""
    return Observation(image=image, psf=obs.psf, jacobian=obs.jacobian,
                       weight=np.ones(obs.weight.shape) if weight is None else weight,
                       psf_oversampling=obs.psf_oversampling, psf_moffat=(1.0, 3.0))


def expected_noise_response(obs, delta=0.01, psf="dilated"):
    """The versions' noise power of one exposure (its PSF, Jacobian and stamp shape; unit variance) from the impulse
    responses of metacal's two paths, and its spin-2 moments' finite differences: an array of :data:`SHAPE`."""
    shape = obs.weight.shape
    impulse = np.zeros(shape)
    impulse[shape[0] // 2, shape[1] // 2] = 1.0
    stamp = metacal_observations(_noise_obs(obs, impulse), delta, FixedDraw(), fit_moffat=False, psf=psf)
    added = metacal_observations(_noise_obs(obs, np.zeros(shape)), delta, FixedDraw(impulse), fit_moffat=False,
                                 psf=psf)
    out = np.empty(SHAPE)
    ps = {v: np.abs(np.fft.fft2(stamp[v].image)) ** 2 for v in VERSIONS}
    pa = {v: np.abs(np.fft.fft2(added[v].image)) ** 2 for v in VERSIONS}
    frame = sky_frame(shape, obs.jacobian)
    out[0] = _responses({v: spin2_moments(ps[v] + pa[v], frame) for v in VERSIONS}, delta)
    out[1] = _responses({v: spin2_moments(ps[v], frame) for v in VERSIONS}, delta)
    return out


def noise_shear_response(obs, rng, delta=0.01, psf="dilated"):
    """A pure-noise stamp at ``obs``'s weight through metacal's operations, with and without the symmetrising noise
    (the same stamp noise), and its versions' spin-2 moments' finite differences (a Hann window over the inner
    pixels): an array of :data:`SHAPE`."""
    good = obs.weight > 0
    noise = np.where(good, rng.normal(size=obs.weight.shape) / np.sqrt(np.where(good, obs.weight, 1.0)), 0.0)
    o = _noise_obs(obs, noise, obs.weight)
    seed = int(rng.integers(1 << 62))
    out = np.empty(SHAPE)
    inner = tuple(n - 2 * EDGE for n in obs.weight.shape)
    frame, window = sky_frame(inner, obs.jacobian), np.outer(np.hanning(inner[0]), np.hanning(inner[1]))
    for k, gen in enumerate((np.random.default_rng(seed), FixedDraw())):
        v = metacal_observations(o, delta, gen, fit_moffat=False, psf=psf)
        q = {}
        for name in VERSIONS:
            a = v[name].image[EDGE:-EDGE, EDGE:-EDGE]
            q[name] = spin2_moments(np.abs(np.fft.fft2((a - a.mean()) * window)) ** 2, frame)
        out[k] = _responses(q, delta)
    return out


def report(rows, label):
    """Print the mean responses of ``rows`` (n x SHAPE) with their errors, and what the symmetrising noise leaves
    of the noise's shear response (the mean of dq1/dg1 and dq2/dg2) in each band."""
    n = len(rows)
    mean, err = rows.mean(0), rows.std(0) / np.sqrt(n)
    print(f"{label}, {n} exposures:")
    print(f"  {'':22s}{'with the symmetrising noise (shipped)':>40s}{'without it':>24s}")
    names = ("dq1/dg1", "dq2/dg2", "dq2/dg1", "dq1/dg2")
    for b, band in enumerate(("every K", "low-pass")):
        for i, name in enumerate(names):
            print(f"  {band:9s} {name:12s}{mean[0, b, i]:+14.6f} +- {err[0, b, i]:.6f}{'':12s}"
                  f"{mean[1, b, i]:+10.5f} +- {err[1, b, i]:.5f}")
    for b, band in enumerate(("every wavevector", f"low-pass {LOW_PASS}\"")):
        own = rows[:, 1, b, :2].mean()
        left = rows[:, 0, b, :2].mean(axis=1)
        print(f"  left by the symmetrising noise ({band}): {left.mean() / own:+.2e} +- "
              f"{left.std() / np.sqrt(n) / abs(own):.2e} of the unsymmetrised noise's shear response ({own:+.4f})")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-objects", type=int, default=200, help="objects (each with --n-exposures exposures)")
    ap.add_argument("--n-exposures", type=int, default=7)
    ap.add_argument("--stamp-size", type=int, default=64)
    ap.add_argument("--population", choices=["paper", "outside"], default="outside",
                    help="the galaxies ring_test.py would draw (they set only the stamps' PSFs and Jacobians here)")
    ap.add_argument("--size-range", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
                    help="with --population outside: half-light radii (arcsec), as ring_test.py's")
    ap.add_argument("--psf-e-max", type=float, default=0.1,
                    help="the PSFs' |e| is uniform up to this, at a uniform angle (ring_test.py's; 0: round PSFs)")
    ap.add_argument("--delta", type=float, default=0.01, help="metacal's shear step")
    ap.add_argument("--metacal-psf", choices=["dilated", "round"], default="dilated")
    ap.add_argument("--no-monte-carlo", action="store_true", help="the expected spectra only (no pure-noise stamps)")
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    pop = None
    if args.population == "outside":
        pop = (functools.partial(outside_population, hlr_range=tuple(args.size_range)) if args.size_range
               else outside_population)
    t0 = time.perf_counter()
    expected, noisy = [], []
    for _ in range(args.n_objects):
        (obs, _truth), = ring_set(1, (0.0, 0.0), rng, n_rotations=1, n_exposures=args.n_exposures, snr_range=(10, 40),
                                  stamp_size=args.stamp_size, rotate_exposures=True, population=pop,
                                  psf_e_max=args.psf_e_max, profile=outside_profile if pop is not None else None)
        for o in obs:
            expected.append(expected_noise_response(o, args.delta, args.metacal_psf))
            if not args.no_monte_carlo:
                noisy.append(noise_shear_response(o, rng, args.delta, args.metacal_psf))
    print(f"metacal's versions' noise: {args.n_objects} objects x {args.n_exposures} exposures, {args.stamp_size}-pixel "
          f"stamps, rotated pixel grids, Moffat PSFs of |e| up to {args.psf_e_max:g}; new PSF {args.metacal_psf}, "
          f"delta = {args.delta}; {time.perf_counter() - t0:.0f} s")
    report(np.array(expected), "expected (impulse responses)")
    if noisy:
        report(np.array(noisy), "pure-noise stamps")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
