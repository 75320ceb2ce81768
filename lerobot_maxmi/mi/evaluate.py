"""Accuracy and speed of MI estimators against ground truth (used by the benchmark and demo)."""

import time
from dataclasses import dataclass

import torch
from torch import Tensor
from tqdm import tqdm

from lerobot_maxmi.mi.estimators import MIEstimator, load_estimator
from lerobot_maxmi.mi.ground_truth import (
    GaussianMixtures,
    bivariate_gaussian_mi,
    random_gaussian_mixtures,
    sample_bivariate_gaussian,
)

FAMILIES = ("gmm", "gaussian")
TEST_SEED = 12345  # benchmarks/mi_accuracy.py's default; docs/RESULTS.md quotes its rows
MAX_ABS_RHO = 0.95  # the Gaussian family's ρ ~ U(−0.95, 0.95)


@dataclass
class TestSets:
    """B sets of N pairs (x, y) with their true MI."""

    family: str
    x: Tensor  # (B, N)
    y: Tensor  # (B, N)
    mi: Tensor  # (B,)


@dataclass
class Row:
    family: str
    num_samples: int
    estimator: str
    mae: float
    mae_standard_error: float  # over the test distributions: how far the MAE of a fresh draw may move
    bias: float
    ms_per_estimate: float
    gradient_ok: str


def make_test_sets(
    family: str, count: int, num_samples: int, seed: int, mc_samples: int = 100_000, max_components: int = 10
) -> TestSets:
    """Fresh test distributions: GMMs with 1..max_components components, or Gaussians with |ρ| ≤ 0.95."""
    if family == "gaussian":
        _, points, mi = draw_test_gaussians(count, num_samples, seed)
    elif family == "gmm":
        _, points, mi = draw_test_mixtures(count, num_samples, seed, mc_samples, max_components)
    else:
        raise ValueError(f"unknown test family {family!r}; choose one of {', '.join(FAMILIES)}")
    return TestSets(family, points[..., 0].float(), points[..., 1].float(), mi.float())


def draw_test_gaussians(count: int, num_samples: int, seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """The "gaussian" family's correlations ρ, (B, N, 2) samples and MI, as `make_test_sets` draws them."""
    generator = torch.Generator().manual_seed(seed)
    rho = (torch.rand(count, generator=generator, dtype=torch.float64) * 2 - 1) * MAX_ABS_RHO
    return rho, sample_bivariate_gaussian(rho, num_samples, generator), bivariate_gaussian_mi(rho)


def draw_test_mixtures(
    count: int, num_samples: int, seed: int, mc_samples: int = 100_000, max_components: int = 10
) -> tuple[GaussianMixtures, Tensor, Tensor]:
    """The "gmm" family's mixtures, (B, N, 2) samples and Monte-Carlo MI, as `make_test_sets` draws them."""
    generator = torch.Generator().manual_seed(seed)
    mixtures = random_gaussian_mixtures(count, max_components, generator=generator)
    points = mixtures.sample(num_samples, generator)
    mi = torch.cat([chunk_mi(mixtures, i, mc_samples, generator) for i in range(0, count, 16)])
    return mixtures, points, mi


def chunk_mi(mixtures: GaussianMixtures, start: int, mc_samples: int, generator: torch.Generator) -> Tensor:
    """Monte-Carlo MI of 16 mixtures at a time, to bound memory."""
    chunk = type(mixtures)(
        *(t[start : start + 16] for t in (mixtures.weights, mixtures.means, mixtures.covariances))
    )
    return chunk.monte_carlo_mi(mc_samples, generator)


def timed_estimate(estimator: MIEstimator, sets: TestSets) -> tuple[Tensor, float]:
    """Estimates and milliseconds per estimate (one batched call; KSG loops internally)."""
    with torch.no_grad():
        estimator(sets.x[:2], sets.y[:2])  # warm-up
        start = time.perf_counter()
        estimate = estimator(sets.x, sets.y)
    return estimate.float(), 1000 * (time.perf_counter() - start) / sets.x.shape[0]


def gradient_check(estimator: MIEstimator, sets: TestSets) -> str:
    """'yes' if d(MI)/dx is finite and non-zero, 'n/a' for non-differentiable estimators."""
    if not estimator.differentiable:
        return "n/a"
    x = sets.x[:8].clone().requires_grad_(True)
    estimator(x, sets.y[:8]).sum().backward()
    return "yes" if torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0 else "NO"


def mae_and_standard_error(error: Tensor) -> tuple[float, float]:
    """Mean absolute error over the sets, and its standard error (how far a fresh draw may move it)."""
    absolute = error.abs().flatten()
    return absolute.mean().item(), absolute.std().item() / len(absolute) ** 0.5


def case_seeds(families: list[str], sizes: list[int], seed: int) -> dict[tuple[str, int], int]:
    """The test-set seed of each (family, N) row: one seed per row, so that rows do not share samples."""
    cases = [(family, n) for family in families for n in sizes]
    return {case: seed + index for index, case in enumerate(cases)}


def evaluate_estimators(
    names: list[str],
    families: list[str],
    sizes: list[int],
    count: int,
    seed: int,
    mc_samples: int = 100_000,
    infonet_weights: str | None = None,
) -> list[Row]:
    """`infonet_weights` (a directory or hub repo id) replaces the InfoNet estimators' shipped weights."""
    estimators = {
        name: load_estimator(name, device="cpu", **weights_option(name, infonet_weights)) for name in names
    }
    rows = []
    for (family, n), case_seed in tqdm(case_seeds(families, sizes, seed).items(), desc="MI accuracy"):
        sets = make_test_sets(family, count, n, case_seed, mc_samples)
        for name, estimator in estimators.items():
            estimate, ms = timed_estimate(estimator, sets)
            error = estimate - sets.mi
            rows.append(
                Row(
                    family,
                    n,
                    name,
                    *mae_and_standard_error(error),
                    error.mean().item(),
                    ms,
                    gradient_check(estimator, sets),
                )
            )
    return rows


def weights_option(name: str, infonet_weights: str | None) -> dict:
    return {"pretrained": infonet_weights} if infonet_weights and name.startswith("infonet") else {}


def format_table(rows: list[Row]) -> str:
    lines = [
        "| family | N | estimator | MAE ± s.e. (nats) | bias (nats) | ms / estimate | d(MI)/dx ok |",
        "|---|---:|---|---:|---:|---:|---|",
    ]
    lines += [
        f"| {r.family} | {r.num_samples} | {r.estimator} | {r.mae:.4f} ± {r.mae_standard_error:.4f} "
        f"| {r.bias:+.4f} | {r.ms_per_estimate:.3f} | {r.gradient_ok} |"
        for r in rows
    ]
    return "\n".join(lines)
