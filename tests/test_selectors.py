"""Baseline selectors, AWE's dynamic program, dataset-wide NMS and the key-frame quality metrics."""

import math

import pytest
import torch

from lerobot_maxmi.discovery.awe import dp_waypoints, segment_errors
from lerobot_maxmi.discovery.nms import shared_concepts
from lerobot_maxmi.discovery.quality import (
    dataset_quality,
    episode_quality,
    evaluate_selectors,
    markdown_table,
    match,
)
from lerobot_maxmi.discovery.selectors import (
    AWEConfig,
    SelectionContext,
    UniformSelector,
    make_selector,
)
from lerobot_maxmi.discovery.train import DiscoveryConfig


def polyline(corners: list[tuple[float, float]], steps: int) -> torch.Tensor:
    """Straight segments between corners, `steps` frames each (the corners are frames 0, steps, ...)."""
    points = [torch.tensor(corners[0])]
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        a, b = torch.tensor(a), torch.tensor(b)
        points += [a + (b - a) * (i / steps) for i in range(1, steps + 1)]
    return torch.stack(points)


def test_awe_finds_the_corners_of_a_polyline():
    path = polyline([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (2.0, 1.0)], steps=10)
    assert dp_waypoints(path, error_threshold=0.01) == [10, 20, 30]
    assert dp_waypoints(path, error_threshold=10.0) == [30]  # one segment explains everything


def test_awe_segment_error_is_the_point_to_segment_distance():
    points = torch.tensor([[0.0, 0.0], [1.0, 2.0], [2.0, 0.0]])
    assert segment_errors(points, 2).tolist() == pytest.approx([2.0, 0.0])


def test_uniform_frames_are_evenly_spaced_and_end_at_the_final_frame():
    assert UniformSelector.frames(31, 2, append_final=True) == [10, 20, 30]
    assert UniformSelector.frames(31, 1, append_final=False) == [15]


def test_baseline_selectors_on_episodes(tmp_path):
    episodes = [polyline([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)], steps=10), torch.randn(15, 2).cumsum(0)]
    context = SelectionContext(tmp_path, [0, 1], awe=AWEConfig(error_threshold=0.001))
    assert make_selector("last_state", context).select(episodes) == [[20], [14]]
    awe = make_selector("awe", context).select(episodes)
    assert awe[0] == [10, 20] and awe[1][-1] == 14
    with pytest.raises(ValueError, match="unknown selector 'clip'"):
        make_selector("clip", context)


def test_awe_warns_when_noise_makes_it_keep_most_frames(tmp_path, caplog):
    noisy = [torch.randn(40, 30, generator=torch.Generator().manual_seed(0))]
    context = SelectionContext(tmp_path, [0], awe=AWEConfig(error_threshold=0.1))
    make_selector("awe", context).select(noisy)
    assert "Raise the threshold" in caplog.text
    caplog.clear()
    context.awe.error_threshold = 10.0  # every frame within reach of one segment
    assert make_selector("awe", context).select(noisy) == [[39]]
    assert "Raise the threshold" not in caplog.text


def test_shared_concepts_merge_duplicates_dataset_wide():
    # Concepts 0 and 2 sit at the same place (keep the more confident 2); concept 3 is at the end,
    # which the appended final frame stands for.
    fractions, scores = [0.3, 0.6, 0.31, 0.99], [0.2, 0.5, 0.9, 0.5]
    assert shared_concepts(fractions, scores, 0.05, append_final=True) == [2, 1]
    assert shared_concepts(fractions, scores, 0.05, append_final=False) == [2, 1, 3]


def test_matching_is_one_to_one_and_minimizes_total_offset():
    assert sorted(match([10, 12], [11, 30])) == [(10, 0), (12, 1)]  # total 19, not 21
    assert match([5, 50, 95], [48]) == [(50, 0)]
    assert match([], [5]) == []


def test_episode_quality_excludes_the_final_frame_and_counts_extras():
    # GT: sub-goals at 20 and 60, final 99. Found: 22 (2% off), 80 (20% off), 40 (extra), 99 (final).
    quality = episode_quality([22, 40, 80, 99], [20, 60, 99], length=100)
    assert sorted(quality.errors) == pytest.approx([0.02, 0.2])
    assert dict(zip(quality.subgoals, quality.errors, strict=True)) == pytest.approx({0: 0.02, 1: 0.2})
    assert (quality.num_truth, quality.num_found_within, quality.num_extra) == (2, 1, 1)


def test_dataset_quality_reports_percentages():
    summary = dataset_quality([[22, 99], [99]], [[20, 99], [50, 99]], [100, 100])
    assert summary["mean_error_pct"] == pytest.approx(2.0)
    assert summary["mean_error_pct_by_subgoal"] == pytest.approx([2.0])
    assert summary["found_within"] == pytest.approx(0.5)  # episode 2's sub-goal was not found
    assert summary["extra_per_episode"] == 0
    assert math.isnan(dataset_quality([[9]], [[9]], [10])["mean_error_pct"])  # nothing to match


def test_dataset_quality_breaks_the_error_down_by_subgoal():
    # Sub-goal 0 found 1% and 3% off, sub-goal 1 10% off, sub-goal 2 never matched.
    summary = dataset_quality([[21, 50, 99], [47, 70]], [[20, 60, 80, 99], [50, 99]], [100, 100])
    by_subgoal = summary["mean_error_pct_by_subgoal"]
    assert by_subgoal[:2] == pytest.approx([2.0, 10.0])
    assert math.isnan(by_subgoal[2])
    assert summary["mean_error_pct"] == pytest.approx(14 / 3)


def test_selectors_side_by_side_against_ground_truth(tmp_path):
    from tests.test_annotate import make_dataset

    root = make_dataset(tmp_path / "src")  # gt/key_frames = [length // 2, length - 1]
    results = evaluate_selectors(
        root,
        "observation.state",
        ["ground_truth", "last_state", "uniform"],
        DiscoveryConfig(num_concepts=1),
        AWEConfig(),
    )
    assert results["ground_truth"] == {
        "mean_error_pct": 0.0,
        "mean_error_pct_by_subgoal": [0.0],
        "found_within": 1.0,
        "extra_per_episode": 0.0,
        "key_frames_per_episode": 2.0,
    }
    assert results["last_state"]["found_within"] == 0.0 and math.isnan(
        results["last_state"]["mean_error_pct"]
    )
    assert results["uniform"]["found_within"] == 1.0  # one interior frame at the middle
    table = markdown_table(results)
    assert table.splitlines()[2].startswith("| ground_truth | 2.0 | 0.0 | 100% | 0.0 | 0.0 |")


def test_an_annotated_dataset_is_scored_from_its_stored_key_frames(tmp_path):
    from lerobot_maxmi.discovery.annotate import annotate
    from tests.test_annotate import config, make_dataset

    source = make_dataset(tmp_path / "src")
    out = annotate(config(source, tmp_path / "out", "--selector=uniform", "--discovery.num_concepts=3"))
    discovery = DiscoveryConfig(num_concepts=3)
    scores = [
        evaluate_selectors(root, "observation.state", [name], discovery, AWEConfig())[name]
        for root, name in [(source, "uniform"), (out, "annotated")]
    ]
    assert scores[0] == scores[1] and scores[0]["key_frames_per_episode"] == 4.0
    missing = "needs per-episode 'maxmi/key_frames'.*lerobot-maxmi-discover writes it"
    with pytest.raises(ValueError, match=missing):
        evaluate_selectors(source, "observation.state", ["annotated"], DiscoveryConfig(), AWEConfig())
