"""Pre/post-processing pipelines of the CoTPC policies.

LeRobot's standard steps (rename, batch, device, normalize / unnormalize, device), under their registry
names so that lerobot-train and lerobot-eval can override them. The normalizer scales
`observation.key_states` with its own statistics, which the annotator tiles from `observation.state`.
"""

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_cotpc import CotpcConfig


def make_cotpc_pre_post_processors(
    config: CotpcConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Creates the pre- and post-processing pipelines for the CoTPC policy."""
    return make_default_pre_post_processors(config, dataset_stats)


# LeRobot looks the factory up by policy type; the preset shares the pipelines.
make_cotpc_maxmi_pre_post_processors = make_cotpc_pre_post_processors
