"""`maxmi_discovery`: a trained key-state localizer as a LeRobot processor step.

The step holds a KSL-Net (its layer sizes in `get_config`, its weights in `state_dict`) and the
concepts kept dataset-wide. Given one episode's `observation.state` sequence (frames, D) it adds
the episode's key frames (complementary data `maxmi/key_frames`) and `observation.key_states`,
the states at those frames flattened to (K_out · D,). Saved as a one-step LeRobot pipeline
(`maxmi_localizer.json` + safetensors), it annotates new datasets without retraining.

LeRobot's processors see one transition at a time; this step needs a whole episode, so it is
called on episodes, offline, by `lerobot-maxmi-discover` — not inside a policy pipeline.
"""

from dataclasses import dataclass, field
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PipelineFeatureType, PolicyFeature
from lerobot.lerobot_types import EnvTransition, TransitionKey
from lerobot.processor.pipeline import DataProcessorPipeline, ProcessorStep, ProcessorStepRegistry
from lerobot.utils.constants import OBS_STATE
from torch import Tensor

from lerobot_maxmi.discovery.ksl_net import KSLNet, to_episode_frame

KEY_STATES = "observation.key_states"
KEY_FRAMES = "maxmi/key_frames"
LOCALIZER_NAME = "maxmi_localizer"
LOCALIZER_CONFIG = f"{LOCALIZER_NAME}.json"


@ProcessorStepRegistry.register("maxmi_discovery")
@dataclass
class MaxmiDiscoveryStep(ProcessorStep):
    """Adds key frames and key states to an episode's transition (observation[state_key]: (frames, D))."""

    state_dim: int
    length: int  # T, the resampled length KSL-Net reads
    num_concepts: int
    concepts: list[int]  # concepts kept dataset-wide, in time order (one key state each)
    append_final_frame: bool = True
    embed_dim: int = 10
    encoder_dims: list[int] = field(default_factory=lambda: [256, 256, 256])
    head_dims: list[int] = field(default_factory=lambda: [256, 128])
    concept_start: str = "paper"
    state_key: str = OBS_STATE

    def __post_init__(self):
        if not self.concepts and not self.append_final_frame:
            raise ValueError("a localizer must keep at least one concept or append the final frame")
        self.net = KSLNet(
            self.state_dim,
            self.length,
            self.num_concepts,
            self.embed_dim,
            tuple(self.encoder_dims),
            tuple(self.head_dims),
            self.concept_start,
        ).eval()

    @classmethod
    def from_net(cls, net: KSLNet, concepts: list[int], append_final_frame: bool, **architecture):
        """Wrap a trained KSL-Net; `architecture` = the `KSLNetArchitecture` fields it was built with."""
        step = cls(
            state_dim=net.state_mean.shape[0],
            length=net.length,
            num_concepts=net.num_concepts,
            concepts=concepts,
            append_final_frame=append_final_frame,
            **{name: list(v) if isinstance(v, tuple) else v for name, v in architecture.items()},
        )
        step.load_state_dict(net.state_dict())
        return step

    @property
    def num_key_states(self) -> int:
        """K_out: key states per episode."""
        return len(self.concepts) + self.append_final_frame

    def key_frames(self, episodes: list[Tensor]) -> list[list[int]]:
        """Each (frames, D) episode's key frames: one per kept concept (slot order), then its last frame."""
        for i, states in enumerate(episodes):
            if states.ndim != 2 or states.shape[1] != self.state_dim:
                raise ValueError(
                    f"episode {i}: the localizer reads (frames, {self.state_dim}) states, "
                    f"got {tuple(states.shape)}; was it trained on another state feature?"
                )
        t_hat, _ = self.net.locate(episodes)
        final = [[len(states) - 1] if self.append_final_frame else [] for states in episodes]
        return [
            to_episode_frame(t, len(states), self.length).tolist() + last
            for states, t, last in zip(episodes, t_hat[:, self.concepts], final, strict=True)
        ]

    def __call__(self, transition: EnvTransition) -> EnvTransition:
        transition = transition.copy()
        observation = dict(transition[TransitionKey.OBSERVATION])
        states = torch.as_tensor(observation[self.state_key])
        (frames,) = self.key_frames([states])
        observation[KEY_STATES] = states[frames].flatten()
        transition[TransitionKey.OBSERVATION] = observation
        complementary = dict(transition.get(TransitionKey.COMPLEMENTARY_DATA) or {})
        complementary[KEY_FRAMES] = frames
        transition[TransitionKey.COMPLEMENTARY_DATA] = complementary
        return transition

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        shape = (self.num_key_states * self.state_dim,)
        features[PipelineFeatureType.OBSERVATION][KEY_STATES] = PolicyFeature(FeatureType.STATE, shape)
        return features

    def get_config(self) -> dict:
        return {
            "state_dim": self.state_dim,
            "length": self.length,
            "num_concepts": self.num_concepts,
            "concepts": list(self.concepts),
            "append_final_frame": self.append_final_frame,
            "embed_dim": self.embed_dim,
            "encoder_dims": list(self.encoder_dims),
            "head_dims": list(self.head_dims),
            "concept_start": self.concept_start,
            "state_key": self.state_key,
        }

    def state_dict(self) -> dict[str, Tensor]:
        return {name: tensor.detach().cpu().contiguous() for name, tensor in self.net.state_dict().items()}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        self.net.load_state_dict(state)
        self.net.eval()


def save_localizer(step: MaxmiDiscoveryStep, directory: Path) -> None:
    """Write the step as a one-step LeRobot pipeline: `maxmi_localizer.json` + its safetensors."""
    DataProcessorPipeline(steps=[step], name=LOCALIZER_NAME).save_pretrained(
        directory, config_filename=LOCALIZER_CONFIG
    )


def load_localizer(path_or_repo_id: str | Path) -> MaxmiDiscoveryStep:
    """The step saved by `save_localizer`, from a local directory or a hub (model) repo id."""
    pipeline = DataProcessorPipeline.from_pretrained(str(path_or_repo_id), config_filename=LOCALIZER_CONFIG)
    (step,) = pipeline.steps
    if not isinstance(step, MaxmiDiscoveryStep):
        raise TypeError(f"{path_or_repo_id} holds a {type(step).__name__}, not a maxmi_discovery localizer")
    return step
