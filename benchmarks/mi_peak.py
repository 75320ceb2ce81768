"""The MaxMI paper's Fig. 2: does MI(s_{t_k+σ}; s_{t_k+σ−Δt}) across demonstrations peak at key states?

    .venv/bin/python benchmarks/mi_peak.py --dataset.repo_id=local/pick --dataset.root=data/pick \
        --output_dir=outputs/mi_peak [--estimator=ksg] [--delta_t=2] [--max_shift=20]

For each ground-truth key state k (per-episode `gt/key_frames`, named by `gt/key_frame_names` when
present) and each shift σ in [−max_shift, max_shift], the pairs (s_{t_k+σ}, s_{t_k+σ−Δt}) of all
episodes where both frames exist form one sample set; its MI comes from
`lerobot_maxmi.mi.state_mi` with the chosen estimator. One PNG per key state in `output_dir`.
"""

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
    output_dir: Path = Path("outputs/mi_peak")
    state_key: str = "observation.state"
    estimator: str = "ksg"
    state_mi_mode: str = "per_dim"
    delta_t: int = 2  # frames
    max_shift: int = 20  # σ ranges over [−max_shift, max_shift] frames
    min_episodes: int = 8  # fewer pairs than this at a shift gives no estimate


def mi_at_shift(
    episodes: list[Tensor], anchors: list[int], shift: int, cfg: MIPeakConfig, estimator: MIEstimator
) -> float:
    pairs = [
        (states[t + shift], states[t + shift - cfg.delta_t])
        for states, t in zip(episodes, anchors, strict=True)
        if t + shift - cfg.delta_t >= 0 and t + shift < len(states)
    ]
    if len(pairs) < cfg.min_episodes:
        return float("nan")
    now, before = (torch.stack(side)[None] for side in zip(*pairs, strict=True))
    return state_mi(now, before, estimator, cfg.state_mi_mode).item()


def plot_curve(shifts: list[int], mi: list[float], title: str, path: Path, delta_t: int) -> None:
    figure, axes = plt.subplots(figsize=(5, 3))
    axes.plot(shifts, mi, marker="o", markersize=3)
    axes.axvline(0, color="green", linestyle="--", label="ground-truth key state")
    axes.set(title=title, xlabel="shift σ (frames)", ylabel=f"MI(s_t+σ; s_t+σ−{delta_t}) [nats]")
    axes.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


@draccus.wrap()
def main(cfg: MIPeakConfig) -> None:
    init_logging()
    root = cfg.dataset.resolved_root()
    states = load_episode_states(root, cfg.state_key)
    truth = read_episode_column(root, GT_KEY_FRAMES)
    try:
        names = read_episode_column(root, GT_KEY_FRAME_NAMES)[next(iter(states))]
    except KeyError:
        names = [f"key{k}" for k in range(len(truth[next(iter(states))]))]
    estimator = load_estimator(cfg.estimator)
    shifts = list(range(-cfg.max_shift, cfg.max_shift + 1))
    episodes = list(states.values())
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        anchors = [truth[index][k] for index in states]
        mi = [mi_at_shift(episodes, anchors, s, cfg, estimator) for s in tqdm(shifts, desc=name)]
        path = cfg.output_dir / f"{k}_{name}.png"
        plot_curve(shifts, mi, f"{cfg.dataset.repo_id}: {name} ({cfg.estimator})", path, cfg.delta_t)
        peak = shifts[max(range(len(mi)), key=lambda i: mi[i] if mi[i] == mi[i] else float("-inf"))]
        print(f"{name}: MI at σ=0 {mi[cfg.max_shift]:.3f}, maximum at σ={peak} -> {path}")


if __name__ == "__main__":
    main()
