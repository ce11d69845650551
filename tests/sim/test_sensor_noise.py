"""The sensor's draws against closed forms (docs/physics.md §7): the counter-based normals, Poisson shot
noise at low and high counts (the pmf, chi-square), read noise on top of it, the full well, the ADC's
clipping and quantization, and a seeded frame that is the same on any number of threads."""

import numpy as np
import pytest
from polarstripe.sim import threads
from polarstripe.sim.counter_rng import normals
from polarstripe.sim.scene import load_scene
from polarstripe.sim.sensor import expose
from scipy import stats

N = 300_000


def _camera(**changes):
    """The default camera without read noise, dark current, offset and ADC limits unless given."""
    base = {"read_noise_e": 0.0, "dark_current_e_s": 0.0, "offset_dn": 0.0, "gain_e_per_dn": 1.0,
            "bits": 16, "full_well_e": 1e9}
    return load_scene(None).camera.replace(**{**base, **changes})


def _dn(cam, mean_e, seed, n=N):
    return expose(np.ones(n), cam, seed, electrons=np.full(n, float(mean_e)))


def _chi2_p(values, pmf, min_expected=5.0):
    """p-value of a chi-square test of integer ``values`` against ``pmf`` (array over 0…len − 1), the cells
    with fewer than ``min_expected`` counts pooled into one."""
    counts = np.bincount(values, minlength=pmf.size)[:pmf.size]
    expected = pmf * values.size
    keep = expected >= min_expected
    obs = np.append(counts[keep], values.size - counts[keep].sum())
    exp_ = np.append(expected[keep], values.size - expected[keep].sum())
    chi2 = np.sum((obs - exp_) ** 2 / np.maximum(exp_, 1e-300))
    return stats.chi2.sf(chi2, obs.size - 1)


def test_normals_have_the_normal_moments_and_tails():
    z = np.empty(2_000_000)
    normals(np.array([2024, 7], np.uint64), 0, z)
    n = z.size
    assert abs(z.mean()) < 5 / np.sqrt(n)
    assert abs(z.var() - 1) < 5 * np.sqrt(2 / n)
    assert abs(stats.skew(z)) < 5 * np.sqrt(6 / n) and abs(stats.kurtosis(z)) < 5 * np.sqrt(24 / n)
    assert stats.kstest(z, "norm").pvalue > 1e-3
    for t in (1.0, 3.6541528853610088, 4.5):           # inside, at and beyond the ziggurat's tail
        want = 2 * stats.norm.sf(t) * n
        assert abs((np.abs(z) > t).sum() - want) < 5 * np.sqrt(want)
    later = np.empty(1000)
    normals(np.array([2024, 7], np.uint64), 1000, later)    # pixel j's normal does not depend on the band
    assert np.array_equal(later, z[1000:2000])


@pytest.mark.parametrize("mean_e", [0.2, 4.0, 12.5, 29.5, 30.5, 250.0, 1e4])
def test_shot_noise_is_poisson(mean_e):
    """Gain 1 e⁻/DN, no read noise: the DN are the electron counts, inversion below 30 e⁻ and the
    Cornish–Fisher draw above it, both against the Poisson pmf."""
    y = _dn(_camera(), mean_e, seed=int(mean_e * 10) + 1).astype(np.int64)
    ks = np.arange(int(mean_e + 12 * np.sqrt(mean_e) + 20))
    assert _chi2_p(y, stats.poisson.pmf(ks, mean_e)) > 1e-4
    assert abs(y.mean() - mean_e) < 5 * np.sqrt(mean_e / N)
    assert abs(y.var() / mean_e - 1) < 5 * np.sqrt(2 / N) + 5 / np.sqrt(N * mean_e)


@pytest.mark.parametrize("mean_e", [0.5, 5.0, 12.0, 29.0, 31.0, 0.3, 5.06, 12.93, 29.99])
def test_exact_shot_noise_over_many_draws(mean_e):
    """2·10⁶ draws against the Poisson pmf (chi-square): the exact ones below 30 e⁻ (a tabulated count of mean
    ⌊8μ⌋/8 plus one of the rest, sim/sensor_kernels.py) on and off the table's grid, and the Cornish–Fisher
    draw just above (its total variation, 10⁻⁴, needs ~10⁸ draws to show)."""
    n = 2_000_000
    y = _dn(_camera(), mean_e, seed=int(mean_e * 100) + 3, n=n).astype(np.int64)
    assert _chi2_p(y, stats.poisson.pmf(np.arange(int(mean_e + 12 * np.sqrt(mean_e) + 20)), mean_e)) > 1e-4
    assert abs(y.mean() - mean_e) < 5 * np.sqrt(mean_e / n)


def test_shot_noise_of_a_frame_of_many_means():
    """Each pixel its own mean, 1000 means across 0…30 e⁻ (every table row and the parts between them)
    1000 pixels each: the counts against the mixture of their Poisson pmfs."""
    means = np.repeat((np.arange(1000) + 0.5) * 0.03, 1000)
    y = expose(np.ones(means.size), _camera(), 17, electrons=means).astype(np.int64)
    ks = np.arange(80)
    pmf = stats.poisson.pmf(ks[None, :], np.unique(means)[:, None]).mean(axis=0)
    assert _chi2_p(y, pmf) > 1e-4
    per_mean = y.reshape(1000, 1000).mean(axis=1)      # and no row off: each mean's average within 5σ
    assert np.all(np.abs(per_mean - np.unique(means)) < 5 * np.sqrt(np.unique(means) / 1000) + 0.01)


def test_read_noise_adds_to_a_low_poisson_count():
    """3 e⁻ mean with 0.7 e⁻ read noise, gain 1, offset 10: P(y) = Σ_k Pois(k; 3)·[Φ((y − 10 + ½ − k)/σ)
    − Φ((y − 10 − ½ − k)/σ)], neither Poisson nor normal."""
    sigma = 0.7
    y = _dn(_camera(read_noise_e=sigma, offset_dn=10.0), 3.0, seed=3).astype(np.int64)
    ks = np.arange(40)
    ys = np.arange(60)[:, None]
    pmf = (stats.poisson.pmf(ks, 3.0) * (stats.norm.cdf((ys - 10 + 0.5 - ks) / sigma)
                                         - stats.norm.cdf((ys - 10 - 0.5 - ks) / sigma))).sum(axis=1)
    assert _chi2_p(y, pmf) > 1e-4


@pytest.mark.parametrize("mean_e", [2.0, 20.0, 500.0, 2e4])
def test_emva_mean_and_variance_of_the_default_camera(mean_e):
    """μ_y = (μ_e + μ_d)/K + offset, σ_y² = (σ_r² + μ_e + μ_d)/K² + 1/12 (EMVA 1288; σ_y ≥ 1 DN here, so
    the 1/12 of the rounding holds)."""
    cam = load_scene(None).camera
    y = _dn(cam, mean_e, seed=7).astype(float)
    dark = cam.dark_current_e_s * cam.exposure_s
    k = cam.gain_e_per_dn
    var = (cam.read_noise_e ** 2 + mean_e + dark) / k ** 2 + 1 / 12
    assert abs(y.mean() - ((mean_e + dark) / k + cam.offset_dn)) < 5 * np.sqrt(var / N)
    assert abs(y.var() / var - 1) < 5 * np.sqrt(2 / N)


def test_quantization_adds_a_twelfth():
    """No read noise, 10 e⁻/DN, 100 e⁻: y = round(P/10), variance 100/10² + 1/12 (Sheppard), whole DN."""
    y = _dn(_camera(gain_e_per_dn=10.0), 100.0, seed=11).astype(float)
    assert abs(y.mean() - 10.0) < 5 * np.sqrt(1.1 / N)
    assert abs(y.var() - (1 + 1 / 12)) < 5 * np.sqrt(2 / N) * 1.1
    assert abs(y.var() - 1) > 10 * np.sqrt(2 / N)      # the rounding's 1/12 is there


def test_full_well_and_adc_saturation_fractions():
    """The full well caps the Poisson count: P(y = 1000) = P(Pois(990) ≥ 1000). An 8-bit ADC clips:
    P(y = 255) = Σ_k Pois(k; 250)·P(k + σ z ≥ 254.5)."""
    y = _dn(_camera(full_well_e=1000.0), 990.0, seed=5)
    want = stats.poisson.sf(999, 990.0)
    assert y.max() == 1000 and abs((y == 1000).mean() - want) < 5 * np.sqrt(want * (1 - want) / N)
    y = _dn(_camera(bits=8, read_noise_e=3.0), 250.0, seed=6)
    ks = np.arange(400)
    want = float(np.sum(stats.poisson.pmf(ks, 250.0) * stats.norm.sf((254.5 - ks) / 3.0)))
    assert y.max() == 255 and abs((y == 255).mean() - want) < 5 * np.sqrt(want * (1 - want) / N)


def test_bad_radiance_reads_as_dark():
    cam = _camera(read_noise_e=0.0, offset_dn=5.0)
    y = expose(np.array([np.nan, np.inf, -np.inf, -3.0, 0.0]), cam, 1, electrons=np.full(5, 1e4))
    assert np.all(y == 5)


@pytest.fixture
def restore_threads():
    before = threads.threads()
    yield
    threads.set_threads(before)


def test_a_seed_gives_one_frame_on_any_thread_count(restore_threads):
    cam = load_scene(None).camera.resized((640, 480))       # 307 200 pixels: up to 4 bands
    radiance = np.random.default_rng(0).uniform(0.0, 2.0, (480, 640)) * 10.0 ** np.linspace(-6, 2, 640)
    frames = []
    for n in (1, 2, 3):
        threads.set_threads(n)
        frames.append(expose(radiance, cam, 42))
    assert all(np.array_equal(frames[0], f) for f in frames[1:])
    assert not np.array_equal(frames[0], expose(radiance, cam, 43))
    rng = np.random.default_rng(42)
    first, second = expose(radiance, cam, rng), expose(radiance, cam, rng)
    assert np.array_equal(first, frames[0]) and not np.array_equal(first, second)
