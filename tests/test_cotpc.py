"""CoTPC policies: shapes, hybrid masking, inference history, save/load, and lerobot-train end to end."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_maxmi.pipeline import FILE_PER_EPISODE_MB
from lerobot_maxmi.policies.cotpc.configuration_cotpc import OBS_KEY_STATES, CotpcConfig, CotpcMaxmiConfig
from lerobot_maxmi.policies.cotpc.modeling_cotpc import CotpcMaxmiPolicy, CotpcPolicy

STATE_DIM, ACTION_DIM, NUM_KEY_STATES, CONTEXT, FPS = 5, 3, 2, 8, 10
TINY = {"dim_model": 32, "n_heads": 4, "n_layers": 2, "dim_encoder_hidden": 32, "dim_head_hidden": 32}
TINY_FLAGS = [f"--policy.{name}={value}" for name, value in {**TINY, "context_length": CONTEXT}.items()]


def tiny_config(num_key_states: int, config_class=CotpcConfig, **overrides) -> CotpcConfig:
    input_features = {OBS_STATE: PolicyFeature(FeatureType.STATE, (STATE_DIM,))}
    if num_key_states:
        input_features[OBS_KEY_STATES] = PolicyFeature(FeatureType.STATE, (num_key_states * STATE_DIM,))
    return config_class(
        device="cpu",
        fps=FPS,
        context_length=CONTEXT,
        input_features=input_features,
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
        **{**TINY, **overrides},
    )


def training_batch(num_key_states: int, padding=(0, 3, CONTEXT - 1), generator=None) -> dict:
    """Windows as LeRobot's loader yields them: left padding where the window starts before the episode."""
    batch_size = len(padding)
    is_pad = torch.arange(CONTEXT)[None] < torch.tensor(padding)[:, None]
    batch = {
        OBS_STATE: torch.randn(batch_size, CONTEXT, STATE_DIM, generator=generator),
        ACTION: torch.randn(batch_size, CONTEXT, ACTION_DIM, generator=generator),
        f"{OBS_STATE}_is_pad": is_pad,
        f"{ACTION}_is_pad": is_pad,
        # The window ends at episode step CONTEXT - 1 - padding (+ 20 when unpadded, to use the global table).
        "timestamp": torch.tensor([(CONTEXT - 1 - pad + (20 if pad == 0 else 0)) / FPS for pad in padding]),
    }
    if num_key_states:
        key_states = torch.randn(batch_size, 1, num_key_states * STATE_DIM, generator=generator)
        batch[OBS_KEY_STATES] = key_states.expand(-1, CONTEXT, -1)
    return batch


def run_model(policy: CotpcPolicy, batch: dict, horizon: torch.Tensor):
    start_step = policy._window_start_step(batch["timestamp"])
    states, actions = batch[OBS_STATE], batch[ACTION][:, :-1]
    return policy.model(states, actions, batch[f"{OBS_STATE}_is_pad"], start_step, horizon)


@pytest.mark.parametrize("num_key_states", [0, NUM_KEY_STATES])
def test_forward_backward_shapes(num_key_states, generator):
    policy = CotpcPolicy(tiny_config(num_key_states))
    batch = training_batch(num_key_states, generator=generator)
    loss, loss_dict = policy.forward(batch)
    loss.backward()
    assert torch.isfinite(loss)
    assert set(loss_dict) == ({"action_loss", "key_state_loss"} if num_key_states else {"action_loss"})
    assert all(p.grad is not None for p in policy.parameters() if p.requires_grad)

    actions, key_states = run_model(policy, batch, horizon=torch.full((3,), CONTEXT - 1))
    assert actions.shape == (3, CONTEXT, ACTION_DIM)
    assert key_states is None if not num_key_states else key_states.shape == (3, num_key_states, STATE_DIM)


def perturbed(batch: dict, from_step: int, also_action_at_step: bool) -> dict:
    """A copy of `batch` whose states after `from_step` and actions from it (or after it) are replaced."""
    changed = {key: value.clone() for key, value in batch.items()}
    changed[OBS_STATE][:, from_step + 1 :] += 10.0
    changed[ACTION][:, from_step if also_action_at_step else from_step + 1 :] += 10.0
    return changed


def test_key_state_tokens_never_see_beyond_their_horizon(generator):
    policy = CotpcPolicy(tiny_config(NUM_KEY_STATES)).eval()
    batch = training_batch(NUM_KEY_STATES, padding=(0, 0, 2), generator=generator)
    horizon = torch.tensor([2, 4, 4])
    _, key_states = run_model(policy, batch, horizon)
    _, key_states_after_future_change = run_model(
        policy, perturbed(batch, 4, also_action_at_step=True), horizon
    )
    _, key_states_after_past_change = run_model(
        policy, perturbed(batch, 1, also_action_at_step=True), horizon
    )
    # Sample 0 sees up to step 2, the others up to step 4: a change from step 5 on is invisible to all.
    torch.testing.assert_close(key_states_after_future_change, key_states)
    assert not torch.allclose(key_states_after_past_change, key_states)


@pytest.mark.parametrize("num_key_states", [0, NUM_KEY_STATES])
def test_actions_never_see_future_steps(num_key_states, generator):
    policy = CotpcPolicy(tiny_config(num_key_states)).eval()
    batch = training_batch(num_key_states, padding=(0, 0, 2), generator=generator)
    horizon = torch.tensor([1, 4, CONTEXT - 1])  # as sampled in training: any real step
    actions, _ = run_model(policy, batch, horizon)
    for step in range(CONTEXT - 1):
        # The action at `step` is predicted from state `step`, so the action taken then is future too.
        changed, _ = run_model(policy, perturbed(batch, step, also_action_at_step=True), horizon)
        torch.testing.assert_close(changed[:, : step + 1], actions[:, : step + 1])
        assert not torch.allclose(changed[:, step + 1 :], actions[:, step + 1 :])


def test_padded_steps_are_ignored(generator):
    policy = CotpcPolicy(tiny_config(NUM_KEY_STATES)).eval()
    batch = training_batch(NUM_KEY_STATES, padding=(3, 3, 3), generator=generator)
    actions, key_states = run_model(policy, batch, torch.full((3,), CONTEXT - 1))
    changed = {key: value.clone() for key, value in batch.items()}
    changed[OBS_STATE][:, :3] = 99.0
    changed[ACTION][:, :3] = 99.0
    changed_actions, changed_key_states = run_model(policy, changed, torch.full((3,), CONTEXT - 1))
    torch.testing.assert_close(changed_actions[:, 3:], actions[:, 3:])
    torch.testing.assert_close(changed_key_states, key_states)


def test_select_action_replays_the_training_window(generator):
    """select_action on observation.state alone gives what the model predicts for the loader's window."""
    policy = CotpcPolicy(tiny_config(NUM_KEY_STATES))
    episode = torch.randn(CONTEXT + 4, 2, STATE_DIM, generator=generator)  # 2 parallel rollouts
    policy.reset()
    actions = torch.stack([policy.select_action({OBS_STATE: state}) for state in episode])
    assert actions.shape == (CONTEXT + 4, 2, ACTION_DIM)

    for step in (0, 3, CONTEXT + 3):
        window = torch.arange(step - CONTEXT + 1, step + 1)
        is_pad = (window < 0).expand(2, -1)
        batch = {  # the loader repeats the first frame before the episode start
            OBS_STATE: episode[window.clamp_min(0)].transpose(0, 1),
            ACTION: actions[window.clamp_min(0)].transpose(0, 1),
            f"{OBS_STATE}_is_pad": is_pad,
            "timestamp": torch.full((2,), step / FPS),
        }
        predicted, _ = run_model(policy, batch, torch.full((2,), CONTEXT - 1))
        torch.testing.assert_close(predicted[:, -1], actions[step])

    policy.reset()
    torch.testing.assert_close(policy.select_action({OBS_STATE: episode[0]}), actions[0])


@pytest.mark.parametrize("policy_class", [CotpcPolicy, CotpcMaxmiPolicy])
def test_save_load_roundtrip(policy_class, tmp_path, generator):
    policy = policy_class(tiny_config(NUM_KEY_STATES, config_class=policy_class.config_class))
    policy.save_pretrained(tmp_path)
    loaded = policy_class.from_pretrained(tmp_path, strict=True)
    assert loaded.config == policy.config
    for name, tensor in policy.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[name], tensor)
    states = torch.randn(3, 1, STATE_DIM, generator=generator)
    policy.reset()
    expected = [policy.select_action({OBS_STATE: state}) for state in states]
    assert all(
        torch.equal(loaded.select_action({OBS_STATE: s}), e) for s, e in zip(states, expected, strict=True)
    )


# ---- LeRobot datasets and lerobot-train ------------------------------------------------------------


def make_dataset(root: Path, with_key_states: bool, file_size_mb: float | None = None) -> LeRobotDataset:
    """3 short state-only episodes; optionally the annotator's per-frame key-state column."""
    features = {
        OBS_STATE: {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
        ACTION: {"dtype": "float32", "shape": (ACTION_DIM,), "names": None},
    }
    if with_key_states:
        features[OBS_KEY_STATES] = {"dtype": "float32", "shape": (NUM_KEY_STATES * STATE_DIM,), "names": None}
    dataset = LeRobotDataset.create(
        repo_id="local/cotpc_test",
        fps=FPS,
        features=features,
        root=root,
        use_videos=False,
        data_files_size_in_mb=file_size_mb,
    )
    rng = np.random.default_rng(0)
    for length in (12, 15, 6):
        states = np.cumsum(rng.normal(size=(length, STATE_DIM)), axis=0).astype(np.float32)
        key_states = states[[length // 2, -1]].reshape(-1)
        for state in states:
            frame = {OBS_STATE: state, ACTION: rng.normal(size=ACTION_DIM).astype(np.float32), "task": "t"}
            if with_key_states:
                frame[OBS_KEY_STATES] = key_states
            dataset.add_frame(frame)
        dataset.save_episode()
    dataset.finalize()
    return dataset


def lerobot_train(*args: str) -> subprocess.CompletedProcess:
    command = [str(Path(sys.executable).parent / "lerobot-train"), *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=600)


def test_missing_key_state_column_names_the_annotator(tmp_path):
    dataset = make_dataset(tmp_path / "plain", with_key_states=False)
    with pytest.raises(ValueError, match="lerobot-maxmi-discover"):
        make_policy(CotpcMaxmiConfig(device="cpu"), ds_meta=dataset.meta)


def test_dataset_dims_are_checked_when_resuming(tmp_path):
    dataset = make_dataset(tmp_path / "annotated", with_key_states=True)
    config = tiny_config(NUM_KEY_STATES)
    config.output_features = {ACTION: PolicyFeature(FeatureType.ACTION, (ACTION_DIM + 1,))}
    with pytest.raises(ValueError, match="shape"):
        CotpcPolicy(config, dataset_meta=dataset.meta)


@pytest.mark.slow
def test_lerobot_train_checkpoints_resumes_and_serves_state_only(tmp_path):
    root, output = tmp_path / "annotated", tmp_path / "run"
    make_dataset(root, with_key_states=True)
    common = ["--batch_size=4", "--num_workers=0", "--log_freq=1", "--save_freq=2"]
    result = lerobot_train(
        "--policy.type=cotpc_maxmi", "--policy.device=cpu", "--policy.push_to_hub=false", *TINY_FLAGS,
        "--dataset.repo_id=local/cotpc_test", f"--dataset.root={root}", f"--output_dir={output}",
        "--steps=2", *common,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert "key_state_loss:" in result.stdout + result.stderr  # the training log line

    train_config = output / "checkpoints/last/pretrained_model/train_config.json"
    result = lerobot_train("--resume=true", f"--config_path={train_config}", "--steps=4", *common)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Resuming" in result.stdout + result.stderr
    checkpoint = output / "checkpoints/000004/pretrained_model"
    assert checkpoint.is_dir()

    # A checkpoint alone (as on the hub) serves actions from observation.state.
    policy = CotpcMaxmiPolicy.from_pretrained(checkpoint, strict=True)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    policy.reset()
    for _ in range(3):
        observation = preprocessor({OBS_STATE: torch.randn(2, STATE_DIM)})
        action = postprocessor(policy.select_action(observation))
    assert action.shape == (2, ACTION_DIM)


@pytest.mark.slow
def test_lerobot_train_without_key_states_is_the_baseline_and_streams(tmp_path):
    """Streamed by two loader workers from a file per episode, as the gpu table profile trains."""
    root = tmp_path / "plain"
    make_dataset(root, with_key_states=False, file_size_mb=FILE_PER_EPISODE_MB)
    assert len(list(root.glob("data/*/*.parquet"))) == 3
    result = lerobot_train(
        "--policy.type=cotpc", "--policy.device=cpu", "--policy.push_to_hub=false", *TINY_FLAGS,
        "--dataset.repo_id=local/cotpc_test", f"--dataset.root={root}", f"--output_dir={tmp_path / 'run'}",
        "--dataset.streaming=true", "--num_workers=2",
        "--steps=2", "--batch_size=4", "--log_freq=1", "--save_checkpoint=false",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert "action_loss:" in result.stdout + result.stderr
    assert "key_state_loss:" not in result.stdout + result.stderr


def serve_from(directory: Path, monkeypatch) -> list[str]:
    """Answer LeRobot's hub downloads (policy config, weights, processors) from `directory`: the network
    boundary. Returns the repo ids asked for."""
    import lerobot.configs.policies
    import lerobot.policies.pretrained
    import lerobot.processor.pipeline

    asked = []

    def hf_hub_download(repo_id, filename, **kwargs):
        asked.append(repo_id)
        return str(directory / filename)

    for module in (lerobot.configs.policies, lerobot.policies.pretrained, lerobot.processor.pipeline):
        monkeypatch.setattr(module, "hf_hub_download", hf_hub_download)
    return asked


def test_checkpoint_loads_by_hub_repo_id(tmp_path, monkeypatch, generator):
    """What lerobot-eval --policy.path=<repo id> does: config, weights and processors from the hub."""
    from lerobot.configs.policies import PreTrainedConfig

    config = tiny_config(NUM_KEY_STATES, config_class=CotpcMaxmiConfig)
    stats = {OBS_STATE: {"mean": torch.ones(STATE_DIM), "std": 2 * torch.ones(STATE_DIM)}}
    policy = CotpcMaxmiPolicy(config)
    policy.save_pretrained(tmp_path)
    for pipeline in make_pre_post_processors(config, dataset_stats=stats):
        pipeline.save_pretrained(tmp_path)
    asked = serve_from(tmp_path, monkeypatch)

    repo_id = "someone/cotpc_maxmi_pickcube"
    loaded_config = PreTrainedConfig.from_pretrained(repo_id)
    assert loaded_config == config
    loaded = CotpcMaxmiPolicy.from_pretrained(repo_id, strict=True)
    preprocessor, postprocessor = make_pre_post_processors(loaded_config, pretrained_path=repo_id)
    assert set(asked) == {repo_id}
    state = torch.randn(1, STATE_DIM, generator=generator)
    torch.testing.assert_close(preprocessor({OBS_STATE: state})[OBS_STATE], (state - 1) / 2)
    expected = policy.select_action({OBS_STATE: state})
    assert torch.equal(loaded.select_action({OBS_STATE: state}), expected)
    assert postprocessor(expected).shape == (1, ACTION_DIM)
