"""The MaxMI paper's Fig. 2: does MI(s_{t_k+σ}; s_{t_k+σ−Δt}) across demonstrations peak at key states?

    .venv/bin/python benchmarks/mi_peak.py --dataset.repo_id=local/pick --dataset.root=data/pick \
        --output=outputs/mi_peak/pick.png [--estimator=ksg] [--delta_t=2] [--max_shift=20] \
        [--state_mi_mode=sliced --seed=0]

For each ground-truth sub-goal k (per-episode `gt/key_frames` without the final frame, named by
`gt/key_frame_names` when present) and each shift σ in [−max_shift, max_shift], the pairs
(s_{t_k+σ}, s_{t_k+σ−Δt}) of all episodes where both frames exist form one sample set; its MI comes
from `lerobot_maxmi.mi.state_mi` with the chosen estimator. One PNG per dataset, one curve per
sub-goal, and a line per sub-goal on stdout: MI at σ = 0, the maximum and its shift.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import draccus
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from lerobot.utils.utils import init_logging  # noqa: E402
from torch import Tensor  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_maxmi.discovery.annotate import DatasetLocation, load_episode_states  # noqa: E402
from lerobot_maxmi.episode_metadata import GT_KEY_FRAME_NAMES, GT_KEY_FRAMES, read_episode_column  # noqa: E402
from lerobot_maxmi.mi import MIEstimator, load_estimator, state_mi  # noqa: E402


@dataclass
class MIPeakConfig:
    dataset: DatasetLocation
    output: Path = Path("outputs/mi_peak/mi_peak.png")
    state_key: str = "observation.state"
    estimator: str = "ksg"
    state_mi_mode: str = "per_dim"
    delta_t: int = 2  # frames
    max_shift: int = 20  # σ ranges over [−max_shift, max_shift] frames
    min_episodes: int = 8  # fewer pairs than this at a shift gives no estimate
    seed: int = 0  # sliced mode: the random projections, the same at every shift


def mi_curve(
    episodes: list[Tensor], anchors: list[int], shifts: list[int], cfg: MIPeakConfig, estimator: MIEstimator
) -> list[float]:
    """MI(s_{t+σ}; s_{t+σ−Δt}) over the episodes for each shift σ, t the anchor; nan where too few pairs."""
    curve = []
    for shift in shifts:
        pairs = [
            (states[t + shift], states[t + shift - cfg.delta_t])
            for states, t in zip(episodes, anchors, strict=True)
            if t + shift - cfg.delta_t >= 0 and t + shift < len(states)
        ]
        if len(pairs) < cfg.min_episodes:
            curve.append(math.nan)
            continue
        now, before = (torch.stack(side)[None] for side in zip(*pairs, strict=True))
        # A fresh generator per shift: every shift is scored with the same projections, so the
        # curve's shape comes from the states, not from the projection draw.
        projections = torch.Generator().manual_seed(cfg.seed)
        curve.append(state_mi(now, before, estimator, cfg.state_mi_mode, generator=projections).item())
    return curve


def peak(shifts: list[int], curve: list[float]) -> tuple[float, int]:
    """The curve's maximum MI and its shift."""
    return max((mi, shift) for shift, mi in zip(shifts, curve, strict=True) if not math.isnan(mi))


def plot_curves(shifts: list[int], curves: dict[str, list[float]], cfg: MIPeakConfig) -> None:
    figure, axes = plt.subplots(figsize=(6, 3.2))
    for name, curve in curves.items():
        axes.plot(shifts, curve, marker="o", markersize=2.5, label=name)
    axes.axvline(0, color="grey", linestyle="--", label="ground-truth key state")
    axes.set(
        title=f"{cfg.dataset.repo_id} ({cfg.estimator}, {cfg.state_mi_mode}, Δt = {cfg.delta_t})",
        xlabel="shift σ from the ground-truth key frame (frames)",
        ylabel="MI(s_t+σ ; s_t+σ−Δt) [nats]",
    )
    axes.legend(fontsize=7)
    figure.tight_layout()
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(cfg.output, dpi=100)
    plt.close(figure)


@draccus.wrap()
def main(cfg: MIPeakConfig) -> None:
    init_logging()
    root = cfg.dataset.resolved_root()
    states = load_episode_states(root, cfg.state_key)
    truth = read_episode_column(root, GT_KEY_FRAMES)
    first = next(iter(states))
    num_subgoals = len(truth[first]) - 1  # the last entry is the final frame
    try:
        names = read_episode_column(root, GT_KEY_FRAME_NAMES)[first][:num_subgoals]
    except KeyError:
        names = [f"sub-goal {k}" for k in range(num_subgoals)]
    estimator = load_estimator(cfg.estimator)
    shifts = list(range(-cfg.max_shift, cfg.max_shift + 1))
    episodes = list(states.values())
    curves = {
        name: mi_curve(episodes, [truth[index][k] for index in states], shifts, cfg, estimator)
        for k, name in enumerate(tqdm(names, desc="sub-goals"))
    }
    plot_curves(shifts, curves, cfg)
    for name, curve in curves.items():
        highest, shift = peak(shifts, curve)
        print(f"{name}: MI at σ=0 {curve[cfg.max_shift]:.3f}, maximum {highest:.3f} at σ={shift}")
    print(f"-> {cfg.output}")


if __name__ == "__main__":
    main()
