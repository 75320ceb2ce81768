"""Key-frame selectors: MaxMI and the baselines it is compared with, behind one interface.

Every selector returns, per episode, a list of frame indices (the key frames, the final frame
last where the selector uses it), so the annotator writes all of them in the same format.
"""

import abc
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from lerobot_maxmi.discovery.awe import dp_waypoints
from lerobot_maxmi.discovery.processor import KEY_FRAMES, MaxmiDiscoveryStep, load_localizer, save_localizer
from lerobot_maxmi.discovery.train import DiscoveryConfig, check_episodes, fit_localizer, training_record
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column

LOCALIZER_DIR = "maxmi_localizer"  # inside the annotated dataset's root
TRAINING_RECORD = "discovery_config.json"  # beside a localizer trained here


@dataclass
class AWEConfig:
    # Largest allowed distance of a frame from its reconstructing segment, as an RMS over the
    # used state dims in units of each dim's dataset std (states mix metres, radians, flags).
    error_threshold: float = 0.1
    dims: list[int] | None = None  # state dims to reconstruct (e.g. the end-effector position); None = all


@dataclass
class SelectionContext:
    """What selectors may need besides the episodes' states."""

    dataset_root: Path
    episode_indices: list[int]
    discovery: DiscoveryConfig = field(default_factory=DiscoveryConfig)
    awe: AWEConfig = field(default_factory=AWEConfig)


class KeyFrameSelector(abc.ABC):
    name: str  # set by register_selector

    def __init__(self, context: SelectionContext):
        self.context = context

    @abc.abstractmethod
    def select(self, episodes: list[Tensor]) -> list[list[int]]:
        """Key frames of each (frames, D) episode."""

    def save(self, dataset_root: Path) -> None:  # noqa: B027  (most selectors have nothing to save)
        """Store what is needed to repeat the selection on new data."""


SELECTORS: dict[str, type[KeyFrameSelector]] = {}


def register_selector(name: str) -> Callable[[type[KeyFrameSelector]], type[KeyFrameSelector]]:
    def register(cls: type[KeyFrameSelector]) -> type[KeyFrameSelector]:
        SELECTORS[name], cls.name = cls, name
        return cls

    return register


def make_selector(name: str, context: SelectionContext) -> KeyFrameSelector:
    if name not in SELECTORS:
        raise ValueError(f"unknown selector {name!r}; choose one of {', '.join(SELECTORS)}")
    return SELECTORS[name](context)


@register_selector("maxmi")
class MaxMISelector(KeyFrameSelector):
    """KSL-Net trained with the MaxMI criterion (or a saved one, `discovery.pretrained_path`)."""

    step: MaxmiDiscoveryStep | None = None

    def select(self, episodes: list[Tensor]) -> list[list[int]]:
        cfg = self.context.discovery
        if cfg.pretrained_path:
            self.step = load_localizer(cfg.pretrained_path)
        else:
            self.step = fit_localizer(episodes, cfg)
        check_episodes(episodes, self.step.num_key_states)
        return self.step.key_frames(episodes)

    def save(self, dataset_root: Path) -> None:
        directory = dataset_root / LOCALIZER_DIR
        save_localizer(self.step, directory)
        if not self.context.discovery.pretrained_path:
            record = training_record(self.context.discovery)
            (directory / TRAINING_RECORD).write_text(json.dumps(record, indent=2))


@register_selector("last_state")
class LastStateSelector(KeyFrameSelector):
    """Only the final frame: the goal-conditioning baseline of the MaxMI paper (Table 4)."""

    def select(self, episodes: list[Tensor]) -> list[list[int]]:
        return [[len(states) - 1] for states in episodes]


@register_selector("uniform")
class UniformSelector(KeyFrameSelector):
    """K = `discovery.num_concepts` frames evenly spaced inside the episode (then the final frame)."""

    def select(self, episodes: list[Tensor]) -> list[list[int]]:
        cfg = self.context.discovery
        check_episodes(episodes, cfg.num_concepts + cfg.append_final_frame)
        return [self.frames(len(states), cfg.num_concepts, cfg.append_final_frame) for states in episodes]

    @staticmethod
    def frames(length: int, count: int, append_final: bool) -> list[int]:
        interior = [round(i * (length - 1) / (count + 1)) for i in range(1, count + 1)]
        return interior + ([length - 1] if append_final else [])


@register_selector("awe")
class AWESelector(KeyFrameSelector):
    """AWE's dynamic-programming waypoints on standardized states (see `awe.py`)."""

    def select(self, episodes: list[Tensor]) -> list[list[int]]:
        awe = self.context.awe
        dims = awe.dims if awe.dims is not None else list(range(episodes[0].shape[1]))
        frames = torch.cat(episodes)[:, dims]
        mean, std = frames.mean(0), frames.std(0).clamp_min(1e-6)
        # Distances in std units, divided by √D so the threshold is a per-dim RMS.
        scale = std * len(dims) ** 0.5
        standardized = [(states[:, dims] - mean) / scale for states in episodes]
        waypoints = [dp_waypoints(states, awe.error_threshold) for states in standardized]
        warn_if_most_frames_kept(waypoints, episodes, awe.error_threshold)
        return waypoints


def warn_if_most_frames_kept(waypoints: list[list[int]], episodes: list[Tensor], threshold: float) -> None:
    """Noisy states defeat AWE's reconstruction: nearly every frame becomes a key state."""
    kept = sum(map(len, waypoints)) / len(waypoints)
    length = sum(map(len, episodes)) / len(episodes)
    if kept > length / 2:
        logging.warning(
            "AWE kept %.1f of %.1f frames per episode at --awe.error_threshold=%g: the states are too "
            "noisy for it to skip frames. Raise the threshold (FrankaKitchen-v1's 30-d state keeps about "
            "13 at 0.5) or reconstruct only smooth dims with --awe.dims",
            kept,
            length,
            threshold,
        )


class StoredKeyFramesSelector(KeyFrameSelector):
    """Key frames a dataset already carries in a per-episode metadata column."""

    column: str
    written_by: str  # named in the error when the column is missing

    def select(self, episodes: list[Tensor]) -> list[list[int]]:
        try:
            stored = read_episode_column(self.context.dataset_root, self.column)
        except KeyError as error:
            raise ValueError(
                f"selector {self.name!r} needs per-episode {self.column!r} metadata, which the dataset at "
                f"{self.context.dataset_root} lacks ({self.written_by} writes it); pick another --selector"
            ) from error
        result = []
        for index, states in zip(self.context.episode_indices, episodes, strict=True):
            frames = [int(f) for f in stored[index]]
            if not frames or not all(0 <= f < len(states) for f in frames):
                raise ValueError(f"episode {index}: {self.column} {frames} is empty or outside its frames")
            result.append(frames)
        return result


@register_selector("ground_truth")
class GroundTruthSelector(StoredKeyFramesSelector):
    """The demo generator's `gt/key_frames` (first frame of each sub-goal, then the final frame)."""

    column, written_by = GT_KEY_FRAMES, "the ManiSkill demo generator"


@register_selector("annotated")
class AnnotatedSelector(StoredKeyFramesSelector):
    """The key frames an earlier `lerobot-maxmi-discover` run wrote, to score them against ground truth."""

    column, written_by = KEY_FRAMES, "lerobot-maxmi-discover"
