"""Training KSL-Net and localizing key frames: determinism and input checks (tiny configs)."""

import logging
import subprocess
import sys

import pytest
import torch

from lerobot_maxmi.discovery.train import (
    DiscoveryConfig,
    KSLNetArchitecture,
    collapse_warning,
    fit_localizer,
    train_localizer,
)
from tests.conftest import load_benchmark

discovery_planted = load_benchmark("discovery_planted")


def tiny_config(**overrides):
    defaults = dict(
        num_concepts=2,
        steps=5,
        batch_size=8,
        estimator="gaussian",
        model=KSLNetArchitecture(embed_dim=4, encoder_dims=(16,), head_dims=(16,)),
    )
    return DiscoveryConfig(**{**defaults, **overrides})


def random_walks(count=8, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return [torch.cumsum(torch.randn(20 + i, 3, generator=generator), 0) for i in range(count)]


@pytest.mark.parametrize("objective", ["paper", "released"])
def test_same_seed_gives_same_key_frames(objective):
    episodes, cfg = random_walks(), tiny_config(objective=objective)
    first = fit_localizer(episodes, cfg).key_frames(episodes)
    second = fit_localizer(episodes, cfg).key_frames(episodes)
    assert first == second
    for frames, states in zip(first, episodes, strict=True):
        assert frames == sorted(frames) and frames[-1] == len(states) - 1  # final frame appended


def test_a_collapsed_objective_is_reported(caplog):
    """The released objective pulls every concept to one position on random walks; the user is told."""
    episodes = random_walks(16)
    cfg = tiny_config(objective="released", num_concepts=3, steps=30, batch_size=16)
    with caplog.at_level(logging.WARNING):
        step = fit_localizer(episodes, cfg)
    assert len(step.key_frames(episodes)[0]) == 2  # one concept + the final frame
    assert "the objective collapsed" in caplog.text


def test_every_collapse_is_named_and_a_spread_is_not():
    """Concepts merged into the final frame (seen on PegInsertionSide without the diversity term)
    leave the last state's key states: that is a collapse too, not a silent success."""
    assert "no concept is kept" in collapse_warning(0, 4)
    assert "one key state is kept" in collapse_warning(1, 4)
    assert "--discovery.num_concepts" in collapse_warning(0, 1)  # K = 1 has no diversity term to fix it
    assert collapse_warning(2, 4) is None and collapse_warning(1, 1) is None


@pytest.mark.parametrize(
    ("episodes", "message"),
    [
        ([torch.randn(1, 3)], "fewer than the 2 key states"),
        ([torch.full((20, 3), float("nan"))], "NaN or inf"),
        ([torch.randn(20)], r"\(frames, state_dim\)"),
        ([], "no episodes"),
    ],
)
def test_bad_episodes_are_rejected_clearly(episodes, message):
    with pytest.raises(ValueError, match=message):
        train_localizer(episodes, tiny_config())


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("num_concepts", 0, "num_concepts must be >= 1"),
        ("objective", "infocon", "paper, released"),
        ("estimator", "mine", "unknown estimator"),
        ("state_mi_mode", "pca", "per_dim, sliced"),
    ],
)
def test_bad_config_is_rejected_clearly(field, value, message):
    with pytest.raises(ValueError, match=message):
        tiny_config(**{field: value})


def test_an_unknown_concept_start_is_rejected_before_training():
    with pytest.raises(ValueError, match="unknown model.concept_start 'middle'; choose one of paper, spread"):
        tiny_config(model=KSLNetArchitecture(concept_start="middle"))


@pytest.mark.parametrize(
    ("state_mi_mode", "concept_start", "data_seed", "steps"),
    [("per_dim", "paper", 0, 200), ("sliced", "paper", 2, 600), ("per_dim", "spread", 2, 200)],
)
def test_maxmi_finds_planted_pauses(state_mi_mode, concept_start, data_seed, steps):
    # Per-dim MI (the default) finds both pauses on draw 0 but only one on draws 2, 3, 4 and 6, where
    # sliced MI, or per-dim MI with spread concepts, finds both (benchmarks/discovery_planted.py;
    # docs/RESULTS.md).
    cfg = discovery_planted.planted_config(concept_start, state_mi_mode=state_mi_mode, steps=steps)
    errors = discovery_planted.pause_errors(cfg, data_seed)
    median, within = errors.median().item(), (errors <= 0.05).float().mean(0).tolist()
    assert discovery_planted.within_bounds(errors), f"median error {median:.3f}; pauses within 5%: {within}"


FAULTS_WHILE_REALLOCATING = """
import resource, sys, torch
from lerobot_maxmi.cpu_memory import reuse_freed_memory
print(reuse_freed_memory(torch.device(sys.argv[1])))
size = 64 << 20  # above glibc's largest default mmap threshold (32 MB)
for _ in range(3):  # the heap grows to hold it
    torch.ones(size, dtype=torch.uint8)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    torch.ones(size, dtype=torch.uint8)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.parametrize("device", ["cpu", "meta"])
def test_freed_tensor_memory_is_reused_when_training_on_cpu(device):
    # A fresh process, so the heap's state does not depend on the tests that ran before.
    run = subprocess.run(
        [sys.executable, "-c", FAULTS_WHILE_REALLOCATING, device], capture_output=True, text=True
    )
    changed, faults = run.stdout.split()
    # Unmapped on free, each 64 MB tensor page-faults in afresh: 16,384 faults of 4 KiB pages apiece.
    if device == "cpu":
        assert changed == "True" and int(faults) < 16_384
    else:  # not CPU memory: nothing changes
        assert changed == "False" and int(faults) >= 4 * 16_384
