"""Discovered vs ground-truth key frames, every selector side by side; prints a markdown table.

    .venv/bin/python benchmarks/discovery_quality.py --dataset.repo_id=local/pick --dataset.root=data/pick \
        [--selectors='[maxmi,uniform,awe,last_state]'] [--discovery.steps=2000] [--output=quality.md]

The dataset needs per-episode `gt/key_frames` (the ManiSkill demo generator writes them). Per
episode, discovered and ground-truth key frames are matched one-to-one (Hungarian on |Δt|); the
final frame is left out on both sides (see `lerobot_maxmi.discovery.quality`). Columns: mean
|Δt| of matched ground-truth key frames as % of the episode length, the share of ground-truth key
frames matched within the tolerance, unmatched discovered frames per episode, and the mean error of
each sub-goal in `gt/key_frames` order (e.g. PickCube: grasp; StackCube: grasp / A on B).
"""

from dataclasses import dataclass, field
from pathlib import Path

import draccus
from lerobot.utils.utils import init_logging

from lerobot_maxmi.discovery.annotate import DatasetLocation
from lerobot_maxmi.discovery.quality import TOLERANCE, evaluate_selectors, markdown_table
from lerobot_maxmi.discovery.selectors import AWEConfig
from lerobot_maxmi.discovery.train import DiscoveryConfig


@dataclass
class QualityConfig:
    dataset: DatasetLocation
    selectors: list[str] = field(default_factory=lambda: ["maxmi", "uniform", "awe", "last_state"])
    discovery: DiscoveryConfig = field(default_factory=DiscoveryConfig)
    awe: AWEConfig = field(default_factory=AWEConfig)
    state_key: str = "observation.state"
    tolerance: float = TOLERANCE
    output: Path | None = None  # also write the table here


@draccus.wrap()
def main(cfg: QualityConfig) -> None:
    init_logging()
    results = evaluate_selectors(
        cfg.dataset.resolved_root(), cfg.state_key, cfg.selectors, cfg.discovery, cfg.awe, cfg.tolerance
    )
    table = markdown_table(results, cfg.tolerance)
    print(f"\n{cfg.dataset.repo_id}: key frames vs gt/key_frames (final frame excluded)\n\n{table}")
    if cfg.output:
        cfg.output.write_text(table + "\n")


if __name__ == "__main__":
    main()
