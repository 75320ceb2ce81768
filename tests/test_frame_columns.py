import hashlib

import numpy as np
import pyarrow.parquet as pq
import pytest

from lerobot_maxmi import frame_columns
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column, write_episode_columns
from lerobot_maxmi.frame_columns import add_frame_columns, vector_column

DOUBLED = {"dtype": "float32", "shape": (6,), "names": None}


def doubled_state(rows) -> np.ndarray:
    return 2 * vector_column(rows, "observation.state")


def file_digests(root) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*.*")}


def test_column_is_added_to_a_copy_batch_by_batch(state_dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(frame_columns, "BATCH_ROWS", 7)  # episodes of 20-30 frames span several batches
    write_episode_columns(state_dataset.root, {GT_KEY_FRAMES: [[3], [5], [7]]})
    before = file_digests(state_dataset.root)

    copy = add_frame_columns(
        state_dataset, {"doubled": (doubled_state, DOUBLED)}, tmp_path / "copy", "local/copy"
    )

    assert file_digests(state_dataset.root) == before
    assert len(copy) == len(state_dataset) == 75
    for index in (0, 19, 20, 44, 74):
        frame, original = copy[index], state_dataset[index]
        np.testing.assert_array_equal(frame["doubled"], 2 * original["observation.state"])
        np.testing.assert_array_equal(frame["action"], original["action"])
        assert frame["episode_index"] == original["episode_index"]
    assert copy.meta.features["doubled"]["shape"] == (6,)
    assert read_episode_column(copy.root, GT_KEY_FRAMES) == {0: [3], 1: [5], 2: [7]}
    data_file = pq.ParquetFile(next((copy.root / "data").glob("*/*.parquet")))
    groups = [data_file.read_row_group(i, columns=["episode_index"]) for i in range(data_file.num_row_groups)]
    assert all(len(set(g["episode_index"].to_pylist())) == 1 for g in groups)


def test_one_dimensional_values_are_stored_as_scalars(state_dataset, tmp_path):
    first = {"dtype": "float32", "shape": (1,), "names": None}
    column = (lambda rows: vector_column(rows, "observation.state")[:, :1], first)

    copy = add_frame_columns(state_dataset, {"first": column}, tmp_path / "copy", "local/copy")

    assert copy[30]["first"].item() == state_dataset[30]["observation.state"][0].item()


def test_videos_are_copied(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (6,), "names": None},
        "observation.images.top": {
            "dtype": "video",
            "shape": (64, 64, 3),
            "names": ["height", "width", "channels"],
        },
    }
    source = LeRobotDataset.create("local/video", fps=10, features=features, root=tmp_path / "video")
    rng = np.random.default_rng(0)
    for _ in range(6):
        image = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
        source.add_frame(
            {"observation.state": np.ones(6, np.float32), "observation.images.top": image, "task": "t"}
        )
    source.save_episode()
    source.finalize()

    copy = add_frame_columns(source, {"doubled": (doubled_state, DOUBLED)}, tmp_path / "copy", "local/copy")

    assert copy[5]["observation.images.top"].shape == (3, 64, 64)
    np.testing.assert_array_equal(copy[5]["doubled"], np.full(6, 2.0))


@pytest.mark.parametrize(
    ("name", "info", "match"),
    [
        ("observation.state", DOUBLED, "already has a feature 'observation.state'"),
        ("image_like", {"dtype": "float32", "shape": (2, 3), "names": None}, "only 1-D features"),
    ],
)
def test_bad_columns_are_refused_before_anything_is_written(state_dataset, tmp_path, name, info, match):
    with pytest.raises(ValueError, match=match):
        add_frame_columns(state_dataset, {name: (doubled_state, info)}, tmp_path / "copy", "local/copy")
    assert not (tmp_path / "copy").exists()
