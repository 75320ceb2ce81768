"""The data-path benchmark (benchmarks/cotpc_data_speed.py) compares like with like."""

import itertools

import torch
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.streaming_dataset import StreamingLeRobotDataset

from lerobot_maxmi.policies.cotpc.configuration_cotpc import OBS_KEY_STATES, CotpcConfig
from tests.conftest import load_benchmark

cotpc_data_speed = load_benchmark("cotpc_data_speed")


def test_both_loaders_give_cotpc_the_same_windows(tmp_path):
    """Streaming and map-style reads of one frame agree on every window and padding mask, so their
    costs per sample measure the same work."""
    root = tmp_path / "dataset"
    cotpc_data_speed.write_dataset(root, episodes=3, length=12, state_dim=4, key_states=2)
    config = CotpcConfig(context_length=5)
    map_style = LeRobotDataset(cotpc_data_speed.REPO_ID, root=root)
    delta_timestamps = resolve_delta_timestamps(config, map_style.meta)
    assert set(delta_timestamps) == {"observation.state", "action", OBS_KEY_STATES}
    map_style = LeRobotDataset(cotpc_data_speed.REPO_ID, root=root, delta_timestamps=delta_timestamps)
    streaming = StreamingLeRobotDataset(
        cotpc_data_speed.REPO_ID, root=root, delta_timestamps=delta_timestamps, max_num_shards=1
    )
    streamed = list(itertools.islice(streaming, 36))
    assert sorted(int(item["index"]) for item in streamed) == list(range(36))
    for item in streamed:
        expected = map_style[int(item["index"])]
        for key in delta_timestamps:
            assert item[key].shape == (5, *map_style.meta.features[key]["shape"])
            assert torch.equal(item[key], expected[key]), key
            assert torch.equal(item[f"{key}_is_pad"], expected[f"{key}_is_pad"]), key


def test_the_synthetic_key_states_are_the_episodes_states_at_evenly_spaced_frames(tmp_path):
    root = tmp_path / "dataset"
    cotpc_data_speed.write_dataset(root, episodes=2, length=7, state_dim=3, key_states=3)
    dataset = LeRobotDataset(cotpc_data_speed.REPO_ID, root=root)
    for episode in range(2):
        frames = [dataset[i] for i in range(7 * episode, 7 * episode + 7)]
        states = torch.stack([frame["observation.state"] for frame in frames])
        expected = states[[0, 3, 6]].reshape(-1)
        assert all(torch.equal(frame[OBS_KEY_STATES], expected) for frame in frames)
