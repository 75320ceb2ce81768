"""How close discovered key frames are to ground-truth ones.

Per episode, discovered and ground-truth key frames are matched one-to-one by the Hungarian
algorithm on |Δt|. The final frame is excluded from both sides: every selector that appends it
gets it exactly right by construction, so it would only inflate the score. The ground truth's
sub-goal frames are `gt/key_frames` without its last entry (the final frame); discovered frames
at the episode's last index are dropped.
"""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from lerobot_maxmi.discovery.annotate import load_episode_states
from lerobot_maxmi.discovery.selectors import AWEConfig, SelectionContext, make_selector
from lerobot_maxmi.discovery.train import DiscoveryConfig
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column

TOLERANCE = 0.05  # "found" = matched within 5% of the episode length


def match(found: Sequence[int], truth: Sequence[int]) -> list[tuple[int, int]]:
    """One-to-one (found, truth index) pairs minimizing the total |Δt|; min(len) pairs."""
    if not found or not truth:
        return []
    cost = np.abs(np.subtract.outer(np.asarray(found), np.asarray(truth)))
    rows, columns = linear_sum_assignment(cost)
    return [(found[r], int(c)) for r, c in zip(rows, columns, strict=True)]


@dataclass
class Quality:
    errors: list[float]  # |Δt| / episode length of every matched ground-truth key frame
    subgoals: list[int]  # which sub-goal (position in gt/key_frames) each error belongs to
    num_truth: int  # ground-truth sub-goal key frames
    num_found_within: int  # ground-truth key frames matched within the tolerance
    num_extra: int  # discovered key frames left unmatched

    def __add__(self, other: "Quality") -> "Quality":
        return Quality(
            self.errors + other.errors,
            self.subgoals + other.subgoals,
            self.num_truth + other.num_truth,
            self.num_found_within + other.num_found_within,
            self.num_extra + other.num_extra,
        )


def episode_quality(
    found: Sequence[int], truth: Sequence[int], length: int, tolerance: float = TOLERANCE
) -> Quality:
    """Score one episode; `truth` is its `gt/key_frames` (final frame last), `found` any selector's output."""
    final = length - 1
    found = [f for f in found if f != final]
    truth = list(truth[:-1])
    pairs = match(found, truth)
    errors = [abs(f - truth[subgoal]) / length for f, subgoal in pairs]
    within = sum(error <= tolerance for error in errors)
    return Quality(errors, [subgoal for _, subgoal in pairs], len(truth), within, len(found) - len(errors))


def subgoal_means(total: Quality, num_subgoals: int) -> list[float]:
    """Mean matched error (% of length) of each sub-goal, in gt/key_frames order."""
    subgoals = np.asarray(total.subgoals, dtype=int)
    counts = np.bincount(subgoals, minlength=num_subgoals)  # never matched: no mean (NaN, shown as "–")
    sums = np.bincount(subgoals, weights=np.asarray(total.errors), minlength=num_subgoals)
    with np.errstate(invalid="ignore"):
        return (100 * sums / counts).tolist()


def dataset_quality(
    found: Sequence[Sequence[int]],
    truth: Sequence[Sequence[int]],
    lengths: Sequence[int],
    tolerance: float = TOLERANCE,
) -> dict[str, float | list[float]]:
    """Key frames per episode, mean matched error (% of length) overall and per sub-goal, share of
    GT key states found within tolerance, extras per episode."""
    total = sum(
        (episode_quality(f, t, n, tolerance) for f, t, n in zip(found, truth, lengths, strict=True)),
        Quality([], [], 0, 0, 0),
    )
    return {
        "key_frames_per_episode": float(np.mean([len(f) for f in found])),
        "mean_error_pct": 100 * float(np.mean(total.errors)) if total.errors else float("nan"),
        "mean_error_pct_by_subgoal": subgoal_means(total, max(len(t) for t in truth) - 1),
        "found_within": total.num_found_within / total.num_truth if total.num_truth else float("nan"),
        "extra_per_episode": total.num_extra / len(lengths),
    }


def evaluate_selectors(
    root: Path,
    state_key: str,
    selectors: Sequence[str],
    discovery: DiscoveryConfig,
    awe: AWEConfig,
    tolerance: float = TOLERANCE,
) -> dict[str, dict[str, float]]:
    """Run each selector on the dataset at `root` and score it against its `gt/key_frames`."""
    states = load_episode_states(root, state_key)
    truth = read_episode_column(root, GT_KEY_FRAMES)
    episodes, lengths = list(states.values()), [len(s) for s in states.values()]
    context = SelectionContext(root, list(states), discovery, awe)
    results = {}
    for name in selectors:
        found = make_selector(name, context).select(episodes)
        results[name] = dataset_quality(found, [truth[i] for i in states], lengths, tolerance)
    return results


def _pct(value: float) -> str:
    return "–" if np.isnan(value) else f"{value:.1f}"  # NaN: the selector proposed no frame to score


def markdown_table(results: dict[str, dict[str, float | list[float]]], tolerance: float = TOLERANCE) -> str:
    header = (
        f"| selector | key frames / episode | mean error (% of length) | GT found within {tolerance:.0%} "
        "| extra / episode | error by sub-goal (%) |\n|---|---|---|---|---|---|"
    )
    rows = [
        f"| {name} | {r['key_frames_per_episode']:.1f} | {_pct(r['mean_error_pct'])} "
        f"| {r['found_within']:.0%} | {r['extra_per_episode']:.1f} "
        f"| {' / '.join(map(_pct, r['mean_error_pct_by_subgoal'])) or '–'} |"
        for name, r in results.items()
    ]
    return "\n".join([header, *rows])
