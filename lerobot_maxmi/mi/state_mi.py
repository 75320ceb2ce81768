"""MI between high-dimensional states, built from a scalar-pair estimator."""

import torch
from torch import Tensor

from lerobot_maxmi.mi.estimators import MIEstimator

STATE_MI_MODES = ("per_dim", "sliced")


def state_mi(
    s_a: Tensor,
    s_b: Tensor,
    estimator: MIEstimator,
    mode: str = "per_dim",
    num_projections: int = 64,
    generator: torch.Generator | None = None,
) -> Tensor:
    """MI between paired states s_a, s_b of shape (B, N, D), one value per set (B,).

    ``per_dim``: the mean over dimensions of MI(s_a[..., d]; s_b[..., d]), as MaxMI's released
    code does; a dimension constant in either state within a set counts as MI 0.
    ``sliced``: the mean over `num_projections` random unit directions (independent for s_a and
    s_b) of MI(θᵀ s_a; φᵀ s_b), as the InfoNet authors recommend for high-dimensional data.
    """
    if s_a.shape != s_b.shape or s_a.ndim != 3:
        raise ValueError(f"s_a and s_b must both be (B, N, D); got {tuple(s_a.shape)} and {tuple(s_b.shape)}")
    if mode == "per_dim":
        return per_dimension_mi(s_a, s_b, estimator)
    if mode == "sliced":
        return sliced_mi(s_a, s_b, estimator, num_projections, generator)
    raise ValueError(f"unknown state_mi mode {mode!r}; choose one of {', '.join(STATE_MI_MODES)}")


def per_dimension_mi(s_a: Tensor, s_b: Tensor, estimator: MIEstimator) -> Tensor:
    batch, n, dims = s_a.shape
    varying = is_varying(s_a) & is_varying(s_b)  # (B, D)
    columns = [s.transpose(1, 2).reshape(batch * dims, n) for s in (s_a, s_b)]
    mi = estimator(*columns).view(batch, dims)
    return torch.where(varying, mi, torch.zeros_like(mi)).mean(dim=1)


def sliced_mi(
    s_a: Tensor, s_b: Tensor, estimator: MIEstimator, num_projections: int, generator: torch.Generator | None
) -> Tensor:
    if num_projections < 1:
        raise ValueError(f"num_projections must be >= 1; got {num_projections}")
    batch, n, dims = s_a.shape
    theta, phi = (
        torch.nn.functional.normalize(
            torch.randn(num_projections, dims, generator=generator, dtype=s_a.dtype).to(s_a.device), dim=1
        )
        for _ in range(2)
    )
    projected = [
        (s @ p.T).transpose(1, 2).reshape(batch * num_projections, n) for s, p in ((s_a, theta), (s_b, phi))
    ]
    return estimator(*projected).view(batch, num_projections).mean(dim=1)


def is_varying(s: Tensor, tolerance: float = 1e-8) -> Tensor:
    """(B, D) mask of dimensions whose spread within the set exceeds `tolerance` (relative)."""
    spread = s.amax(dim=1) - s.amin(dim=1)
    scale = s.abs().amax(dim=1).clamp_min(1.0)
    return spread > tolerance * scale
