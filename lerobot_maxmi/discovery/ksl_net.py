"""Key State Localization Network (KSL-Net, MaxMI §3.2).

Every trajectory is resampled to a fixed length T. For concept k, each time step t is
described by [standardized s_t ; positional embedding(t) ; concept embedding(k)]. A pointwise
(kernel-size-1) convolutional encoder maps the steps to features, a max-pool over time summarizes
the trajectory, and an MLP gives T logits: where concept k sits in this trajectory. The
positional embedding is what lets a max-pooled, pointwise encoder know *when* a state occurs.

Where the concepts start (`concept_start`): "paper" leaves it to the untrained head, whose
near-uniform p_k put every t̂ near the middle of the episode; "spread" (ours) adds a learned bias
to each concept's logits that starts as a bump on its own K-th of the episode, so that training
moves each concept to a key state near its stretch instead of several to the same one.
"""

import warnings

import torch
import torch.nn.functional as F  # noqa: N812
from huggingface_hub import PyTorchModelHubMixin
from torch import Tensor, nn

EPISODES_PER_FORWARD = 64  # bounds the (episodes, K, T, hidden) activations of one forward pass
CONCEPT_STARTS = ("paper", "spread")


def resample(states: Tensor, length: int) -> Tensor:
    """Linearly resample a (L, D) trajectory to (length, D); frame j sits at j·(L−1)/(length−1)."""
    return F.interpolate(states.T.unsqueeze(0), size=length, mode="linear", align_corners=True)[0].T


def to_episode_frame(t: Tensor, episode_length: int, length: int) -> Tensor:
    """Map resampled (fractional) indices back to integer frames of an episode of `episode_length`."""
    return (t * (episode_length - 1) / (length - 1)).round().long().clamp(0, episode_length - 1)


def stack_resampled(episodes: list[Tensor], length: int) -> Tensor:
    """(E, length, D): every (L_i, D) episode resampled to a common length."""
    return torch.stack([resample(states.float(), length) for states in episodes])


def spread_start(num_concepts: int, length: int) -> Tensor:
    """(K, T) logits: concept k a Gaussian bump (log-density, one K-th of the episode wide) centred on
    the k-th of K equal stretches of the T steps."""
    steps = torch.arange(length, dtype=torch.float32)
    width = (length - 1) / num_concepts
    centres = (torch.arange(num_concepts) + 0.5) * width
    return -0.5 * ((steps - centres[:, None]) / width) ** 2


def soft_argmax(logits: Tensor) -> Tensor:
    """(B, K, T) logits -> (B, K) expected indices t̂ = Σ_t t · p_t."""
    steps = torch.arange(logits.shape[-1], device=logits.device, dtype=logits.dtype)
    return logits.softmax(dim=-1) @ steps


class MaxOverTimeLinear(torch.autograd.Function):
    """max over time of a linear layer, (B, K, T, C_in) -> (B, K, C_out), with a sparse backward.

    Only each output channel's arg-max step receives gradient, so both gradient products run on a
    sparse matrix with one entry per (trajectory, concept, channel): 1/T of the dense products' work.
    """

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        values, steps = F.linear(x, weight, bias).max(dim=2)
        ctx.save_for_backward(x, weight, steps)
        return values

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        x, weight, steps = ctx.saved_tensors
        rows, length = steps.shape[0] * steps.shape[1], x.shape[2]
        grad, steps = grad.reshape(rows, -1), steps.reshape(rows, -1)
        # Row c of the (C_out, rows * T) gradient w.r.t. the pre-pooling output holds one entry per row.
        columns = steps + torch.arange(rows, device=x.device).unsqueeze(1) * length
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "Sparse (CSR tensor support|invariant checks)")
            by_channel = torch.sparse_csr_tensor(
                torch.arange(0, grad.numel() + 1, rows, device=x.device),
                columns.T.reshape(-1),
                grad.T.reshape(-1),
                (grad.shape[1], rows * length),
                check_invariants=False,  # valid by construction
            )
        grad_x = (by_channel.t() @ weight).view_as(x)
        grad_weight = by_channel @ x.reshape(rows * length, -1)
        return grad_x, grad_weight, grad.sum(dim=0)


def max_over_time(x: Tensor, layer: nn.Linear) -> Tensor:
    """max over time of `layer` on (B, K, T, C_in) inputs -> (B, K, C_out).

    The sparse backward is what pays on the CPU; on an accelerator the dense products are fast, and
    its sparse kernels are not what we test on.
    """
    if x.device.type == "cpu":
        return MaxOverTimeLinear.apply(x, layer.weight, layer.bias)
    return layer(x).max(dim=2).values


def mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class KSLNet(nn.Module, PyTorchModelHubMixin, library_name="lerobot_maxmi", tags=["maxmi", "key-states"]):
    """(B, T, D) resampled trajectories -> (B, K, T) localization logits."""

    def __init__(
        self,
        state_dim: int,
        length: int,
        num_concepts: int,
        embed_dim: int,
        encoder_dims: tuple[int, ...],
        head_dims: tuple[int, ...],
        concept_start: str = "paper",
    ):
        super().__init__()
        if concept_start not in CONCEPT_STARTS:
            raise ValueError(
                f"unknown concept_start {concept_start!r}; choose one of {', '.join(CONCEPT_STARTS)}"
            )
        self.length = length
        self.num_concepts = num_concepts
        self.position = nn.Embedding(length, embed_dim)
        self.concept = nn.Embedding(num_concepts, embed_dim)
        self.encoder = mlp([state_dim + 2 * embed_dim, *encoder_dims])  # pointwise over time
        self.head = mlp([encoder_dims[-1], *head_dims, length])
        self.start = nn.Parameter(spread_start(num_concepts, length)) if concept_start == "spread" else None
        self.register_buffer("state_mean", torch.zeros(state_dim))
        self.register_buffer("state_std", torch.ones(state_dim))

    def set_state_statistics(self, mean: Tensor, std: Tensor) -> None:
        """Standardize inputs with dataset statistics (saved with the weights)."""
        self.state_mean.copy_(mean)
        self.state_std.copy_(std.clamp_min(1e-6))

    def forward(self, states: Tensor) -> Tensor:
        length = states.shape[1]
        if length != self.length:
            raise ValueError(
                f"KSL-Net was built for trajectories resampled to {self.length} steps, got {length}"
            )
        features = self._first_layer(states)  # (B, K, T, C)
        if len(self.encoder) == 1:
            pooled = features.max(dim=2).values
        else:
            pooled = max_over_time(self.encoder[1:-1](features), self.encoder[-1])
        logits = self.head(F.relu(pooled))  # (B, K, T)
        return logits if self.start is None else logits + self.start

    def _first_layer(self, states: Tensor) -> Tensor:
        """The encoder's first layer on [standardized s_t ; position(t) ; concept(k)] for every (k, t).

        A linear map of a concatenation is the sum of its blocks' maps, so each block is mapped once at
        its own size and the sum broadcasts to (B, K, T, C): K times fewer multiplications for the states.
        """
        layer, state_dim = self.encoder[0], states.shape[-1]
        weight_state, weight_position, weight_concept = layer.weight.split(
            [state_dim, self.position.embedding_dim, self.concept.embedding_dim], dim=1
        )
        x = F.linear((states - self.state_mean) / self.state_std, weight_state, layer.bias)  # (B, T, C)
        position = self.position.weight @ weight_position.T  # (T, C)
        concept = self.concept.weight @ weight_concept.T  # (K, C)
        return (x + position).unsqueeze(1) + concept[None, :, None, :]

    @torch.no_grad()
    def locate(self, episodes: list[Tensor]) -> tuple[Tensor, Tensor]:
        """Each concept's position t̂ on the resampled axis and its confidence (peak probability).

        Returns two (E, K) CPU tensors for the (L_i, D) `episodes`.
        """
        positions, confidences = [], []
        for start in range(0, len(episodes), EPISODES_PER_FORWARD):
            chunk = stack_resampled(episodes[start : start + EPISODES_PER_FORWARD], self.length)
            logits = self(chunk.to(self.state_mean.device))
            positions.append(soft_argmax(logits).cpu())
            confidences.append(logits.softmax(dim=-1).amax(dim=-1).cpu())
        return torch.cat(positions), torch.cat(confidences)
