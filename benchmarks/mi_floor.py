"""The least mean absolute error any of our estimators can reach on mi_accuracy.py's Gaussian rows.

    .venv/bin/python benchmarks/mi_floor.py

Those rows draw ρ ~ U(−0.95, 0.95) and N samples of a bivariate Gaussian. None of the estimators
there changes when x or y is shifted or scaled (ours read ranks; scikit-learn's KSG standardizes
each variable first). Among such estimators the sample correlation r carries all that the data
say about ρ, and the one with the least MAE is the posterior median of MI given r. Its MAE (the
Bayes risk) is a floor for every estimator in that table, even one told that the data are Gaussian.

r is drawn exactly for a grid of ρ (Bartlett's decomposition of the Wishart scatter matrix). The
posterior median is read per bin of |r| from one draw and scored on a second, independent one (an
estimator that exists, so its MAE can only overstate the floor, by less with finer bins and more
draws), and on mi_accuracy.py's own Gaussian test sets, beside which its rows can be read. The
plug-in −½·log(1 − r²) is scored beside it.

The mixture rows have no such floor (no one-number statistic carries what their data say about
MI). A second table gives a reference scale for both families instead: each test set's pointwise
MI log p(x, y) − log p(x) − log p(y), read from its exact density, averaged over the set's own
N points. That average is unbiased, but as noisy as N points make it. It is not a floor (an
estimator given the density would know MI itself, and one with a prior can beat an unbiased
average by shrinking it); on the Gaussian rows it can be read beside the floor.
"""

import argparse

import torch
from torch import Tensor
from torch.distributions import Chi2

from lerobot_maxmi.mi.evaluate import (
    FAMILIES,
    MAX_ABS_RHO,
    TEST_SEED,
    case_seeds,
    draw_test_gaussians,
    draw_test_mixtures,
    mae_and_standard_error,
    make_test_sets,
)
from lerobot_maxmi.mi.ground_truth import bivariate_gaussian_mi, bivariate_gaussians


def sample_correlations(rho: Tensor, num_samples: int, draws: int) -> Tensor:
    """(len(rho), draws) sample correlations of `num_samples` Gaussian pairs with means estimated.

    With Σ = L Lᵀ, L = [[1, 0], [ρ, √(1−ρ²)]], the scatter matrix is L B Bᵀ Lᵀ for Bartlett's
    B = [[b11, 0], [b21, b22]], b11² ~ χ²(n−1), b22² ~ χ²(n−2), b21 ~ N(0, 1).
    """
    shape = (len(rho), draws)
    b11 = Chi2(torch.tensor(num_samples - 1.0, dtype=rho.dtype)).sample(shape).sqrt()
    b22 = Chi2(torch.tensor(num_samples - 2.0, dtype=rho.dtype)).sample(shape).sqrt()
    b21 = torch.randn(shape, dtype=rho.dtype)
    rho = rho.unsqueeze(1)
    spread = (1 - rho.square()).sqrt()
    row = rho * b11 + spread * b21  # second row of L B, first column
    return row / (row.square() + (spread * b22).square()).sqrt()


def pearson(x: Tensor, y: Tensor) -> Tensor:
    """Sample correlation of each of the (B, N) sets."""
    x, y = x - x.mean(dim=1, keepdim=True), y - y.mean(dim=1, keepdim=True)
    return (x * y).sum(dim=1) / (x.square().sum(dim=1) * y.square().sum(dim=1)).sqrt()


def weighted_median(values: Tensor, weights: Tensor) -> Tensor:
    """Per column of `weights` (len(values), bins): the median of `values` (sorted ascending)."""
    cumulative = weights.cumsum(dim=0)
    below_half = cumulative < cumulative[-1:] / 2
    return values[below_half.sum(dim=0).clamp(max=len(values) - 1)]


class PosteriorMedian:
    """MI's posterior median given |r|, per bin of |r|, under |ρ| ~ U(0, 0.95) (MI depends on |ρ| only)."""

    def __init__(self, num_samples: int, grid: int, draws: int, bins: int):
        self.abs_rho = torch.linspace(0, MAX_ABS_RHO, grid, dtype=torch.float64)
        self.mi = bivariate_gaussian_mi(self.abs_rho)  # rises with |ρ|: sorted
        self.num_samples, self.draws = num_samples, draws
        self.edges = torch.linspace(0, 1, bins + 1, dtype=torch.float64)[1:-1]
        fit = self.draw()
        counts = torch.zeros(grid, bins, dtype=torch.float64)
        counts.scatter_add_(1, torch.bucketize(fit, self.edges), torch.ones_like(fit))
        self.per_bin = weighted_median(self.mi, counts)

    def draw(self) -> Tensor:
        """(grid, draws) fresh |r| for each |ρ| of the grid."""
        return sample_correlations(self.abs_rho, self.num_samples, self.draws).abs()

    def __call__(self, abs_r: Tensor) -> Tensor:
        return self.per_bin[torch.bucketize(abs_r, self.edges)]


def known_density_average_errors(family: str, num_samples: int, count: int, seed: int) -> Tensor:
    """Per test set: its N points' mean pointwise MI under the exact density, minus the true MI."""
    if family == "gaussian":
        rho, points, mi = draw_test_gaussians(count, num_samples, seed)
        densities = bivariate_gaussians(rho)
    else:
        densities, points, mi = draw_test_mixtures(count, num_samples, seed)
    return densities.pointwise_mi(points).mean(dim=1) - mi


def mean_and_error(errors: Tensor) -> str:
    return "{:.4f} ± {:.4f}".format(*mae_and_standard_error(errors))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", nargs="+", type=int, default=[100, 1000])
    parser.add_argument("--grid", type=int, default=1901, help="values of |ρ| in [0, 0.95]")
    parser.add_argument("--draws", type=int, default=4000, help="sample correlations per value of |ρ|")
    parser.add_argument("--bins", type=int, default=1000, help="bins of |r| in [0, 1]")
    parser.add_argument("--count", type=int, default=200, help="mi_accuracy.py's test sets per row")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    test_seeds = case_seeds(list(FAMILIES), args.sizes, TEST_SEED)  # as mi_accuracy.py draws them
    print(
        "| N | floor: posterior median, expected | floor on mi_accuracy.py's test sets "
        "| plug-in −½ log(1 − r²), expected |\n|---:|---:|---:|---:|"
    )
    for n in args.sizes:
        floor = PosteriorMedian(n, args.grid, args.draws, args.bins)
        abs_r, truth = floor.draw(), floor.mi.unsqueeze(1)
        tests = make_test_sets("gaussian", args.count, n, test_seeds["gaussian", n])
        on_tests = floor(pearson(tests.x.double(), tests.y.double()).abs()) - tests.mi.double()
        plug_in = bivariate_gaussian_mi(abs_r.clamp(max=1 - 1e-12)) - truth
        cells = (mean_and_error(floor(abs_r) - truth), mean_and_error(on_tests), mean_and_error(plug_in))
        print(f"| {n} | " + " | ".join(cells) + " |")
    print(
        "\nExact-density average of the N points' pointwise MI, on mi_accuracy.py's test sets:\n"
        "| N | gaussian | gmm |\n|---:|---:|---:|"
    )
    for n in args.sizes:
        cells = [
            mean_and_error(known_density_average_errors(family, n, args.count, test_seeds[family, n]))
            for family in ("gaussian", "gmm")
        ]
        print(f"| {n} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
