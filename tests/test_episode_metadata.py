import pytest

from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column, write_episode_columns


def test_episode_columns_round_trip_through_lerobot(state_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    key_frames = [[3, 19], [5, 24], [7, 29]]
    write_episode_columns(state_dataset.root, {GT_KEY_FRAMES: key_frames})

    assert read_episode_column(state_dataset.root, GT_KEY_FRAMES) == dict(enumerate(key_frames))
    reopened = LeRobotDataset(state_dataset.repo_id, root=state_dataset.root)
    assert [list(v) for v in reopened.meta.episodes[GT_KEY_FRAMES]] == key_frames
    assert len(reopened) == 75  # frames are untouched


def test_missing_column_names_the_alternatives(state_dataset):
    with pytest.raises(KeyError, match="no per-episode column 'gt/key_frames'.*episode_index"):
        read_episode_column(state_dataset.root, GT_KEY_FRAMES)


def test_not_a_dataset(tmp_path):
    with pytest.raises(FileNotFoundError, match="LeRobotDataset v3"):
        write_episode_columns(tmp_path, {GT_KEY_FRAMES: []})
