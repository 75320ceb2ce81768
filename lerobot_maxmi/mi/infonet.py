"""InfoNet-style amortized MI estimator: one forward pass per set of sample pairs.

The network reads a set of N copula-normalized pairs (u, v) in (0, 1)^2 with a Perceiver-style
encoder (latents cross-attend to the pairs, then self-attend) and has two heads:

* ``critic``: a G x G table θ read by bilinear interpolation, scored with the Donsker–Varadhan
  bound  Î = mean_i θ(u_i, v_i) − log E_{u,v ~ U(0,1)^2} exp θ(u, v).  Copula marginals are
  exactly uniform, so the product-of-marginals term is the mean of exp θ over the grid: no
  shuffling, no permutation noise. This is the InfoNet design.
* ``regression``: MI read directly from the pooled latents and statistics of the set (the critic's
  DV estimate, the Gaussian-copula MI, log N, binned plug-in MIs and k-nearest-neighbour MIs),
  trained to Monte-Carlo ground truth.
"""

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from huggingface_hub import PyTorchModelHubMixin
from torch import Tensor, nn

from lerobot_maxmi.mi.normalize import binned_copula_mi, gaussian_copula_mi, knn_copula_mi

HEADS = ("critic", "regression")
# Log set sizes are centred on the middle of the pretraining range (64 to 1024 pairs).
LOG_SET_SIZE_CENTRE = math.log(256)


@dataclass
class InfoNetConfig:
    """Architecture of `InfoNet`; the shipped weights use these defaults."""

    dim: int = 64
    num_latents: int = 16
    num_heads: int = 4
    num_layers: int = 2
    grid_size: int = 32
    critic_rank: int = 16
    num_frequencies: int = 4
    regression_width: int = 256
    # Grids of the plug-in MIs the regression head reads: coarse ones are steady at N = 100, fine
    # ones resolve mixtures' structure at N = 1000.
    histogram_bins: tuple[int, ...] = (3, 4, 6, 8, 12, 16)
    # Neighbour counts k of the Kozachenko–Leonenko MIs the regression head reads: local detail of
    # the set that the pooled latents average away, and differentiable in the samples.
    knn_neighbors: tuple[int, ...] = (1, 3, 10)


def fourier_features(points: Tensor, num_frequencies: int) -> Tensor:
    """[p, sin(2^k π p), cos(2^k π p)] for coordinates p in (0, 1), k < num_frequencies."""
    scales = math.pi * 2.0 ** torch.arange(num_frequencies, device=points.device, dtype=points.dtype)
    angles = (points.unsqueeze(-1) * scales).flatten(-2)
    return torch.cat([points, angles.sin(), angles.cos()], dim=-1)


def attend(attention: nn.MultiheadAttention, query: Tensor, context: Tensor) -> Tensor:
    """`attention` of batch-first queries to a (B, N, dim) context, computed from the module's own weights.

    nn.MultiheadAttention turns batch-first inputs sequence-first and back, and projects a shared
    key/value input with one small matrix product per position. Projecting the batch-first tensors
    directly is the same computation in large contiguous products. Queries of shape (Q, dim) are
    shared by every set and projected once.
    """
    dim = query.shape[-1]
    weights, biases = attention.in_proj_weight.split(dim), attention.in_proj_bias.split(dim)

    def heads(projected: Tensor) -> Tensor:  # (..., L, dim) -> (..., heads, L, dim / heads)
        return projected.unflatten(-1, (attention.num_heads, -1)).transpose(-3, -2)

    query = heads(F.linear(query, weights[0], biases[0]))
    key, value = (heads(F.linear(context, w, b)) for w, b in zip(weights[1:], biases[1:], strict=True))
    read = F.scaled_dot_product_attention(query.expand(context.shape[0], -1, -1, -1), key, value)
    return attention.out_proj(read.transpose(-3, -2).flatten(-2))


def pre_norm_layer(layer: nn.TransformerEncoderLayer, x: Tensor) -> Tensor:
    """`layer` (norm_first, no dropout) applied to batch-first x, with its self-attention through `attend`."""
    normed = layer.norm1(x)
    x = x + attend(layer.self_attn, normed, normed)
    return x + layer.linear2(layer.activation(layer.linear1(layer.norm2(x))))


class CrossAttentionBlock(nn.Module):
    """Queries attend to a context set, then a feed-forward layer; pre-norm residuals."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.norm_query = nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(dim)
        self.attention = nn.MultiheadAttention(dim, num_heads, batch_first=True)
        self.norm_ff = nn.LayerNorm(dim)
        self.feed_forward = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, query: Tensor, context: Tensor) -> Tensor:
        """(Q, dim) queries shared by every set, or (B, Q, dim), attend to the (B, N, dim) context."""
        query = query + attend(self.attention, self.norm_query(query), self.norm_context(context))
        return query + self.feed_forward(self.norm_ff(query))


class RegressionHead(nn.Module):
    """MI from the mean latent and (B, S) set statistics, through an MLP; softplus keeps it non-negative."""

    def __init__(self, dim: int, width: int, num_statistics: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(
            nn.Linear(dim + num_statistics, width),
            nn.GELU(),
            nn.Linear(width, width),
            nn.GELU(),
            nn.Linear(width, 1),
        )

    def forward(self, latents: Tensor, statistics: Tensor) -> Tensor:
        features = torch.cat([self.norm(latents.mean(dim=1)), statistics], dim=-1)
        return F.softplus(self.mlp(features).squeeze(-1))


class InfoNet(nn.Module, PyTorchModelHubMixin, library_name="lerobot_maxmi", tags=["mutual-information"]):
    """Set encoder with a Donsker–Varadhan critic head and a direct MI regression head."""

    def __init__(
        self,
        dim: int,
        num_latents: int,
        num_heads: int,
        num_layers: int,
        grid_size: int,
        critic_rank: int,
        num_frequencies: int,
        regression_width: int,
        histogram_bins: tuple[int, ...] = (),  # () for weights saved before the head read plug-in MIs
        knn_neighbors: tuple[int, ...] = (),  # () for weights saved before the head read k-NN MIs
    ):
        super().__init__()
        self.grid_size = grid_size
        self.histogram_bins = tuple(histogram_bins)
        self.knn_neighbors = tuple(knn_neighbors)
        self.num_frequencies = num_frequencies
        in_features = 2 + 4 * num_frequencies

        def point_embedding() -> nn.Module:
            return nn.Sequential(nn.Linear(in_features, dim), nn.GELU(), nn.Linear(dim, dim))

        self.embed_pairs = point_embedding()
        self.latents = nn.Parameter(0.02 * torch.randn(num_latents, dim))
        self.read_pairs = CrossAttentionBlock(dim, num_heads)
        layer = nn.TransformerEncoderLayer(
            dim, num_heads, 4 * dim, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
        )
        # Holds the self-attention layers and their weights' names; `encode` runs them via `pre_norm_layer`.
        self.process = nn.TransformerEncoder(layer, num_layers, enable_nested_tensor=False)
        # One query per grid row (a value of v) and per column (a value of u): 2G queries, not G².
        self.embed_axis = nn.Sequential(
            nn.Linear(1 + 2 * num_frequencies, dim), nn.GELU(), nn.Linear(dim, dim)
        )
        self.axis_id = nn.Parameter(0.02 * torch.randn(2, dim))
        self.read_latents = nn.MultiheadAttention(dim, num_heads, batch_first=True)
        self.norm_axis = nn.LayerNorm(dim)
        self.norm_latents = nn.LayerNorm(dim)
        self.critic_out = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, critic_rank + 1))
        # Statistics: DV estimate, Gaussian-copula MI, log N, one plug-in MI per grid, one k-NN MI per k.
        num_statistics = 3 + len(self.histogram_bins) + len(self.knn_neighbors)
        self.regression_head = RegressionHead(dim, regression_width, num_statistics)
        centres = ((torch.arange(grid_size) + 0.5) / grid_size).unsqueeze(-1)
        self.register_buffer("grid_centres", centres, persistent=False)

    def encode(self, u: Tensor, v: Tensor) -> Tensor:
        """(B, N) copula samples -> (B, num_latents, dim) set summary."""
        pairs = self.embed_pairs(fourier_features(torch.stack([u, v], dim=-1), self.num_frequencies))
        latents = self.read_pairs(self.latents, pairs)
        for layer in self.process.layers:
            latents = pre_norm_layer(layer, latents)
        return latents

    def critic_table(self, latents: Tensor) -> Tensor:
        """(B, G, G) critic at the grid cell centres (rows index v, columns u).

        θ(u, v) = <f(u), g(v)> + a(u) + b(v): a rank-R factorization whose row and column
        features are read from the latents by cross-attention. A Gaussian copula's log-density
        is exactly rank 3 in this form.
        """
        axis = self.embed_axis(fourier_features(self.grid_centres.to(latents.dtype), self.num_frequencies))
        queries = torch.cat([axis + self.axis_id[0], axis + self.axis_id[1]])  # (2G, dim): one set for all
        features = queries + attend(self.read_latents, self.norm_axis(queries), self.norm_latents(latents))
        features = self.critic_out(features)  # (B, 2G, R + 1)
        columns, rows = features.split(self.grid_size, dim=1)  # columns: u axis, rows: v axis
        table = rows[..., :-1] @ columns[..., :-1].transpose(1, 2) / math.sqrt(rows.shape[-1] - 1)
        return table + rows[..., -1:] + columns[..., -1].unsqueeze(1)

    def regression(self, latents: Tensor, u: Tensor, v: Tensor, table: Tensor) -> Tensor:
        """Direct MI estimate from the latents of (u, v) and the critic `table` read from them.

        Attention pooling averages over the pairs, so the latents alone do not tell 100 pairs from
        1,000 and cannot correct small-sample bias; log N, the critic's DV estimate and the Gaussian-copula
        MI give the head that context. The plug-in MIs on fine grids and the k-NN MIs carry what 16
        latents lose of a large set's detail.
        """
        log_set_size = torch.full_like(u[:, 0], math.log(u.shape[1]) - LOG_SET_SIZE_CENTRE)
        binned = [binned_copula_mi(u, v, bins) for bins in self.histogram_bins]
        statistics = [donsker_varadhan(table, u, v), gaussian_copula_mi(u, v), log_set_size, *binned]
        statistics = torch.stack(statistics, -1)
        if self.knn_neighbors:
            statistics = torch.cat([statistics, knn_copula_mi(u, v, self.knn_neighbors)], -1)
        return self.regression_head(latents, statistics)

    def forward(self, u: Tensor, v: Tensor, head: str = "critic") -> Tensor:
        """MI estimate in nats, shape (B,), from copula samples u, v of shape (B, N)."""
        latents = self.encode(u, v)
        table = self.critic_table(latents)
        if head == "regression":
            return self.regression(latents, u, v, table)
        return donsker_varadhan(table, u, v)


def lookup(table: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear read of a (B, G, G) table at (B, N) points in (0, 1)^2; cell centres are nodes."""
    coords = torch.stack([2 * u - 1, 2 * v - 1], dim=-1).unsqueeze(2)  # (B, N, 1, 2) as (x=u, y=v)
    values = F.grid_sample(
        table.unsqueeze(1), coords, mode="bilinear", padding_mode="border", align_corners=False
    )
    return values.squeeze(1).squeeze(-1)


def donsker_varadhan(table: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """DV bound of critic `table` on joint samples (u, v) against uniform marginals."""
    joint = lookup(table, u, v).mean(dim=1)
    marginal = torch.logsumexp(table.flatten(1), dim=1) - math.log(table[0].numel())
    return joint - marginal
