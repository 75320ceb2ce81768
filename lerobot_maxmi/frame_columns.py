"""Per-frame columns added to a copy of a LeRobotDataset, streamed through the data files.

LeRobot's `dataset_tools.add_features` turns each data file into a pandas frame, then Python lists,
then an HF dataset before writing it: for 500 episodes of 150 frames that raised the process's peak
by about 1.5 GiB. Here every data file is read and written one record batch at a time with pyarrow, so memory
stays at one batch whatever the dataset's size (docs/RESULTS.md, "Annotation memory").
"""

import dataclasses
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.feature_utils import get_hf_features_from_features
from lerobot.datasets.io_utils import write_info
from lerobot.datasets.lerobot_dataset import LeRobotDataset

# Rows per record batch: a few MB of states, and far below a data file's 100 MB.
BATCH_ROWS = 4096
# A function of a record batch's rows (it can read any source column) -> (rows, dim) values.
FrameValues = Callable[[pa.RecordBatch], np.ndarray]


def add_frame_columns(
    source: LeRobotDataset,
    columns: Mapping[str, tuple[FrameValues, dict]],
    output_root: Path,
    repo_id: str,
) -> LeRobotDataset:
    """A copy of `source` at `output_root` with one new 1-D feature per entry of `columns`
    (`name: (values, feature_info)`); the source is only read. Videos and metadata are copied as
    they are, stats included: stats of the new columns are the caller's to write."""
    check_new_features(source.meta.features, columns)
    features = {**source.meta.features, **{name: info for name, (_, info) in columns.items()}}
    output_root = Path(output_root)
    copy_metadata_and_videos(Path(source.root), output_root, source.meta.video_path)
    write_info(dataclasses.replace(source.meta.info, features=features), output_root)
    schema = get_hf_features_from_features(features).arrow_schema
    for path in sorted((Path(source.root) / "data").glob("*/*.parquet")):
        target = output_root / path.relative_to(source.root)
        target.parent.mkdir(parents=True, exist_ok=True)
        write_with_columns(path, target, schema, columns)
    return LeRobotDataset(repo_id, root=output_root)


def check_new_features(existing: dict, columns: Mapping[str, tuple[FrameValues, dict]]) -> None:
    for name, (_, info) in columns.items():
        if name in existing:
            raise ValueError(f"the dataset already has a feature {name!r}")
        if len(info.get("shape", ())) != 1:
            raise ValueError(f"{name!r}: only 1-D features can be added, got shape {info.get('shape')}")


def copy_metadata_and_videos(source_root: Path, output_root: Path, video_path: str | None) -> None:
    """All of the dataset but its data files, which are rewritten instead."""
    shutil.copytree(source_root / "meta", output_root / "meta")
    videos = source_root / Path(video_path).parts[0] if video_path else None
    if videos is not None and videos.is_dir():
        shutil.copytree(videos, output_root / videos.name)


def write_with_columns(
    source: Path, target: Path, schema: pa.Schema, columns: Mapping[str, tuple[FrameValues, dict]]
) -> None:
    """Copy one data file batch by batch, appending the new columns; one row group per episode
    within a batch, as LeRobot's own writers lay data files out."""
    with pq.ParquetWriter(target, schema, compression="snappy", use_dictionary=True) as writer:
        for batch in pq.ParquetFile(source).iter_batches(batch_size=BATCH_ROWS):
            arrays = {name: batch.column(name) for name in batch.schema.names}
            arrays |= {name: to_arrow(values(batch)) for name, (values, _) in columns.items()}
            table = pa.table(arrays).select(schema.names).cast(schema)
            for episode in split_by_episode(table):
                writer.write_table(episode)


def to_arrow(values: np.ndarray) -> pa.Array:
    """(rows, dim) values as LeRobot stores a 1-D feature: a scalar when dim is 1, else a fixed-size list."""
    if values.ndim != 2:
        raise ValueError(f"frame values must be (rows, dim), got shape {values.shape}")
    if values.shape[1] == 1:
        return pa.array(values[:, 0])
    return pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), values.shape[1])


def vector_column(rows: pa.RecordBatch | pa.Table, name: str) -> np.ndarray:
    """A 1-D feature's values as a (rows, dim) float32 array."""
    column = rows[name]
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    return np.asarray(column.flatten(), dtype=np.float32).reshape(len(column), -1)


def episode_starts(episode_index: np.ndarray) -> np.ndarray:
    """The rows where a new episode begins, in rows grouped by episode."""
    return np.flatnonzero(np.diff(episode_index, prepend=-1))


def split_by_episode(table: pa.Table) -> list[pa.Table]:
    starts = episode_starts(table.column("episode_index").to_numpy())
    stops = np.append(starts[1:], table.num_rows)
    return [table.slice(start, stop - start) for start, stop in zip(starts, stops, strict=True)]
