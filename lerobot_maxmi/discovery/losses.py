"""The MaxMI objective (MaxMI §3.2–3.3), one function per equation.

t̂_k = Σ_t t · softmax(φ(τ))_k,t                         `ksl_net.soft_argmax`
s_t̂ by linear interpolation at fractional t̂             `interpolate_states`
L_MaxMI = −Σ_k I({s_t̂_k, s_t̂_k−Δt}_i)                 `maxmi_loss`
L_div   = Σ_{u<v} softplus(−|t̂_u − t̂_v|)  (paper)       `diversity_loss`

and the released code's variant: one MI over the pairs of all concepts pooled, s_t̂−Δt by its
extrapolating gather, weight 4, and an ordering loss on consecutive concepts
(`released_maxmi_loss`, `ordering_loss`).
"""

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from lerobot_maxmi.mi import MIEstimator, state_mi

RELEASED_MI_WEIGHT = 4.0
RELEASED_SHIFT = -2
RELEASED_ORDER_BETA = 0.3


def gather_frames(states: Tensor, index: Tensor) -> Tensor:
    """(B, T, D) states at integer indices (B, K), clamped to the trajectory -> (B, K, D)."""
    index = index.long().clamp(0, states.shape[1] - 1)
    return states.gather(1, index.unsqueeze(-1).expand(-1, -1, states.shape[-1]))


def lerp_frames(states: Tensor, base: Tensor, t: Tensor) -> Tensor:
    """The line through frames `base` and `base + 1`, evaluated at t; differentiable in t."""
    weight = (t - base).unsqueeze(-1)
    return (1 - weight) * gather_frames(states, base) + weight * gather_frames(states, base + 1)


def interpolate_states(states: Tensor, t: Tensor) -> Tensor:
    """States at fractional indices t (B, K) of (B, T, D) trajectories -> (B, K, D); differentiable in t."""
    t = t.clamp(0, states.shape[1] - 1)
    return lerp_frames(states, t.detach().floor().clamp(max=states.shape[1] - 2), t)


def released_shifted_states(states: Tensor, t: Tensor, shift: int = RELEASED_SHIFT) -> Tensor:
    """The released code's gather: base frame ⌊t⌋+shift, weight t − base (an extrapolation for shift < 0)."""
    return lerp_frames(states, t.detach().floor() + shift, t)


def maxmi_loss(
    states: Tensor, t_hat: Tensor, delta_t: float, estimator: MIEstimator, mode: str = "per_dim"
) -> tuple[Tensor, Tensor]:
    """−Σ_k MI(s_t̂_k ; s_t̂_k−Δt), each MI over the batch's trajectories; returns (loss, MI per concept)."""
    now = interpolate_states(states, t_hat)
    before = interpolate_states(states, t_hat - delta_t)
    mi = state_mi(now.transpose(0, 1), before.transpose(0, 1), estimator, mode)  # sets = concepts
    return -mi.sum(), mi


def released_maxmi_loss(
    states: Tensor, t_hat: Tensor, estimator: MIEstimator, mode: str = "per_dim"
) -> Tensor:
    """The released code: one MI over all (trajectory, concept) pairs pooled, weighted by 4."""
    now = interpolate_states(states, t_hat).flatten(0, 1).unsqueeze(0)
    before = released_shifted_states(states, t_hat).flatten(0, 1).unsqueeze(0)
    return -RELEASED_MI_WEIGHT * state_mi(now, before, estimator, mode).squeeze(0)


def diversity_loss(t_hat: Tensor) -> Tensor:
    """Paper: Σ_{u<v} softplus(−|t̂_u − t̂_v|), averaged over trajectories; pushes concepts apart."""
    gaps = (t_hat.unsqueeze(-1) - t_hat.unsqueeze(-2)).abs()
    upper = torch.triu(torch.ones_like(gaps[0], dtype=torch.bool), diagonal=1)
    return F.softplus(-gaps[:, upper]).sum(dim=1).mean()


def ordering_loss(t_hat: Tensor, beta: float = RELEASED_ORDER_BETA) -> Tensor:
    """Released code: Σ_k mean_i softplus_β(−(t̂_k+1 − t̂_k)); concept k+1 should come after concept k."""
    return F.softplus(-t_hat.diff(dim=1), beta=beta).mean(dim=0).sum()
