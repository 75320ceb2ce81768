"""`lerobot-maxmi-pretrain-mi`: tiny runs of the real training loop."""

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from lerobot_maxmi.mi.infonet import InfoNetConfig
from lerobot_maxmi.mi.normalize import gaussian_copula_mi
from lerobot_maxmi.mi.pretrain import CHECKPOINT_DIR, FINAL_DIR, PretrainMIConfig, draw_batch, pretrain


def tiny_config(output_dir, steps):
    return PretrainMIConfig(
        output_dir=output_dir,
        steps=steps,
        batch_size=4,
        warmup_steps=10,
        min_samples=16,
        max_samples=32,
        critic_samples=32,
        mc_samples=64,
        max_components=3,
        save_freq=2,
        device="cpu",
        model=InfoNetConfig(dim=16, num_latents=4, num_heads=2, num_layers=1, grid_size=8, num_frequencies=2),
    )


def weights(directory):
    return load_file(directory / "model.safetensors")


def test_resumed_run_matches_uninterrupted_run(tmp_path):
    straight = pretrain(tiny_config(tmp_path / "straight", steps=4))
    pretrain(tiny_config(tmp_path / "resumed", steps=2))
    resumed_cfg = tiny_config(tmp_path / "resumed", steps=4)
    resumed_cfg.resume = True
    resumed = pretrain(resumed_cfg)
    a, b = weights(straight), weights(resumed)
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], msg=key)


def test_refuses_to_overwrite_without_resume(tmp_path):
    pretrain(tiny_config(tmp_path, steps=2))
    assert (tmp_path / CHECKPOINT_DIR / "training_state.pt").exists()
    with pytest.raises(FileExistsError, match="--resume=true"):
        pretrain(tiny_config(tmp_path, steps=2))


def test_command_line_entry_point(tmp_path):
    args = [
        f"--output_dir={tmp_path}",
        "--steps=1",
        "--batch_size=2",
        "--min_samples=16",
        "--max_samples=16",
        "--critic_samples=16",
        "--mc_samples=32",
        "--model.dim=8",
        "--model.num_latents=2",
        "--model.num_heads=2",
        "--model.num_layers=1",
        "--model.grid_size=4",
        "--device=cpu",
    ]
    command = Path(sys.executable).parent / "lerobot-maxmi-pretrain-mi"  # the installed console script
    result = subprocess.run([command, *args], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / FINAL_DIR / "model.safetensors").exists()


def test_regression_head_stage_trains_only_the_head(tmp_path):
    base = pretrain(tiny_config(tmp_path / "base", steps=2))

    def head_stage(name, steps):
        cfg = tiny_config(tmp_path / name, steps=steps)
        cfg.init_from, cfg.trainable = str(base), "regression_head"
        return weights(pretrain(cfg))

    untrained, trained, backbone = head_stage("start", 0), head_stage("head", 3), weights(base)
    for key, tensor in trained.items():
        if key.startswith("regression_head."):
            assert not torch.equal(tensor, untrained[key]), f"{key} did not learn"
        else:
            torch.testing.assert_close(tensor, backbone[key], rtol=0, atol=0, msg=key)


def test_fine_tuning_all_starts_from_every_saved_tensor(tmp_path):
    base = pretrain(tiny_config(tmp_path / "base", steps=2))
    cfg = tiny_config(tmp_path / "fine_tune", steps=0)
    cfg.init_from = str(base)
    started = weights(pretrain(cfg))
    for key, tensor in weights(base).items():
        torch.testing.assert_close(started[key], tensor, rtol=0, atol=0, msg=key)


def test_regression_head_stage_needs_init_from():
    with pytest.raises(ValueError, match="--init_from"):
        PretrainMIConfig(trainable="regression_head")


def test_init_from_an_infonet_of_other_sizes_is_rejected(tmp_path):
    base = pretrain(tiny_config(tmp_path / "base", steps=1))
    cfg = tiny_config(tmp_path / "other", steps=1)
    cfg.init_from, cfg.model.dim = str(base), 8
    with pytest.raises(ValueError, match="other sizes"):
        pretrain(cfg)


def test_init_from_a_repo_id_goes_through_the_hub_client(tmp_path):
    """Offline here, so it stops at the network boundary."""
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError, OfflineModeIsEnabled

    cfg = tiny_config(tmp_path, steps=1)
    cfg.init_from = "lerobot-maxmi-tests/no-such-infonet"
    with pytest.raises((OfflineModeIsEnabled, LocalEntryNotFoundError, HfHubHTTPError)):
        pretrain(cfg)


def test_gaussian_share_draws_single_gaussians(tmp_path):
    """A single Gaussian's MI is the Gaussian-copula MI of its samples; a mixture's mostly is not."""

    def copula_error(share):
        cfg = replace(
            tiny_config(tmp_path, steps=1),
            batch_size=32,
            min_samples=2048,
            max_samples=2048,
            mc_samples=4096,
            max_components=10,
            gaussian_share=share,
        )
        batch = draw_batch(cfg, step=0)
        return (gaussian_copula_mi(batch["u"], batch["v"]) - batch["mi"]).abs().mean()

    assert copula_error(1.0) < 0.03 < 0.1 < copula_error(0.0)


def test_gaussian_share_must_be_a_fraction():
    with pytest.raises(ValueError, match="gaussian_share"):
        PretrainMIConfig(gaussian_share=1.5)
