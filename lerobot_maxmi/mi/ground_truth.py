"""Distributions with known mutual information, for pretraining and validating estimators.

Random 2-D Gaussian mixtures follow InfoNet's generator: weights ~ Dirichlet(1), means ~ U(-5, 5)^2,
covariances [[a11, a12], [a12, a22]] + 0.01 I with a11, a22 sums of squares of two U(-3, 3)
draws and a12 ~ U(-1, 1) * sqrt(a11 a22). Their MI is computed by Monte Carlo from the exact
joint and marginal densities; bivariate Gaussians have it in closed form.

The densities are written out for 2x2 covariances: pretraining labels every batch, and
torch.distributions' batched triangular solves made that ~10x slower.
"""

import math
from dataclasses import dataclass

import torch
from torch import Tensor

LOG_2PI = math.log(2 * math.pi)


@dataclass
class GaussianMixtures:
    """A batch of 2-D Gaussian mixtures; unused components carry zero weight."""

    weights: Tensor  # (B, K)
    means: Tensor  # (B, K, 2)
    covariances: Tensor  # (B, K, 2, 2)

    def sample(self, num_samples: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw (B, num_samples, 2) points."""
        batch = self.weights.shape[0]
        component = torch.multinomial(self.weights, num_samples, replacement=True, generator=generator)
        noise = torch.randn(batch, num_samples, 2, generator=generator, dtype=self.means.dtype)
        chol = torch.linalg.cholesky(self.covariances)
        rows = torch.arange(batch).unsqueeze(1)
        return self.means[rows, component] + (chol[rows, component] @ noise.unsqueeze(-1)).squeeze(-1)

    def pointwise_mi(self, points: Tensor) -> Tensor:
        """log p(x, y) - log p(x) - log p(y) at (B, S, 2) points, shape (B, S)."""
        log_w = self.weights.log().unsqueeze(1)  # (B, 1, K); unused components give -inf
        offset = points.unsqueeze(2) - self.means.unsqueeze(1)  # (B, S, K, 2)
        dx, dy = offset[..., 0], offset[..., 1]
        a11, a12, a22 = (self.covariances[..., i, j].unsqueeze(1) for i, j in ((0, 0), (0, 1), (1, 1)))
        det = a11 * a22 - a12.square()
        mahalanobis = (a22 * dx.square() - 2 * a12 * dx * dy + a11 * dy.square()) / det
        joint = torch.logsumexp(log_w - LOG_2PI - 0.5 * det.log() - 0.5 * mahalanobis, dim=-1)
        return joint - mixture_log_prob_1d(dx, a11, log_w) - mixture_log_prob_1d(dy, a22, log_w)

    def monte_carlo_mi(self, num_samples: int = 100_000, generator: torch.Generator | None = None) -> Tensor:
        """MI in nats per mixture, shape (B,); standard error ~ std(pmi) / sqrt(num_samples)."""
        return self.pointwise_mi(self.sample(num_samples, generator)).mean(dim=1)


def mixture_log_prob_1d(offset: Tensor, variance: Tensor, log_weights: Tensor) -> Tensor:
    """Log density of a 1-D mixture, from per-component offsets (x - mean) and variances."""
    log_components = -0.5 * (LOG_2PI + variance.log() + offset.square() / variance)
    return torch.logsumexp(log_weights + log_components, dim=-1)


def random_gaussian_mixtures(
    batch: int,
    max_components: int = 20,
    min_components: int = 1,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> GaussianMixtures:
    """Draw `batch` random mixtures with a uniform number of components in [min, max]."""

    def uniform(*shape: int, low: float, high: float) -> Tensor:
        return low + (high - low) * torch.rand(*shape, generator=generator, dtype=dtype)

    k = max_components
    count = torch.randint(min_components, max_components + 1, (batch, 1), generator=generator)
    active = torch.arange(k).unsqueeze(0) < count
    gamma = -torch.log(uniform(batch, k, low=1e-12, high=1.0))  # Exp(1) draws: Dirichlet(1) once normalized
    weights = gamma * active
    weights = weights / weights.sum(dim=1, keepdim=True)
    a11 = uniform(batch, k, 2, low=-3, high=3).square().sum(-1)
    a22 = uniform(batch, k, 2, low=-3, high=3).square().sum(-1)
    a12 = uniform(batch, k, low=-1, high=1) * (a11 * a22).sqrt()
    covariances = torch.stack([torch.stack([a11, a12], -1), torch.stack([a12, a22], -1)], -2)
    covariances = covariances + 0.01 * torch.eye(2, dtype=dtype)
    return GaussianMixtures(weights, uniform(batch, k, 2, low=-5, high=5), covariances)


def bivariate_gaussian_mi(rho: Tensor) -> Tensor:
    """Closed-form MI of a bivariate Gaussian with correlation rho: -1/2 log(1 - rho^2)."""
    return -0.5 * torch.log1p(-rho.square())


def bivariate_gaussians(rho: Tensor) -> GaussianMixtures:
    """Standard bivariate Gaussians with correlations rho (B,) as one-component mixtures (densities)."""
    ones = torch.ones_like(rho)
    covariances = torch.stack([torch.stack([ones, rho], -1), torch.stack([rho, ones], -1)], -2)
    return GaussianMixtures(
        ones.unsqueeze(1), torch.zeros(len(rho), 1, 2, dtype=rho.dtype), covariances.unsqueeze(1)
    )


def sample_bivariate_gaussian(
    rho: Tensor, num_samples: int, generator: torch.Generator | None = None
) -> Tensor:
    """(B, num_samples, 2) standard bivariate Gaussian samples with correlations rho (B,)."""
    z = torch.randn(rho.shape[0], num_samples, 2, generator=generator, dtype=rho.dtype)
    r = rho.unsqueeze(1)
    return torch.stack([z[..., 0], r * z[..., 0] + (1 - r.square()).sqrt() * z[..., 1]], dim=-1)
