"""The Gaussian MAE floor (benchmarks/mi_floor.py) that the estimators' accuracy targets are read against."""

import torch

from lerobot_maxmi.mi.evaluate import draw_test_mixtures, make_test_sets
from lerobot_maxmi.mi.ground_truth import (
    bivariate_gaussian_mi,
    bivariate_gaussians,
    sample_bivariate_gaussian,
)
from tests.conftest import load_benchmark

mi_floor = load_benchmark("mi_floor")


def test_bartlett_correlations_match_sample_correlations_of_drawn_pairs():
    torch.manual_seed(0)
    rho = torch.tensor([0.0, 0.6, 0.9], dtype=torch.float64)
    drawn = mi_floor.sample_correlations(rho, num_samples=20, draws=20_000)
    pairs = sample_bivariate_gaussian(rho.repeat_interleave(20_000), 20)
    direct = mi_floor.pearson(pairs[..., 0], pairs[..., 1]).view(3, 20_000)
    assert torch.allclose(drawn.mean(1), direct.mean(1), atol=0.01)
    assert torch.allclose(drawn.std(1), direct.std(1), rtol=0.03)


def test_the_posterior_median_beats_the_plug_in_and_shrinks_with_n():
    torch.manual_seed(0)
    posterior_median, plug_in = {}, {}
    for n in (30, 300):
        floor = mi_floor.PosteriorMedian(n, grid=96, draws=2000, bins=200)
        abs_r, truth = floor.draw(), floor.mi.unsqueeze(1)
        posterior_median[n] = (floor(abs_r) - truth).abs().mean()
        plug_in[n] = (bivariate_gaussian_mi(abs_r.clamp(max=1 - 1e-12)) - truth).abs().mean()
    assert posterior_median[30] < plug_in[30]  # the plug-in's upward bias shows at small N
    assert posterior_median[300] < posterior_median[30] / 2


def test_the_known_density_averages_read_the_benchmarks_own_test_sets():
    mixtures, points, _ = draw_test_mixtures(count=4, num_samples=50, seed=7, mc_samples=1000)
    sets = make_test_sets("gmm", count=4, num_samples=50, seed=7, mc_samples=1000)
    assert torch.equal(points[..., 0].float(), sets.x) and torch.equal(points[..., 1].float(), sets.y)
    for family in ("gaussian", "gmm"):
        errors = {
            n: mi_floor.known_density_average_errors(family, n, count=64, seed=7).abs().mean()
            for n in (50, 2000)
        }
        assert errors[2000] < errors[50] / 3  # unbiased, with noise shrinking like 1/sqrt(N)


def test_bivariate_gaussians_as_mixtures_have_the_closed_form_mi():
    rho = torch.tensor([-0.8, 0.0, 0.5], dtype=torch.float64)
    mi = bivariate_gaussians(rho).monte_carlo_mi(50_000, torch.Generator().manual_seed(0))
    torch.testing.assert_close(mi, bivariate_gaussian_mi(rho), atol=0.01, rtol=0)
