"""Metacal's own k-space operations (shearfit.calib.kspace) against GalSim and the discrete transform."""

import galsim
import numpy as np
import pytest

from shearfit.calib import kspace, metacal
from shearfit.engine.kernel import USE_KERNEL

from test_metacal import PIX, _obs


def _dtft(im, kx, ky, n):
    """The discrete-time transform of ``im`` about its pixel (ny // 2, nx // 2) at 2 pi (kx, ky) / n."""
    ny, nx = im.shape
    y, x = np.mgrid[:ny, :nx]
    return np.array([np.sum(im * np.exp(-2j * np.pi * (a * (x - nx // 2) + b * (y - ny // 2)) / n))
                     for a, b in zip(kx, ky)])


def test_quintic_kernel_is_galsims():
    x = np.linspace(-3.5, 3.5, 20001)
    assert np.abs(kspace.quintic(x) - galsim.Quintic().xval(x)).max() < 1e-14


@pytest.mark.parametrize("shape", [(48, 48), (25, 25), (41, 36)])
def test_table_points_are_the_discrete_transform_and_between_them_close(shape):
    """At the padded grid's points the interpolated transform is the images' discrete-time transform (to
    rounding), for even, odd and oblong images; between them within 5e-4 of the peak (the quintic on a grid
    padded four times); every image of the table with one set of weights."""
    rng = np.random.default_rng(3)
    ims = [rng.normal(size=shape), rng.normal(size=shape) + 1.0]
    n = kspace.padded_size(shape)
    table = kspace.padded_transforms(ims, n)
    kx = np.array([0.0, 3.0, -7.0, 50.0, -n / 2])
    ky = np.array([0.0, -2.0, 11.0, -90.0, n / 2 - 1])
    at = kspace.kvalues(table, kx, ky)
    tx, ty = rng.uniform(-n / 2, n / 2, (2, 200))
    between = kspace.kvalues(table, tx, ty)
    for t, im in enumerate(ims):
        peak = np.abs(im).sum()
        assert np.abs(at[:, t] - _dtft(im, kx, ky, n)).max() < 1e-12 * peak
        assert np.abs(between[:, t] - _dtft(im, tx, ty, n)).max() < 5e-4 * peak


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled loops are not built")
def test_compiled_interpolation_is_the_numpy_reference():
    rng = np.random.default_rng(4)
    ims = [rng.normal(size=(48, 48)), rng.normal(size=(48, 48)), rng.normal(size=(25, 25))]
    n = kspace.padded_size((48, 48))
    table = kspace.padded_transforms(ims, n)
    tx, ty = rng.uniform(-n / 2 - 4, n / 2 + 4, (2, 3000))   # across the periodic and Hermitian edges
    # and points periods away, at the table's own points and the edges' exact values
    far = np.array([-5.3 * n, -2 * n - 0.5, -n, -n / 2, -1e-9, 0.0, n / 2, n - 2.5, 3.7 * n])
    tx, ty = np.concatenate([tx, far, far[::-1]]), np.concatenate([ty, far[::-1], far])
    for sub in (table, table[2:3]):
        ref = kspace.kvalues_numpy(sub, tx, ty)
        assert np.abs(kspace.kvalues(sub, tx, ty) - ref).max() < 1e-12 * np.abs(ref).max()


JACOBIANS = [PIX * np.array([[-1.0, 0.0], [0.0, 1.0]]), PIX * np.array([[0.3, -0.95], [0.94, 0.31]])]


def _any_point_maxk(col, J, thr=kspace.MAXK_THRESHOLD):
    """The band as the largest sky wavenumber of any padded-grid point above the threshold (GalSim's
    calculate_maxk's test, shearfit's band before session 97), at most the Nyquist disc's pi / s_max."""
    kx, ky, xx = kspace._band_grid(col.shape[1], metacal._LANCZOS.kval)
    above = np.abs(col) * xx > thr * abs(col[0, 0])
    jit = np.linalg.inv(J).T
    ksky = np.hypot(jit[0, 0] * kx + jit[0, 1] * ky, jit[1, 0] * kx + jit[1, 1] * ky)
    return min(ksky[above].max(), np.pi / np.linalg.svd(J, compute_uv=False)[0])


@pytest.mark.parametrize("J", JACOBIANS)
def test_band_of_a_psf_model_with_noise_stays_at_the_psfs(J):
    """A PSF image with white noise of a fitted pixel model's level (2e-5 of the flux per pixel of a 25-pixel
    image: 5e-4 of it per Fourier mode, half the threshold): the band stays within 3 % of the noise-free image's
    (most of each ring's points fall below the threshold where the PSF's do), where the largest wavenumber of any
    point above the threshold reaches the Nyquist disc; for a PSF wide enough that the noise-free band lies well
    inside it (0.75-0.9")."""
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    xk = metacal._LANCZOS.kval
    rng = np.random.default_rng(7)
    nyquist = np.pi / np.linalg.svd(J, compute_uv=False)[0]
    for fwhm in (0.75, 0.9):
        img = draw_psf_image(moffat_psf(fwhm, 3.0, 0.05, -0.03), J, size=25)
        img = img / img.sum()
        n = kspace.padded_size(img.shape, (48, 48))
        clean = kspace.band_maxk(kspace.padded_transforms([img], n)[0], xk, J)
        assert clean < 0.9 * nyquist, fwhm
        for seed in range(3):
            noisy = kspace.padded_transforms([img + rng.normal(0.0, 2e-5, img.shape)], n)[0]
            assert abs(kspace.band_maxk(noisy, xk, J) / clean - 1) < 0.03, (fwhm, seed)
            assert _any_point_maxk(noisy, J) == pytest.approx(nyquist, rel=1e-9), (fwhm, seed)


@pytest.mark.parametrize("J", JACOBIANS)
def test_band_edge_is_the_first_ring_mostly_below_the_threshold(J):
    """band_edge against a count made here point by point from the padded grid's wavevectors: the inner radius of
    the first ring (one grid step wide) where at most half of the points lie above the threshold, natively and for a
    PSF oversampled 3 times, with and without noise, for thresholds that keep many points, a few and none (a band of
    0)."""
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    xk = metacal._LANCZOS.kval
    rng = np.random.default_rng(5)
    for k in (1, 3):
        for fwhm, noise in ((0.45, 0.0), (0.6, 0.0), (0.9, 0.0), (0.6, 1e-4)):
            img = draw_psf_image(moffat_psf(fwhm, 3.0, 0.05, -0.03), J, size=25 * k, oversampling=k)
            img = img + rng.normal(0.0, noise, img.shape)
            n = kspace.padded_size(img.shape)
            col = kspace.padded_transforms([img], n)[0]
            kx, ky, xx = kspace._band_grid(n, xk)
            radius = np.hypot(kx, ky) * n / (2 * np.pi)
            above = np.abs(col) * xx
            for thr in (1e-3, 0.3, 0.97, 2.0):
                edge = kspace.band_edge(col, xk, thr)
                b = int(round(edge * n / (2 * np.pi)))
                assert abs(edge - 2 * np.pi * b / n) < 1e-12
                for ring in range(b + 1):
                    sel = (radius >= ring - 1e-9) & (radius < ring + 1 - 1e-9)
                    if not sel.any():
                        continue
                    share = np.mean(above[sel] > thr * abs(col[0, 0]))
                    assert (share <= 0.5) if ring == b else (share > 0.5), (k, fwhm, noise, thr, ring)
                assert (edge > 0.0) if thr < 0.9 else (edge >= 0.0)
            assert kspace.band_edge(col, xk, 2.0) == 0.0 and kspace.band_maxk(col, xk, J / k, 2.0) == 0.0


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled loops are not built")
def test_compiled_ring_count_is_numpys():
    """band_edge's compiled count (``band_rings``, its test on squares) gives numpy's counts ring by ring, also where
    points lie within rounding of the threshold (planted at 1 -+ 1e-14 and 1 -+ 1e-13 of it, which the squares alone
    cannot decide: numpy's test there), on a table's first rows alone, and where more such points than its room are
    found (numpy's count instead); the edges of noisy PSF tables are numpy's."""
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    xk = metacal._LANCZOS.kval
    rng = np.random.default_rng(9)
    img = draw_psf_image(moffat_psf(0.6, 3.0, 0.05, -0.03), JACOBIANS[1], size=25)
    img = img / img.sum() + rng.normal(0.0, 1e-4, img.shape)
    n = kspace.padded_size(img.shape, (48, 48))
    col = np.array(kspace.padded_transforms([img], n)[0])
    xx = kspace._band_grid(n, xk)[2]
    thr = kspace.MAXK_THRESHOLD * abs(col[0, 0])
    # points moved onto the threshold, within rounding of it (their phase kept)
    pick = rng.choice(col.size, 40, replace=False)
    f = np.array([1 - 1e-14, 1 + 1e-14, 1 - 1e-13, 1 + 1e-13] * 10)
    flat, xflat = col.ravel(), xx.ravel()
    flat[pick] = flat[pick] / np.abs(flat[pick]) * (thr / xflat[pick]) * f
    xx2, labels = kspace._ring_tables(n, xk)
    total = kspace._ring_totals(n)
    for rows in (col.shape[0], 40):
        part = np.ascontiguousarray(col[:rows])
        ref = np.bincount(kspace._ring_labels(n)[:rows][np.abs(part) * xx[:rows] > thr], minlength=total.size)
        above = np.empty(total.size, np.int64)
        near = np.empty(256, np.int64)
        got = kspace.KERNEL.band_rings(part, xx2, labels, thr, above, near)
        assert got >= 1   # the planted points inside these rows come back for numpy's test
        q = near[:got]
        np.add.at(above, labels.ravel()[q][np.abs(part.ravel()[q]) * xx.ravel()[q] > thr], 1)
        assert np.array_equal(above, ref), rows
        assert kspace.KERNEL.band_rings(part, xx2, labels, thr, np.empty(total.size, np.int64),
                                        np.empty(0, np.int64)) == -1
    edges = {}
    tables = (col, col[:40], kspace.padded_transforms([img + rng.normal(0.0, 2e-4, img.shape)], n)[0])
    for use in (True, False):
        kspace.USE_KERNEL = use
        try:
            edges[use] = [kspace.band_edge(c, xk) for c in tables]
        finally:
            kspace.USE_KERNEL = USE_KERNEL
    assert edges[True] == edges[False]


@pytest.mark.parametrize("J", JACOBIANS)
def test_table_made_within_the_band_is_the_whole_tables(J):
    """padded_transform_within makes the columns it keeps to the bit of the whole table's, leaves the others only
    where every wavevector there lies below the band's threshold (so that band_edge of the columns made is the
    whole table's), and makes the whole table where the transform stays above it far out (a PSF image
    with pixel noise) or where the columns asked for are all of them; padded_transform_rest makes the rest, the
    whole table's to the bit."""
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    xk = metacal._LANCZOS.kval
    rng = np.random.default_rng(3)
    seen = set()
    for k, fwhm, noise in ((3, 0.6, 0.0), (3, 0.9, 0.0), (3, 0.45, 0.0), (1, 0.6, 0.0), (3, 0.6, 1e-5)):
        img = draw_psf_image(moffat_psf(fwhm, 3.0, 0.05, -0.03), J, size=48 * k, oversampling=k)
        img = img + rng.normal(0.0, noise, img.shape)
        n = kspace.padded_size(img.shape)
        whole = kspace.padded_transforms([img], n)
        for columns in (1, n // (2 * k) + 4, n // 2 + 1):
            table, m = kspace.padded_transform_within(img, n, columns, xk)
            assert table.shape == whole.shape and min(columns, n // 2 + 1) <= m <= n // 2 + 1
            assert np.array_equal(table[0, :m], whole[0, :m]), (k, fwhm, noise, columns)
            assert kspace.band_edge(table[0, :m], xk) == kspace.band_edge(whole[0], xk)
            rest = table.copy()   # made whole in place: the whole table to the bit
            kspace.padded_transform_rest(img, rest, m)
            assert np.array_equal(rest, whole)
            seen.add((noise > 0, m == n // 2 + 1))
            if noise > 0:
                assert m == n // 2 + 1   # its transform is above the threshold out to the grid's edge
    # some tables made in part, and the noisy image's whole
    assert (False, False) in seen and (True, True) in seen


@pytest.mark.parametrize("size", [48, 47])
@pytest.mark.parametrize("psf", ["dilated", "round"])
def test_noise_turned_back_on_the_bands_is_the_turned_image(size, psf, monkeypatch):
    """own_kspace_images(turn_noise=True): each version plus its noise turned back (``np.rot90(..., -1)``), the
    turn made on the bands (turned_band's phase for an even stamp, none for an odd one), then the first noise
    turned back, are the images turned in pixels and summed, to rounding; the compiled bands (the versions'
    interpolation, the unsheared version read from the table's own points, the turn) are the numpy lines', on
    a reflected and on a rotated, sheared pixel grid."""
    names = tuple(metacal.VERSIONS)
    for J in JACOBIANS:
        obs = _obs(0.3, (0.2, -0.1), snr=40, n_exp=1, seed=4, J=J)[0]
        image = obs.image[:size, :size]
        noise = np.rot90(np.random.default_rng(6).normal(size=image.shape), 1)
        new = None if psf == "dilated" else metacal.round_psf(obs.psf, J, 0.01, image.shape)
        out = {}
        for kernel in (True, False):
            with monkeypatch.context() as m:
                m.setattr(kspace, "USE_KERNEL", kernel and USE_KERNEL)
                apart = np.asarray(metacal.own_kspace_images(image, noise, obs.psf, J, 0.01, names, new_psf=new))
                out[kernel] = (apart, np.asarray(metacal.own_kspace_images(image, noise, obs.psf, J, 0.01, names,
                                                                           new_psf=new, turn_noise=True)))
        apart, turned = out[True]
        back = np.rot90(apart[1::2], -1, axes=(1, 2))
        peak = np.abs(apart).max()
        assert turned.shape == (len(names) + 1,) + image.shape
        assert np.abs(turned[:-1] - (apart[0::2] + back)).max() < 1e-13 * peak
        assert np.abs(turned[-1] - back[0]).max() < 1e-13 * peak
        for a, b in zip(out[True], out[False]):
            assert np.abs(a - b).max() < 1e-13 * peak
    with pytest.raises(ValueError, match="square"):
        metacal.own_kspace_images(image[:, :-1], noise[:, :-1], obs.psf, J, 0.01, names, turn_noise=True)


class _VersionsSpy:
    """The compiled kernel, its band loop ``name`` watched: each call's (step, number of versions) appended to
    ``called`` (the versions' matrices argument ``a_arg``, the step ``step_arg``, the output last), and where it
    takes several versions, each one's band checked to be the one its own call gives, to the bit."""

    def __init__(self, name, a_arg, step_arg, called):
        self._kernel = kspace.KERNEL
        self._real = getattr(self._kernel, name)
        self._args = a_arg, step_arg
        self._called = called
        setattr(self, name, self._watched)

    def __getattr__(self, name):
        return getattr(self._kernel, name)

    def _watched(self, *a):
        ia, istep = self._args
        nv = np.asarray(a[ia]).size // 4
        self._called.append((a[istep], nv))
        self._real(*a)
        for v in range(nv if nv > 1 else 0):
            alone = np.full(a[-1].shape[1:], np.nan, complex)
            self._real(*a[:ia], np.ascontiguousarray(a[ia][v]), *a[ia + 1:-1], alone)
            assert np.array_equal(alone, a[-1][v])


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled kernel is not built")
@pytest.mark.parametrize("shape", [(48, 48), (47, 47), (40, 33)])
def test_compiled_padded_rows_are_the_numpy_lines(shape, monkeypatch):
    """padded_transforms_rows of two images of one shape, laid out and placed by the compiled loops (padded_rows,
    padded_place), is the numpy lines' array to the bit, and padded_transforms' transposed."""
    rng = np.random.default_rng(8)
    images = [rng.normal(size=shape), np.rot90(rng.normal(size=shape[::-1]), 1)]
    n = kspace.padded_size(shape)
    got = kspace.padded_transforms_rows(images, n)
    monkeypatch.setattr(kspace, "USE_KERNEL", False)
    assert np.array_equal(got, kspace.padded_transforms_rows(images, n))
    assert np.array_equal(got, kspace.padded_transforms(images, n).transpose(2, 1, 0))


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled kernel is not built")
def test_sheared_bands_of_a_native_psf_in_one_call_are_each_ones_own(monkeypatch):
    """A PSF image on the stamp's pixels: the sheared versions of one band radius go through the compiled band in one
    call (quintic_band with their matrices together), each version's band that of its own call to the bit, with and
    without the noise's turn; the version without shear alone, at the table's own points."""
    called = []
    monkeypatch.setattr(kspace, "KERNEL", _VersionsSpy("quintic_band", 4, 9, called))
    names = tuple(metacal.VERSIONS)
    for J in JACOBIANS:
        obs = _obs(0.3, (0.2, -0.1), snr=40, n_exp=1, seed=4, J=J)[0]
        noise = np.rot90(np.random.default_rng(6).normal(size=obs.image.shape), 1)
        for turn in (False, True):
            metacal.own_kspace_images(obs.image, noise, obs.psf, J, 0.01, names, turn_noise=turn)
    assert sum(nv for _, nv in called) == 2 * 2 * len(names)
    assert all(nv == 1 for s, nv in called if s > 0) and any(nv == len(names) - 1 for _, nv in called)


@pytest.mark.parametrize("J", JACOBIANS)
def test_band_edge_is_where_galsims_psf_transform_falls_below_the_threshold(J):
    """The deconvolution's band: GalSim's transform of the same interpolated PSF exceeds 1e-3 of its flux in more
    than half of 720 directions at 0.96 of the band's edge, and in at most half of them 4 % beyond it, unless the
    band is the pixels' Nyquist disc (a PSF sharp enough to be aliased), which it then equals; within 20 % of the
    largest wavenumber of any point above the threshold (GalSim's maxk test; the 25-pixel image's truncation lifts
    points along the axes above it beyond the PSF's core)."""
    ang = np.linspace(0, 2 * np.pi, 721)[:-1]
    for fwhm in (0.6, 0.75, 0.9):
        psf = galsim.Moffat(fwhm=fwhm, beta=3.0).shear(g1=0.04, g2=0.03)
        img = psf.drawImage(nx=25, ny=25, wcs=metacal._wcs(J), method="no_pixel").array
        ii = metacal._interpolated(img, metacal._wcs(J))
        n = kspace.padded_size(img.shape, (48, 48))
        col = kspace.padded_transforms([img], n)[0]
        band = kspace.band_maxk(col, metacal._LANCZOS.kval, J)
        nyquist = np.pi / np.linalg.svd(J, compute_uv=False)[0]

        def above(radius):
            amp = np.array([abs(ii.kValue(galsim.PositionD(radius * np.cos(a), radius * np.sin(a)))) for a in ang])
            return np.mean(amp > 1e-3 * ii.flux)

        if band < nyquist:
            assert above(0.96 * band) > 0.5 and above(1.04 * band) <= 0.5, fwhm
        else:
            assert abs(band / nyquist - 1) < 1e-12 and above(0.99 * band) > 0.5, fwhm
        assert 0.8 < band / _any_point_maxk(col, J) <= 1.0 + 1e-12, fwhm


def _own_and_galsims(obs, psf, monkeypatch):
    """metacal_observations of ``obs`` by the own operations (out[True]) and by GalSim's objects (out[False]), the
    same symmetrising noise; the kept pixels and the noshear version's peak there."""
    out = {}
    for own in (True, False):
        monkeypatch.setattr(metacal, "OWN_KSPACE", own)
        out[own] = metacal.metacal_observations(obs, rng=np.random.default_rng(5), psf=psf)
    good = out[False]["noshear"].weight > 0
    return out, good, np.abs(out[False]["noshear"].image[good]).max()


@pytest.mark.parametrize("J", JACOBIANS)
@pytest.mark.parametrize("snr", [None, 40])
@pytest.mark.parametrize("psf", ["dilated", "round"])
def test_own_versions_are_galsims_with_its_band(J, snr, psf, monkeypatch):
    """Given GalSim's band (its maxk of the PSF), the versions made by shearfit's own k-space operations are
    those of GalSim's objects to 1e-6 of the peak without noise and 2e-5 with it (the two pad the PSF's
    transform differently), weights to 1e-5, on a reflected and on a rotated, sheared pixel grid; with either
    new PSF (the round one's image convolved as an interpolated image by both)."""
    obs = _obs(0.3, (0.2, -0.1), snr=snr, n_exp=1, seed=4, J=J)[0]
    maxk = metacal._interpolated(obs.psf, metacal._wcs(J), calculate_maxk=True).maxk
    monkeypatch.setattr(kspace, "band_maxk", lambda *a, **k: maxk)
    out, good, peak = _own_and_galsims(obs, psf, monkeypatch)
    tol = 1e-6 if snr is None else 2e-5
    for name, ref in out[False].items():
        assert np.abs(out[True][name].image - ref.image)[good].max() < tol * peak, name
        assert np.allclose(out[True][name].weight, ref.weight, rtol=1e-5, atol=0)
        assert np.array_equal(out[True][name].psf, ref.psf)


@pytest.mark.parametrize("J", JACOBIANS)
@pytest.mark.parametrize("psf", ["dilated", "round"])
def test_own_versions_of_an_oversampled_psf_are_galsims(J, psf, monkeypatch):
    """A PSF image 3 times finer than the stamp (the stamp's and the PSF's x-interpolants at their own pixels'
    wavevectors, which no longer cancel): given GalSim's band, a noise-free galaxy's versions (no symmetrising
    noise) are those of GalSim's objects to 2e-6 of the peak, on a reflected and on a rotated, sheared pixel grid, with
    either new PSF. At SNR 40 with the symmetrising noise, whose deconvolution peaks at the band's edge, the
    versions agree to 5e-3 of the galaxy's peak and the weights to 1e-3: where the band reaches past the stamp's Nyquist (the
    reflected grid here) GalSim leaves out its edge's points on the axes, 3e-5 inside its maxk, that the own
    operations keep (seen: 1.9e-3 and 2.8e-4; 5e-5 and 1e-6 on the rotated grid)."""
    import shearfit
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    k = 3
    free = _obs(0.3, (0.2, -0.1), n_exp=1, seed=4, J=J)[0]
    pim = draw_psf_image(moffat_psf(0.6, 3.0, 0.04, 0.03), J, size=25 * k, oversampling=k)
    maxk = metacal._interpolated(pim, metacal._wcs(J, k), calculate_maxk=True).maxk
    monkeypatch.setattr(kspace, "band_maxk", lambda *a, **kw: maxk)
    monkeypatch.setattr(kspace, "maxk_of_edge", lambda *a, **kw: maxk)   # (the oversampled PSF's way)
    names = tuple(metacal.VERSIONS)
    new = None if psf == "dilated" else metacal.round_psf(pim, J / k, 0.01, pim.shape)
    zero = np.zeros(free.image.shape)
    own = np.asarray(metacal.own_kspace_images(free.image, zero, pim, J, 0.01, names, new_psf=new, k=k))
    ref = np.asarray(metacal._galsim_images(free.image, zero, pim, metacal._wcs(J), metacal._wcs(J, k), 0.01, names,
                                            new_psf_image=new))
    inner = np.zeros(free.image.shape, bool)
    inner[4:-4, 4:-4] = True
    for v in range(0, 2 * len(names), 2):
        assert np.abs(own[v] - ref[v])[inner].max() < 2e-6 * np.abs(ref[v]).max(), names[v // 2]
    base = _obs(0.3, (0.2, -0.1), snr=40, n_exp=1, seed=4, J=J)[0]
    obs = shearfit.Observation(image=base.image, weight=base.weight, jacobian=J, offset=base.offset, psf=pim,
                               psf_oversampling=k)
    out, good, peak = _own_and_galsims(obs, psf, monkeypatch)
    for name, r in out[False].items():
        assert np.abs(out[True][name].image - r.image)[good].max() < 5e-3 * peak, name
        assert np.allclose(out[True][name].weight, r.weight, rtol=1e-3, atol=0)
        assert np.array_equal(out[True][name].psf, r.psf)


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled loops are not built")
@pytest.mark.parametrize("k", [2, 3])
def test_compiled_oversampled_bands_are_the_numpy_lines(k, monkeypatch):
    """quintic_band_os (an oversampled PSF's versions in one compiled loop, the x-interpolant's transform from a
    table within 3e-10 of GalSim's) gives the numpy lines' images to 1e-9 of their largest, with and without the
    noise's turn, with either new PSF, on a reflected and on a rotated, sheared pixel grid; the table itself is
    GalSim's transform to 3e-10 between its points."""
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    xt, h = metacal._x_table(4)
    u = np.random.default_rng(1).uniform(0, 4 * np.pi - 0.01, 20000)
    t = u / h
    i = t.astype(int)
    f = t - i
    xm = np.where(i > 0, xt[np.maximum(i - 1, 0)], xt[1])   # the compiled Catmull-Rom step, in numpy
    cr = xt[i] + f * (0.5 * (xt[i + 1] - xm) + f * (xm - 2.5 * xt[i] + 2 * xt[i + 1] - 0.5 * xt[i + 2]
                                                      + f * (1.5 * (xt[i] - xt[i + 1]) + 0.5 * (xt[i + 2] - xm))))
    assert np.abs(cr - metacal._LANCZOS.kval(u)).max() < 3e-10
    names = tuple(metacal.VERSIONS)
    for J in JACOBIANS:
        obs = _obs(0.3, (0.2, -0.1), snr=40, n_exp=1, seed=4, J=J)[0]
        pim = draw_psf_image(moffat_psf(0.6, 3.0, 0.04, 0.03), J, size=25 * k, oversampling=k)
        noise = np.rot90(np.random.default_rng(6).normal(size=obs.image.shape), 1)
        for new in (None, metacal.round_psf(pim, J / k, 0.01, pim.shape)):
            for turn in (False, True):
                got = {}
                for kernel in (True, False):
                    monkeypatch.setattr(kspace, "USE_KERNEL", kernel)
                    got[kernel] = np.asarray(metacal.own_kspace_images(obs.image, noise, pim, J, 0.01, names, k=k,
                                                                       new_psf=new, turn_noise=turn))
                assert np.abs(got[True] - got[False]).max() < 1e-9 * np.abs(got[False]).max()


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled loops are not built")
@pytest.mark.parametrize("k", [2, 3])
def test_bands_of_a_psf_k_times_the_stamp_read_both_tables_at_the_same_taps(k, monkeypatch):
    """A PSF image k times the stamp's size (its padded grid k times the stamp's, as the simulated fields' given
    PSF images are): the compiled band reads the stamp's and the PSF's rows at the same taps (quintic_band_rows, the
    version without shear at the tables' own points, the sheared ones in one call, each one's band that of its own
    call to the bit), and gives the numpy lines' images to 1e-9 of their largest, with and without the noise's turn,
    with either new PSF, on a reflected and on a rotated, sheared grid; the stamp's transforms in rows are
    padded_transforms' to the bit."""
    from shearfit.simulate.stamps import draw_psf_image, moffat_psf

    called = []
    spy = _VersionsSpy("quintic_band_rows", 8, 14, called)
    names = tuple(metacal.VERSIONS)
    for J, fwhm in zip(JACOBIANS, (0.9, 0.6)):
        obs = _obs(0.3, (0.2, -0.1), snr=40, n_exp=1, seed=4, J=J)[0]
        size = obs.image.shape[0]
        pim = draw_psf_image(moffat_psf(fwhm, 3.0, 0.04, 0.03), J, size=size * k, oversampling=k)
        assert kspace.padded_size(pim.shape) == k * kspace.padded_size(obs.image.shape)
        noise = np.rot90(np.random.default_rng(6).normal(size=obs.image.shape), 1)
        n_s = kspace.padded_size(obs.image.shape)
        assert np.array_equal(kspace.padded_transforms_rows([obs.image, noise], n_s),
                              kspace.padded_transforms([obs.image, noise], n_s).transpose(2, 1, 0))
        for new in (None, metacal.round_psf(pim, J / k, 0.01, pim.shape)):
            for turn in (False, True):
                got = {}
                for use in (True, False):
                    monkeypatch.setattr(kspace, "USE_KERNEL", use)
                    monkeypatch.setattr(kspace, "KERNEL", spy)
                    got[use] = np.asarray(metacal.own_kspace_images(obs.image, noise, pim, J, 0.01, names, k=k,
                                                                    new_psf=new, turn_noise=turn))
                assert np.abs(got[True] - got[False]).max() < 1e-9 * np.abs(got[False]).max()
    # every band through the rows; the version without shear at the tables' own points where its band lies within
    # half the stamp's period (the wider PSF's); the sheared versions of one band radius in one call
    n_bands = 2 * 2 * 2 * len(names)
    assert sum(nv for _, nv in called) == n_bands and 0 < sum(s > 0 for s, _ in called) <= n_bands // len(names)
    assert all(nv == 1 for s, nv in called if s > 0) and any(nv == len(names) - 1 for _, nv in called)


def test_other_interpolants_take_galsims_path(monkeypatch):
    """The own operations serve native and oversampled PSFs with the quintic k-interpolant; another interpolant
    or GalSim's own FFT grid goes through GalSim's objects."""
    calls = []
    real = metacal.own_kspace_images
    monkeypatch.setattr(metacal, "own_kspace_images", lambda *a, **k: calls.append(1) or real(*a, **k))
    obs = _obs(0.3, (0.2, -0.1), n_exp=1, seed=4)[0]
    metacal.metacal_observations(obs, rng=np.random.default_rng(1))
    assert len(calls) == 1
    for name, value in (("K_INTERPOLANT", "cubic"), ("WRAP_STAMPS", 0)):
        with monkeypatch.context() as m:
            m.setattr(metacal, name, value)
            metacal.metacal_observations(obs, rng=np.random.default_rng(1))
    assert len(calls) == 1


def _fold_brute(arr, n):
    """One band folded point by point from the full plane it stands for: F(i, j) stored for i >= 0, F(-i, -j) =
    conj F(i, j); every point lands at (i mod n, j mod n), kept where that column is stored (<= n // 2)."""
    r = arr.shape[1] - 1
    half = n // 2
    out = np.zeros((n, half + 1), complex)
    for j in range(-r, r + 1):
        for i in range(-r, r + 1):
            v = arr[j + r, i] if i >= 0 else np.conj(arr[-j + r, -i])
            if i % n <= half:
                out[j % n, i % n] += v
    return out


@pytest.mark.parametrize("n", [64, 48, 45, 8, 7])
def test_band_fold_is_galsims_wrap_and_the_full_planes_fold(n):
    """The versions' bands are folded onto the FFT grid as the full plane they stand for folds (periodic in n,
    the stored half's mirrors conjugated), which for even n is GalSim's ``Image.wrap(hermitian='x')``: for
    bands narrower than the grid, as wide as it, and several times wider (GalSim's own k grid)."""
    rng = np.random.default_rng(n)
    half = n // 2
    for r in sorted({max(half - 2, 0), half, half + 1, n - 1, n, n + 3, 2 * n + 1}):
        arr = rng.normal(size=(2, 2 * r + 1, r + 1)) + 1j * rng.normal(size=(2, 2 * r + 1, r + 1))
        mine = metacal.fold_band(arr, n)
        for b in range(2):
            assert np.abs(mine[b] - _fold_brute(arr[b], n)).max() < 1e-12
            if n % 2 == 0 and r >= half:
                full = galsim.ImageCD(galsim.BoundsI(0, r, -r, r), scale=1.0)
                full.array[:, :] = arr[b]
                ref = full.wrap(galsim.BoundsI(0, half, -half, half - 1), hermitian="x").array
                assert np.abs(mine[b][np.arange(-half, half) % n] - ref).max() < 1e-12


@pytest.mark.parametrize("n", [64, 48, 45])
def test_band_images_are_the_folded_planes_images(n):
    """band_images draws each band as the inverse transform of its full plane folded onto the grid
    (``_fold_brute``), at the stamp's pixels (origin at (ny // 2, nx // 2)), whatever the band's width: narrower
    than the grid, reaching its Nyquist row and column exactly (folded in place, the usual wide band), wider."""
    rng = np.random.default_rng(100 + n)
    half = n // 2
    rs = [max(half - 2, 0), half, half, half + 1, n + 3]
    for shape in ((min(n, 48), min(n, 40)), (n + 7, n - 3)):   # (the second wider than the period: it wraps)
        _band_images_match(n, shape, rs, rng)


def _band_images_match(n, shape, rs, rng):
    items = [(r, rng.normal(size=(2 * r + 1, r + 1)) + 1j * rng.normal(size=(2 * r + 1, r + 1))) for r in rs]
    got = metacal.band_images(shape, n, items)
    iy = (np.arange(shape[0]) - shape[0] // 2) % n
    ix = (np.arange(shape[1]) - shape[1] // 2) % n
    for (r, arr), im in zip(items, got):
        ref = np.fft.irfft2(_fold_brute(arr, n), s=(n, n))[np.ix_(iy, ix)]
        assert np.abs(im - ref).max() < 1e-12 * np.abs(arr).sum() / n ** 2 + 1e-14


@pytest.mark.parametrize("J", JACOBIANS + [PIX * np.array([[0.62, 0.79], [0.8, -0.6]])])
def test_round_envelope_is_below_the_dilated_psf_in_every_direction_and_close_to_it(J):
    """metacal's round new PSF (``psf='round'``): at every point of the padded grid inside the band its
    envelope lies below the point's |transform| (the dilated PSF's at |K| / dilation), interpolated linearly in
    |K| or in |K|^2, it falls from 1 to 0
    without rising, and against GalSim's transform of the interpolated PSF, dilated, it stays below the least
    over 360 directions at every |K| (to 1e-6 of the flux) and within 0.05 of the flux of it inside the band
    (seen: 0.038, where the transform falls fastest across the bins one grid step wide)."""
    d = 1.02
    xk = metacal._LANCZOS.kval
    for beta, (g1, g2) in ((2.5, (0.08, 0.0)), (4.5, (0.0, -0.1)), (3.0, (0.05, 0.05))):
        psf = galsim.Moffat(fwhm=0.65, beta=beta).shear(g1=g1, g2=g2)
        img = psf.drawImage(nx=25, ny=25, wcs=metacal._wcs(J)).array
        n = kspace.padded_size(img.shape, (48, 48))
        col = kspace.padded_transforms([img], n)[0]
        maxk = kspace.band_maxk(col, xk, J)
        knots, vals = kspace.round_envelope(col, xk, J, d, maxk)
        assert vals[0] == 1.0 and vals[-1] == 0.0 and np.all(np.diff(vals) <= 0) and knots[-1] > maxk / d
        kx, ky, xx = kspace._band_grid(n, xk)
        amp = np.abs(col) * xx / (abs(col[0, 0]) * xx[0, 0])
        jit = np.linalg.inv(J).T
        ksky = np.hypot(jit[0, 0] * kx + jit[0, 1] * ky, jit[1, 0] * kx + jit[1, 1] * ky)
        inside = ksky <= maxk
        for power in (1, 2):   # linear in |K|, and in |K|^2 (round_psf's)
            env = np.interp((ksky[inside] / d) ** power, knots ** power, vals)
            assert np.all(env <= amp[inside] * (1 + 1e-12)), power
        ii = metacal._interpolated(img, metacal._wcs(J)).dilate(d)
        ang = np.linspace(0, np.pi, 361)[:-1]
        for K in np.linspace(0.0, 0.97 * maxk / d, 25):
            least = min(abs(ii.kValue(galsim.PositionD(K * np.cos(a), K * np.sin(a)))) for a in ang) / ii.flux
            env = np.interp(K, knots, vals)
            assert env <= least + 1e-6 and env >= least - 0.05, (beta, K, env, least)


@pytest.mark.parametrize("J", JACOBIANS)
def test_round_psf_image_is_round_on_the_sky_and_wider_than_the_psf(J):
    """The round PSF's image (drawn through the exposure's Jacobian, a flip in the first): GalSim's adaptive
    moments of it as a sky-frame profile give |e| < 1e-3 (seen: 4e-4) for PSFs of |e| up to 0.2, and a size
    between the PSF's and 1.3 times it (seen: 1.13-1.17)."""
    for beta, (g1, g2) in ((2.5, (0.08, 0.0)), (4.5, (0.0, -0.1))):
        psf = galsim.Moffat(fwhm=0.65, beta=beta).shear(g1=g1, g2=g2)
        img = psf.drawImage(nx=25, ny=25, wcs=metacal._wcs(J)).array
        rimg = metacal.round_psf(img, J, 0.01, (48, 48))
        assert abs(rimg.sum() - 1) < 1e-12

        def sky_moments(a):
            prof = metacal._interpolated(a, metacal._wcs(J))
            m = galsim.hsm.FindAdaptiveMom(prof.drawImage(nx=96, ny=96, scale=PIX / 3, method="no_pixel"))
            return m.observed_shape.e1, m.observed_shape.e2, m.moments_sigma

        e1, e2, s = sky_moments(rimg)
        _, _, s0 = sky_moments(img)
        assert np.hypot(e1, e2) < 1e-3, (e1, e2)
        assert s0 < s < 1.3 * s0, (s, s0)
