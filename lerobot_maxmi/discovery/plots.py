"""One PNG per episode: a few standardized state dims over time, with its key frames marked."""

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from torch import Tensor  # noqa: E402

MAX_DIMS = 6


def plot_episode(
    states: Tensor, key_frames: Sequence[int], gt_key_frames: Sequence[int] | None, path: Path, title: str
) -> None:
    standardized = (states - states.mean(0)) / states.std(0).clamp_min(1e-6)
    figure, axes = plt.subplots(figsize=(8, 3))
    for dim in range(min(MAX_DIMS, states.shape[1])):
        axes.plot(standardized[:, dim].numpy(), linewidth=1, label=f"dim {dim}")
    for i, frame in enumerate(key_frames):
        axes.axvline(frame, color="red", linewidth=1.5, label="discovered" if i == 0 else None)
    for i, frame in enumerate(gt_key_frames or []):
        label = "ground truth" if i == 0 else None
        axes.axvline(frame, color="green", linestyle="--", linewidth=1.5, label=label)
    axes.set(title=title, xlabel="frame", ylabel="standardized state")
    axes.legend(fontsize=6, loc="upper left", ncol=2)
    figure.tight_layout()
    figure.savefig(path, dpi=80)
    plt.close(figure)
