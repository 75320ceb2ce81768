"""Per-episode metadata columns in a LeRobotDataset v3 (`meta/episodes/*/*.parquet`).

Key frames are facts about an episode, not about a frame, so they live beside the episode's
length and task: ground truth from the demo generator under `gt/…`, discovered ones under
`maxmi/…`. LeRobot reads extra columns back through `dataset.meta.episodes[name]`.
"""

from collections.abc import Mapping, Sequence
from pathlib import Path

import pandas as pd

EPISODES_GLOB = "meta/episodes/chunk-*/file-*.parquet"

GT_KEY_FRAMES = "gt/key_frames"  # list[int]: first frame each sub-goal holds, then the final frame
GT_KEY_FRAME_NAMES = "gt/key_frame_names"  # list[str], same length ("grasp", ..., "final")
EPISODE_SEED = "episode_seed"  # int: the env seed that reproduces the episode


def write_episode_columns(root: str | Path, columns: Mapping[str, Sequence]) -> None:
    """Add or replace per-episode columns; `columns[name][i]` belongs to episode index i.

    Rewrites every episodes file of the dataset at `root` in place: call it on a dataset you are
    creating, never on a user's source dataset.
    """
    files = sorted(Path(root).glob(EPISODES_GLOB))
    if not files:
        raise FileNotFoundError(f"No episode metadata under {root}/meta/episodes: is it a LeRobotDataset v3?")
    for path in files:
        table = pd.read_parquet(path)
        for name, values in columns.items():
            table[name] = [values[int(index)] for index in table["episode_index"]]
        table.to_parquet(path, index=False)


def read_episode_column(root: str | Path, name: str) -> dict[int, object]:
    """`{episode_index: value}` for one per-episode column; a clear error if it is absent."""
    tables = [pd.read_parquet(path) for path in sorted(Path(root).glob(EPISODES_GLOB))]
    table = pd.concat(tables, ignore_index=True)
    if name not in table.columns:
        raise KeyError(
            f"Dataset at {root} has no per-episode column {name!r}; it has: {sorted(table.columns)}."
        )
    return {
        int(index): _plain(value) for index, value in zip(table["episode_index"], table[name], strict=True)
    }


def _plain(value):
    """Parquet lists come back as numpy arrays; hand out Python lists."""
    return value.tolist() if hasattr(value, "tolist") else value
