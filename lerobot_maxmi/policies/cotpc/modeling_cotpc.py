"""CoTPC: a causal GPT over (state, action) windows with learnable key-state ("chain-of-thought") tokens.

As per Chain-of-Thought Predictive Control (Jia et al., ICML 2023, https://arxiv.org/abs/2304.00776),
used by MaxMI (Zhou et al.) with discovered key states. Token layout of one window of L steps:

    [k_1 .. k_K | s_0 a_0 s_1 a_1 ... a_{L-2} s_{L-1}]

The action for step i is read at the output of state token s_i; the key-state head reads the k tokens
after block `key_state_layer` and predicts the episode's K key states.
"""

from collections import deque
from typing import NamedTuple

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn

from .configuration_cotpc import DISCOVER_HINT, CotpcConfig, CotpcMaxmiConfig

STATE_IS_PAD = f"{OBS_STATE}_is_pad"
ACTION_IS_PAD = f"{ACTION}_is_pad"


class CotpcPolicy(PreTrainedPolicy):
    """CoTPC policy; with K = 0 key states it is a plain causal transformer trained by behaviour cloning."""

    config_class = CotpcConfig
    name = "cotpc"

    def __init__(self, config: CotpcConfig, dataset_meta=None, **kwargs):
        """
        Args:
            config: Policy configuration; its features come from the dataset (training) or checkpoint.
            dataset_meta: `LeRobotDatasetMetadata` of the training dataset, passed by LeRobot's
                `make_policy`; when given, the config is checked against it and `config.fps` filled in.
        """
        super().__init__(config)
        config.validate_features()
        if dataset_meta is not None:
            check_dataset(config, dataset_meta)
        self.config = config
        self.model = CotpcTransformer(config)
        self.reset()

    def get_optim_params(self):
        return self.parameters()

    def reset(self):
        """Forget the rollout history; call whenever the environment is reset."""
        self._history = RolloutHistory(self.config.context_length)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor]) -> Tensor:
        """The action (B, action_dim) for the current `observation.state`, given the history since reset()."""
        self.eval()
        action = self.predict_action_chunk(batch)[:, 0]
        self._history.append(batch[OBS_STATE], action)
        return action

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor]) -> Tensor:
        """A chunk of one action (B, 1, action_dim) for the current step; does not advance the history."""
        self.eval()
        window = self._history.window(batch[OBS_STATE], self.config.action_dim)
        # Key-state tokens see up to the current (last) state.
        horizon = torch.full_like(window.start_step, self.config.context_length - 1)
        actions, _ = self.model(*window, horizon, current_action_only=True)
        return actions

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Masked action MSE + alpha * key-state MSE on a batch of windows from LeRobot's loader."""
        states, actions, is_pad = batch[OBS_STATE], batch[ACTION], batch[STATE_IS_PAD]
        start_step = self._window_start_step(batch["timestamp"])
        horizon = self._key_state_horizon(is_pad)
        pred_actions, pred_key_states = self.model(states, actions[:, :-1], is_pad, start_step, horizon)

        valid = ~batch[ACTION_IS_PAD].unsqueeze(-1)
        squared_error = F.mse_loss(pred_actions, actions, reduction="none")
        action_loss = (squared_error * valid).sum() / (valid.sum() * actions.shape[-1]).clamp_min(1)
        loss_dict = {"action_loss": action_loss.item()}
        loss = action_loss
        if pred_key_states is not None:
            # Every frame of an episode holds the same key states; the last frame is never padding.
            target = batch[self.config.key_states_feature][:, -1].reshape(pred_key_states.shape)
            key_state_loss = F.mse_loss(pred_key_states, target)
            loss_dict["key_state_loss"] = key_state_loss.item()
            loss = loss + self.config.key_state_loss_weight * key_state_loss
        return loss, loss_dict

    def _window_start_step(self, timestamp: Tensor) -> Tensor:
        """Episode step of each window's first real frame (the loader's windows end at `timestamp`)."""
        if self.config.fps is None:
            raise ValueError(
                "`config.fps` is unset, so `timestamp` cannot be turned into an episode step. Build the "
                "policy with `dataset_meta=` (LeRobot's make_policy does) or set `fps` in the config."
            )
        current_step = torch.round(timestamp * self.config.fps).long()
        return (current_step - (self.config.context_length - 1)).clamp_min(0)

    def _key_state_horizon(self, is_pad: Tensor) -> Tensor:
        """Last state index the key-state tokens may see: a random real step in training (CoTPC's hybrid
        mask), the current step otherwise."""
        length = is_pad.shape[1]
        if not self.training:
            return torch.full((is_pad.shape[0],), length - 1, device=is_pad.device)
        first_real = is_pad.sum(dim=1)  # the loader pads only before the episode start
        offset = torch.rand(is_pad.shape[0], device=is_pad.device) * (length - first_real)
        return first_real + offset.long()


class CotpcMaxmiPolicy(CotpcPolicy):
    """CoTPC trained on MaxMI-discovered key states (`lerobot-maxmi-discover`)."""

    config_class = CotpcMaxmiConfig
    name = "cotpc_maxmi"


def check_dataset(config: CotpcConfig, dataset_meta) -> None:
    """Fail early when a (possibly resumed) config does not fit the dataset it is about to train on."""
    features = dataset_meta.features
    expected = {OBS_STATE: config.state_dim, ACTION: config.action_dim}
    if config.num_key_states:
        expected[config.key_states_feature] = config.num_key_states * config.state_dim
    for key, size in expected.items():
        if key not in features:
            hint = DISCOVER_HINT if key == config.key_states_feature else "Train on a dataset that has it."
            raise ValueError(f"The policy needs feature `{key}`, which {dataset_meta.repo_id} lacks. {hint}")
        if tuple(features[key]["shape"]) != (size,):
            raise ValueError(
                f"`{key}` has shape {tuple(features[key]['shape'])} in {dataset_meta.repo_id} but the policy "
                f"was built for ({size},): train a fresh policy for this dataset instead of resuming."
            )
    if config.num_key_states and config.key_states_feature not in (dataset_meta.stats or {}):
        raise ValueError(
            f"`{config.key_states_feature}` has no statistics in meta/stats.json, so it would not be "
            f"normalized like `{OBS_STATE}`. Re-run the annotation (it writes them)."
        )
    longest = max(dataset_meta.episodes["length"])
    if longest > config.max_episode_steps:
        raise ValueError(
            f"The longest episode has {longest} steps but `max_episode_steps` is {config.max_episode_steps}: "
            f"pass `--policy.max_episode_steps={longest}` or more."
        )
    if config.fps is not None and config.fps != dataset_meta.fps:
        raise ValueError(f"The policy was trained at {config.fps} fps, this dataset at {dataset_meta.fps}.")
    config.fps = dataset_meta.fps


class RolloutWindow(NamedTuple):
    """A left-padded window in the layout of LeRobot's training windows."""

    states: Tensor
    past_actions: Tensor
    is_pad: Tensor
    start_step: Tensor


class RolloutHistory:
    """The last context_length - 1 (state, action) pairs of a batch of rollouts and the step count."""

    def __init__(self, context_length: int):
        self.context_length = context_length
        self.states = deque(maxlen=context_length - 1)
        self.actions = deque(maxlen=context_length - 1)
        self.steps = 0

    def append(self, state: Tensor, action: Tensor) -> None:
        self.states.append(state)
        self.actions.append(action)
        self.steps += 1

    def window(self, current_state: Tensor, action_dim: int) -> RolloutWindow:
        """The window ending at `current_state`, padded on the left like the loader pads episode starts."""
        batch_size, length = current_state.shape[0], self.context_length
        seen = len(self.states) + 1
        states = current_state.new_zeros(batch_size, length, current_state.shape[-1])
        states[:, length - seen :] = torch.stack([*self.states, current_state], dim=1)
        past_actions = current_state.new_zeros(batch_size, length - 1, action_dim)
        if self.actions:
            past_actions[:, length - seen :] = torch.stack(list(self.actions), dim=1)
        is_pad = (torch.arange(length, device=current_state.device) < length - seen).expand(batch_size, -1)
        start_step = torch.full((batch_size,), max(0, self.steps - (length - 1)), device=current_state.device)
        return RolloutWindow(states, past_actions, is_pad, start_step)


class CotpcTransformer(nn.Module):
    """CoTPC network: MLP token encoders, pre-LN GPT blocks under the hybrid mask, action/key-state heads."""

    def __init__(self, config: CotpcConfig):
        super().__init__()
        self.config = config
        dim, hidden, heads = config.dim_model, config.dim_encoder_hidden, config.n_heads
        self.num_key_states = config.num_key_states
        self.state_encoder = mlp(config.state_dim, hidden, dim)
        self.action_encoder = mlp(config.action_dim, hidden, dim)
        self.local_position = nn.Parameter(0.02 * torch.randn(1, config.context_length, dim))
        self.global_position = nn.Embedding(config.max_episode_steps, dim)
        self.embedding_dropout = nn.Dropout(config.dropout)
        self.blocks = nn.ModuleList(Block(dim, heads, config.dropout) for _ in range(config.n_layers))
        self.final_norm = nn.LayerNorm(dim)
        self.action_head = mlp(dim, config.dim_head_hidden, config.dim_head_hidden, config.action_dim)
        if self.num_key_states:
            self.key_state_tokens = nn.Parameter(0.02 * torch.randn(1, self.num_key_states, dim))
            self.key_state_head = mlp(dim, config.dim_head_hidden, config.state_dim)
        self.apply(init_weights)

    def forward(
        self,
        states: Tensor,
        past_actions: Tensor,
        is_pad: Tensor,
        start_step: Tensor,
        horizon: Tensor,
        current_action_only: bool = False,
    ) -> tuple[Tensor, Tensor | None]:
        """
        Args:
            states: (B, L, state_dim) window of normalized states, the current one last.
            past_actions: (B, L-1, action_dim) actions taken after states 0 .. L-2.
            is_pad: (B, L) True at padded steps (before the episode start).
            start_step: (B,) episode step of the window's first real state (global position).
            horizon: (B,) index of the last state the key-state tokens may attend to.
            current_action_only: Inference: the last block updates only the current state token.
        Returns:
            (B, L, action_dim) actions read at the state tokens ((B, 1, action_dim) for the current one
            only), and (B, K, state_dim) key states, or None without key states or with current_action_only.
        """
        tokens = self._embed(states, past_actions, start_step)
        mask = hybrid_attention_mask(is_pad, self.num_key_states, horizon)
        key_state_features = None
        for index, block in enumerate(self.blocks):
            is_last = index == len(self.blocks) - 1
            tokens = block(tokens, mask[:, -1:] if is_last and current_action_only else mask)
            if index == self.config.key_state_layer:
                key_state_features = tokens[:, : self.num_key_states]
        if current_action_only:
            return self.action_head(self.final_norm(tokens[:, -1:])), None
        state_outputs = self.final_norm(tokens[:, self.num_key_states :: 2])
        key_states = self.key_state_head(key_state_features) if self.num_key_states else None
        return self.action_head(state_outputs), key_states

    def _embed(self, states: Tensor, past_actions: Tensor, start_step: Tensor) -> Tensor:
        """Interleave state and action embeddings (s_0 a_0 ... s_{L-1}) behind the key-state tokens."""
        batch_size, length, _ = states.shape
        step = start_step.clamp_max(self.config.max_episode_steps - 1)
        position = self.local_position[:, :length] + self.global_position(step)[:, None]
        state_tokens = self.state_encoder(states) + position
        action_tokens = self.action_encoder(past_actions) + position[:, : length - 1]
        sequence = states.new_zeros(batch_size, 2 * length - 1, state_tokens.shape[-1])
        sequence[:, 0::2] = state_tokens
        sequence[:, 1::2] = action_tokens
        if self.num_key_states:
            sequence = torch.cat([self.key_state_tokens.expand(batch_size, -1, -1), sequence], dim=1)
        return self.embedding_dropout(sequence)


def hybrid_attention_mask(is_pad: Tensor, num_key_states: int, horizon: Tensor) -> Tensor:
    """(B, N, N) bool mask, True where a query token (row) may attend to a key token (column).

    State/action tokens are causal and skip padded steps. Key-state tokens see each other and the window
    up to state `horizon`. State/action tokens read the key-state tokens only from step `horizon` on, so no
    action ever receives information from a later state (CoTPC lets all tokens read them, which leaks
    future states into earlier actions during training).
    """
    batch_size, length = is_pad.shape
    num_tokens = 2 * length - 1
    device = is_pad.device
    token_step = torch.arange(num_tokens, device=device) // 2
    real_token = ~is_pad[:, token_step]  # (B, N_seq)
    causal = torch.ones(num_tokens, num_tokens, dtype=torch.bool, device=device).tril()
    itself = torch.eye(num_tokens, dtype=torch.bool, device=device)  # keeps padded rows from being empty
    sequence_rows = (causal & real_token[:, None, :]) | itself
    if not num_key_states:
        return sequence_rows
    within_horizon = torch.arange(num_tokens, device=device)[None] <= 2 * horizon[:, None]  # up to s_horizon
    key_state_rows = torch.cat(
        [
            torch.ones(batch_size, num_key_states, num_key_states, dtype=torch.bool, device=device),
            (within_horizon & real_token)[:, None, :].expand(-1, num_key_states, -1),
        ],
        dim=2,
    )
    reads_key_states = (token_step[None] >= horizon[:, None])[:, :, None].expand(-1, -1, num_key_states)
    return torch.cat([key_state_rows, torch.cat([reads_key_states, sequence_rows], dim=2)], dim=1)


class Block(nn.Module):
    """Pre-LN GPT block: masked self-attention and a 4x GELU MLP, each with a residual connection."""

    def __init__(self, dim: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads, self.dropout = n_heads, dropout
        self.attention_norm = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)
        self.mlp_norm = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))
        self.residual_dropout = nn.Dropout(dropout)

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:
        """Update the last Q = mask.shape[1] tokens of x (all of them unless pruned for inference)."""
        batch_size, num_tokens, dim = x.shape
        num_queries = mask.shape[1]
        qkv = self.qkv(self.attention_norm(x)).view(batch_size, num_tokens, 3, self.n_heads, -1)
        query, key, value = qkv.permute(2, 0, 3, 1, 4)
        attended = F.scaled_dot_product_attention(
            query[:, :, -num_queries:],
            key,
            value,
            attn_mask=mask[:, None],
            dropout_p=self.dropout if self.training else 0.0,
        )
        attended = attended.transpose(1, 2).reshape(batch_size, num_queries, dim)
        x = x[:, -num_queries:] + self.residual_dropout(self.out(attended))
        return x + self.residual_dropout(self.mlp(self.mlp_norm(x)))


def mlp(*dims: int) -> nn.Sequential:
    """Linear layers with ReLU in between (none after the last)."""
    layers = []
    for index, (size_in, size_out) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        if index:
            layers.append(nn.ReLU())
        layers.append(nn.Linear(size_in, size_out))
    return nn.Sequential(*layers)


def init_weights(module: nn.Module) -> None:
    """GPT initialization as in CoTPC: N(0, 0.02) weights and embeddings, zero biases."""
    if isinstance(module, nn.Linear | nn.Embedding):
        nn.init.normal_(module.weight, std=0.02)
    if isinstance(module, nn.Linear) and module.bias is not None:
        nn.init.zeros_(module.bias)
