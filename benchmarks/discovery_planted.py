"""Does MaxMI find planted bottlenecks? Random walks that pause twice per episode, per state-MI mode.

    .venv/bin/python benchmarks/discovery_planted.py                       # both modes, data seeds 0-7
    .venv/bin/python benchmarks/discovery_planted.py --modes sliced --data_seeds 0 2 --steps 600
    .venv/bin/python benchmarks/discovery_planted.py --modes per_dim --concept_start spread

Each data seed draws 64 episodes of a 3-d random walk (50-70 frames) that holds still for 6
frames around two planted times. While still, s_t = s_t-Δt in every episode, so MI across
episodes peaks there: the structure MaxMI looks for. A small KSL-Net (K = 4, no final frame)
trains on them; each pause is scored by its distance to the nearest key frame, as a fraction of
the episode. The unit test (tests/test_discovery_train.py) holds three cases to the bounds of the
last column: per-dim MI (the default) on data seed 0 after 200 steps, sliced MI on data seed 2, and
per-dim MI with the concepts started spread out (--concept_start spread) on data seed 2.
"""

import argparse

import torch
from run_table import machine  # benchmarks/ is this script's import root

from lerobot_maxmi.discovery.ksl_net import CONCEPT_STARTS
from lerobot_maxmi.discovery.train import DiscoveryConfig, KSLNetArchitecture, fit_localizer
from lerobot_maxmi.mi import STATE_MI_MODES

MEDIAN_BOUND = 0.03  # median distance to the nearest key frame, fraction of the episode
WITHIN_5_PERCENT_BOUND = 0.85  # share of pauses with a key frame within 5% of the episode


def random_walks_with_pauses(count: int = 64, seed: int = 0) -> tuple[list[torch.Tensor], list[list[int]]]:
    """`count` episodes of (frames, 3) states, and each episode's two pause centres."""
    generator = torch.Generator().manual_seed(seed)
    episodes, pauses = [], []
    for _ in range(count):
        length = int(torch.randint(50, 71, (1,), generator=generator))
        steps = torch.randn(length, 3, generator=generator)
        centres = [int(length * (low + 0.1 * torch.rand(1, generator=generator))) for low in (0.25, 0.65)]
        for centre in centres:
            steps[centre - 3 : centre + 3] = 0.0
        episodes.append(torch.cumsum(steps, 0))
        pauses.append(centres)
    return episodes, pauses


def planted_config(concept_start: str = "paper", **overrides) -> DiscoveryConfig:
    """The discovery defaults, with K = 4 and a small KSL-Net; no final frame, which is not a pause."""
    small = KSLNetArchitecture(encoder_dims=(64, 64), head_dims=(64,), concept_start=concept_start)
    return DiscoveryConfig(**{"num_concepts": 4, "append_final_frame": False, "model": small, **overrides})


def pause_errors(cfg: DiscoveryConfig, data_seed: int) -> torch.Tensor:
    """(episodes, 2): each pause's distance to the nearest discovered key frame, fraction of the episode."""
    episodes, pauses = random_walks_with_pauses(seed=data_seed)
    found = fit_localizer(episodes, cfg).key_frames(episodes)
    return torch.tensor(
        [
            [min(abs(frame - centre) for frame in frames) / len(states) for centre in centres]
            for frames, centres, states in zip(found, pauses, episodes, strict=True)
        ]
    )


def within_bounds(errors: torch.Tensor) -> bool:
    return errors.median() <= MEDIAN_BOUND and within_5_percent(errors) >= WITHIN_5_PERCENT_BOUND


def within_5_percent(errors: torch.Tensor) -> float:
    return (errors <= 0.05).float().mean().item()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--modes", nargs="+", default=list(STATE_MI_MODES), choices=STATE_MI_MODES)
    parser.add_argument("--data_seeds", nargs="+", type=int, default=list(range(8)))
    parser.add_argument("--steps", type=int, default=600, help="KSL-Net training steps")
    parser.add_argument("--seed", type=int, default=0, help="--discovery.seed")
    parser.add_argument(
        "--concept_start", default="paper", choices=CONCEPT_STARTS, help="--discovery.model.concept_start"
    )
    args = parser.parse_args()

    print(
        f"\nplanted pauses, {machine()}, {args.steps} steps, discovery seed {args.seed}, "
        f"concepts start {args.concept_start}\n"
    )
    print("| state MI | data seed | median error | within 5% | within the test's bounds |")
    print("|---|---:|---:|---:|---|")
    for mode in args.modes:
        cfg = planted_config(args.concept_start, state_mi_mode=mode, steps=args.steps, seed=args.seed)
        for data_seed in args.data_seeds:
            errors = pause_errors(cfg, data_seed)
            scores = f"{errors.median():.1%} | {within_5_percent(errors):.0%}"
            verdict = "yes" if within_bounds(errors) else "no"
            print(f"| {mode} | {data_seed} | {scores} | {verdict} |", flush=True)


if __name__ == "__main__":
    main()
