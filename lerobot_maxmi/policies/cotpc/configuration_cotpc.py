"""Configuration of the CoTPC policy (Chain-of-Thought Predictive Control, Jia et al. 2023).

Two registered types share this code: `cotpc` uses key states when the dataset has them and
trains plain causal-transformer behaviour cloning when it does not; `cotpc_maxmi` requires the key
states that `lerobot-maxmi-discover` writes (the MaxMI recipe).
"""

from dataclasses import dataclass, field
from typing import ClassVar

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamWConfig, CosineDecayWithWarmupSchedulerConfig
from lerobot.utils.constants import OBS_STATE

OBS_KEY_STATES = "observation.key_states"
DISCOVER_HINT = (
    "Annotate the dataset first and train on the output: `lerobot-maxmi-discover --dataset.repo_id=<id> "
    "--dataset.root=<dir> --output.repo_id=<id>_maxmi` writes `observation.key_states`. "
    "For the no-key-state baseline train `--policy.type=cotpc` instead."
)


@PreTrainedConfig.register_subclass("cotpc")
@dataclass
class CotpcConfig(PreTrainedConfig):
    """Configuration class for the CoTPC policy.

    Defaults follow the paper's recipe (4 layers, 8 heads, width 128, 60-step context, AdamW 5e-4 with
    betas 0.9/0.95, 1000 warm-up steps then cosine decay to 0.1x, key-state loss weight 0.1).

    Inputs: `observation.state` (required) and, during training only, the key-state column
    `key_states_feature`: every frame of an episode holds the episode's K key states flattened to
    (K * state_dim,), so K = its size // state_dim. Output: `action`.

    Args:
        context_length: Steps of (state, action) history in one window; the action is read at the last
            state token.
        max_episode_steps: Size of the global (episode-time) position table; later steps reuse its last row.
        key_states_feature: Dataset column holding the key states. `None` trains the no-key-state baseline
            even on an annotated dataset.
        key_state_layer: Index of the transformer block whose key-state token outputs feed the key-state
            head (CoTPC's `key_state_loss`, 0 = first block).
        key_state_loss_weight: Weight alpha of the key-state MSE added to the action MSE.
        fps: Frame rate of the training data, used to turn the loader's `timestamp` into an episode step.
            Filled in from the dataset when training starts.
    """

    # Subclasses that must not train without key states set this.
    requires_key_states: ClassVar[bool] = False

    # Input / output structure.
    context_length: int = 60
    max_episode_steps: int = 1000
    key_states_feature: str | None = OBS_KEY_STATES
    fps: int | None = None

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD,
        }
    )

    # Architecture.
    dim_model: int = 128
    n_heads: int = 8
    n_layers: int = 4
    dim_encoder_hidden: int = 256
    dim_head_hidden: int = 256
    dropout: float = 0.0
    key_state_layer: int = 0

    # Loss.
    key_state_loss_weight: float = 0.1

    # Training preset.
    optimizer_lr: float = 5e-4
    optimizer_betas: tuple[float, float] = (0.9, 0.95)
    optimizer_weight_decay: float = 0.0
    scheduler_warmup_steps: int = 1000
    scheduler_decay_steps: int = 1_600_000
    scheduler_final_lr_ratio: float = 0.1

    # Checkpoints stay local unless asked for: `--policy.push_to_hub=true --policy.repo_id=...`.
    push_to_hub: bool = False

    def __post_init__(self):
        super().__post_init__()
        if self.context_length < 1:
            raise ValueError(f"`context_length` must be >= 1, got {self.context_length}.")
        if self.dim_model % self.n_heads:
            raise ValueError(f"`dim_model` ({self.dim_model}) must be a multiple of `n_heads`.")
        if not 0 <= self.key_state_layer < self.n_layers:
            raise ValueError(f"`key_state_layer` must be in [0, n_layers), got {self.key_state_layer}.")

    @property
    def state_dim(self) -> int:
        return self.robot_state_feature.shape[0]

    @property
    def action_dim(self) -> int:
        return self.action_feature.shape[0]

    @property
    def num_key_states(self) -> int:
        """K, from the key-state column's size; 0 when the policy trains without key states."""
        if self.key_states_feature is None or self.key_states_feature not in self.input_features:
            return 0
        return self.input_features[self.key_states_feature].shape[0] // self.state_dim

    def validate_features(self) -> None:
        if self.robot_state_feature is None:
            raise ValueError(f"CoTPC needs `{OBS_STATE}` among the input features.")
        if self.action_feature is None:
            raise ValueError("CoTPC needs an `action` output feature.")
        if self.key_states_feature in self.input_features:
            size = self.input_features[self.key_states_feature].shape[0]
            if size == 0 or size % self.state_dim:
                raise ValueError(
                    f"`{self.key_states_feature}` has size {size}, not a positive multiple of the state "
                    f"dimension {self.state_dim}: it must hold K key states of `{OBS_STATE}` flattened."
                )
        elif self.requires_key_states:
            raise ValueError(
                f"Policy type '{self.type}' needs the key-state column `{self.key_states_feature}`, "
                f"which the dataset lacks. {DISCOVER_HINT}"
            )

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(
            lr=self.optimizer_lr, betas=self.optimizer_betas, weight_decay=self.optimizer_weight_decay
        )

    def get_scheduler_preset(self) -> CosineDecayWithWarmupSchedulerConfig:
        # LeRobot shrinks warm-up and decay proportionally when `--steps` is below `scheduler_decay_steps`.
        return CosineDecayWithWarmupSchedulerConfig(
            num_warmup_steps=self.scheduler_warmup_steps,
            num_decay_steps=self.scheduler_decay_steps,
            peak_lr=self.optimizer_lr,
            decay_lr=self.optimizer_lr * self.scheduler_final_lr_ratio,
        )

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.context_length, 1))

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(1 - self.context_length, 1))

    @property
    def reward_delta_indices(self) -> None:
        return None


@PreTrainedConfig.register_subclass("cotpc_maxmi")
@dataclass
class CotpcMaxmiConfig(CotpcConfig):
    """CoTPC guided by MaxMI key states: the same model, but training requires the key-state column."""

    requires_key_states: ClassVar[bool] = True
