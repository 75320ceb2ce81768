"""Input checks, the copula (rank) transform shared by every estimator, and the Gaussian-copula MI.

MI is invariant to monotone maps of each variable, so estimators read the *copula* of the
pairs: each column replaced by its normalized rank in (0, 1). The forward value is the exact
average rank (ties share a rank, so a constant column becomes all 0.5); the backward pass uses
the gradient of a sigmoid soft-rank, which lets MI gradients reach the raw samples.
"""

import math

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

MIN_SAMPLES = 4
# Below this std a column is constant for the soft rank (float32 loses (0.1·std)² below about 1e-18).
MIN_STD = 1e-15


def check_pairs(x: Tensor, y: Tensor) -> None:
    """Raise a ValueError that names the problem if (x, y) is not a valid batch of sample sets."""
    if not (isinstance(x, Tensor) and isinstance(y, Tensor)):
        raise TypeError(f"x and y must be torch tensors, got {type(x).__name__} and {type(y).__name__}")
    if x.shape != y.shape:
        raise ValueError(
            f"x and y must have the same shape (B, N); got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    if x.ndim != 2:
        raise ValueError(
            f"x and y must be 2-D (B sets of N paired samples); got shape {tuple(x.shape)}. "
            "For a single set use x.unsqueeze(0)."
        )
    if x.shape[1] < MIN_SAMPLES:
        raise ValueError(f"each set needs at least {MIN_SAMPLES} paired samples; got N={x.shape[1]}")
    if not (x.is_floating_point() and y.is_floating_point()):
        raise TypeError(f"x and y must be floating point tensors; got {x.dtype} and {y.dtype}")
    if not (torch.isfinite(x).all() and torch.isfinite(y).all()):
        raise ValueError("x and y contain NaN or inf; remove or impute those samples before estimating MI")


def hard_rank(x: Tensor) -> Tensor:
    """Average rank of each entry along the last dim, scaled to (0, 1): (rank + 0.5) / N."""
    ordered = x.sort(dim=-1).values.contiguous()
    below = torch.searchsorted(ordered, x.contiguous(), right=False)
    at_or_below = torch.searchsorted(ordered, x.contiguous(), right=True)
    return (below + at_or_below).to(x.dtype) / (2 * x.shape[-1])


def soft_rank(x: Tensor, temperature: float) -> Tensor:
    """Sigmoid relaxation of `hard_rank`; the width is `temperature` standard deviations.

    A column that is constant up to rounding gets unit width: with a width of ~1e-37 the gradient
    through 1/width² overflows, and NaN would reach x even where the caller masks the column's MI.
    """
    std = x.std(dim=-1, keepdim=True)
    width = torch.where(std > MIN_STD, temperature * std, torch.ones_like(std))
    return torch.sigmoid((x.unsqueeze(-1) - x.unsqueeze(-2)) / width.unsqueeze(-1)).mean(dim=-1)


def rank_normalize(x: Tensor, temperature: float = 0.1) -> Tensor:
    """Exact normalized ranks forward, soft-rank gradient backward (straight-through)."""
    ranks = hard_rank(x.detach())
    if not (torch.is_grad_enabled() and x.requires_grad):
        return ranks
    soft = soft_rank(x, temperature)
    return ranks + soft - soft.detach()


def gaussian_copula_mi(u: Tensor, v: Tensor) -> Tensor:
    """MI of the Gaussian copula of (B, N) copula samples in (0, 1): normal scores, then −½ log(1 − ρ²)."""
    zu, zv = (torch.special.ndtri(t) for t in (u, v))
    zu, zv = zu - zu.mean(1, keepdim=True), zv - zv.mean(1, keepdim=True)
    # Clamped before the root: √'s gradient at a constant column's 0 is infinite.
    denominator = (zu.square().sum(1) * zv.square().sum(1)).clamp_min(1e-24).sqrt()
    rho = (zu * zv).sum(1) / denominator
    return -0.5 * torch.log1p(-rho.square().clamp(max=1 - 1e-6))


def binned_copula_mi(u: Tensor, v: Tensor, bins: int) -> Tensor:
    """Plug-in MI of (B, N) copula samples on a bins × bins grid, with the Miller–Madow bias correction.

    Piecewise constant in the samples (no gradient); a cheap statistic whose accuracy grows with N.
    """
    batch, n = u.shape
    cell_u, cell_v = ((t * bins).long().clamp(0, bins - 1) for t in (u, v))
    counts = torch.zeros(batch, bins * bins, dtype=u.dtype, device=u.device)
    counts.scatter_add_(1, cell_u * bins + cell_v, torch.ones_like(u))
    joint = counts.view(batch, bins, bins) / n
    marginals = (joint.sum(2), joint.sum(1))

    def entropy(p: Tensor) -> Tensor:
        return -torch.special.xlogy(p, p).flatten(1).sum(1)

    occupied = [(p > 0).flatten(1).sum(1) for p in (joint, *marginals)]
    miller_madow = (occupied[0] - occupied[1] - occupied[2] + 1) / (2 * n)
    return entropy(marginals[0]) + entropy(marginals[1]) - entropy(joint) - miller_madow


def knn_copula_mi(u: Tensor, v: Tensor, neighbors: tuple[int, ...]) -> Tensor:
    """(B, len(neighbors)) MIs of (B, N) copula samples: minus their Kozachenko–Leonenko entropy.

    A copula's entropy is minus the MI of the pair (Ma & Sun, 2011), and the Kozachenko–Leonenko
    estimate reads it from each point's distance ε to its k-th nearest neighbour:
    H = ψ(N) − ψ(k) + log π + (2 / N) Σ log ε. Differentiable in the samples through ε; biased
    low near the unit square's edges, where neighbourhoods are cut off (the regression head
    learns the correction).
    """
    n = u.shape[1]
    neighbors = tuple(min(k, n - 1) for k in neighbors)  # a set of N points has N − 1 neighbours
    squared = kth_neighbor_squared_distances(torch.stack([u, v], dim=-1), neighbors)
    # Tied ranks put points on top of each other; half the rank spacing keeps log ε finite there.
    log_distance = 0.5 * squared.clamp_min((0.5 / n) ** 2).log().mean(dim=1)  # (B, len(neighbors))
    k = torch.tensor(neighbors, dtype=u.dtype, device=u.device)
    entropy = torch.special.digamma(torch.tensor(float(n))) - torch.special.digamma(k) + math.log(math.pi)
    return -(entropy + 2 * log_distance)


FAR = 1e3  # a coordinate no copula sample has: padding that is never anyone's neighbour
CHUNK = 2**22  # distances held at once


def kth_neighbor_squared_distances(points: Tensor, neighbors: tuple[int, ...]) -> Tensor:
    """(B, N, len(neighbors)) squared distances from each of (B, N, 2) points to its k-th nearest other point.

    Exact, without all N² distances of a large set: sorted by the first coordinate, each point
    searches the `half` points on either side. Anything beyond lies at least the first-coordinate
    gap to the window's edge away, so a point whose k-th distance is within that gap is done; the
    few that are not (sparse regions) search the whole set. The window is 1.5 times the radius
    that holds k neighbours at uniform density: few points then need the whole set.
    Points come back sorted; callers average over them.
    """
    n = points.shape[1]
    half = math.ceil(1.5 * math.sqrt(max(neighbors) * n / math.pi))
    points = points.gather(1, points[..., 0].argsort(dim=1).unsqueeze(-1).expand(-1, -1, 2))
    if 4 * half + 1 >= n:
        itself = torch.arange(n, device=points.device)
        chunks = points.split(max(1, CHUNK // (n * n)))
        return torch.cat(
            [smallest(squared_distances(p.unsqueeze(2), p.unsqueeze(1)), itself, neighbors) for p in chunks]
        )
    result = torch.cat(
        [windowed(p, half, neighbors) for p in points.split(max(1, CHUNK // (n * (2 * half + 1))))]
    )
    with torch.no_grad():
        first = points[..., 0]
        edge = torch.full_like(first[:, : half + 1], FAR)
        # beyond[:, i] and beyond[:, i + 2·half + 2] are the first points outside point i's window.
        beyond = torch.cat([-edge, first, edge], dim=1)
        gap = torch.minimum(beyond[:, 2 * half + 2 :] - first, first - beyond[:, :n])
        sets, rows = (result.amax(dim=-1) > gap.square()).nonzero(as_tuple=True)
    for chunk in torch.arange(len(sets), device=points.device).split(max(1, CHUNK // n)):
        s, r = sets[chunk], rows[chunk]
        whole_set = smallest(squared_distances(points[s, r].unsqueeze(1), points[s]), r, neighbors)
        result = result.index_put((s, r), whole_set)
    return result


def windowed(points: Tensor, half: int, neighbors: tuple[int, ...]) -> Tensor:
    """`smallest` among the `half` neighbours on either side of each of (B, N, 2) points sorted by u."""
    squared = 0  # (B, N, 2·half + 1), each point itself in the middle
    for coordinate in points.unbind(dim=-1):
        window = F.pad(coordinate, (half, half), value=FAR).unfold(1, 2 * half + 1, 1)
        squared = squared + (window - coordinate.unsqueeze(-1)).square()
    return smallest(squared, torch.tensor(half, device=points.device), neighbors)


def squared_distances(a: Tensor, b: Tensor) -> Tensor:
    """Squared distances between broadcastable (..., 2) points, from differences (no cancellation near 0)."""
    return sum((x - y).square() for x, y in zip(a.unbind(dim=-1), b.unbind(dim=-1), strict=True))


def smallest(squared: Tensor, itself: Tensor, neighbors: tuple[int, ...]) -> Tensor:
    """The k-th smallest entry of each row of `squared` for each k, column `itself` (the point) left out."""
    mask = F.one_hot(itself, squared.shape[-1]).to(squared.dtype) * FAR**2
    nearest = (squared + mask).topk(max(neighbors), dim=-1, largest=False).values
    return nearest[..., [k - 1 for k in neighbors]]
