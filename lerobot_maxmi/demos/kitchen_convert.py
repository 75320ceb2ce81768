"""Franka Kitchen demonstrations in their published formats -> `Episode`s for lerobot-maxmi-convert.

* `relay_kitchen` (BeT's relay-kitchen): a directory with `observations_seq.npy` (T, N, 60),
  `actions_seq.npy` (T, N, 9) and `existence_mask.npy` (T, N), time-major and zero-padded; episode n
  is the first `mask[:, n].sum()` steps.
* `d4rl_kitchen` (D4RL HDF5): `observations` (steps, 60), `actions` (steps, 9), and `terminals` /
  `timeouts` flags that end episodes (a file without either is one episode).

Observations are 60-d ([robot qpos 9, object qpos 21, 30 goal dims]) or the env's 59-d full
observation; frames keep the 30-d classic state, the env's default `state_layout`. Key frames come
from the stored object states with the benchmark's completion test: the first frame at which each
subtask is complete (not at the first frame), in completion order, then the final frame.
"""

import logging
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from lerobot_maxmi.demos.episode import FINAL, Episode
from lerobot_maxmi.envs.kitchen import ALL_TASKS, STATE_LAYOUTS, task_completed

logger = logging.getLogger(__name__)

RELAY_FILES = ("observations_seq.npy", "actions_seq.npy", "existence_mask.npy")
CLASSIC_DIM = 30
FULL_DIM = len(STATE_LAYOUTS["full"])


def classic_states(observations: np.ndarray) -> np.ndarray:
    """(T, 30) classic states from 60-d (classic + goal), 30-d or 59-d (full) observations."""
    dim = observations.shape[-1]
    if dim == FULL_DIM:
        return observations[:, STATE_LAYOUTS["classic"]].astype(np.float32)
    if dim >= CLASSIC_DIM:
        return observations[:, :CLASSIC_DIM].astype(np.float32)
    raise ValueError(
        f"Kitchen observations must have 30, 59 or 60 dims (robot qpos 9 + object qpos 21 first), got {dim}."
    )


def kitchen_episode(observations: np.ndarray, actions: np.ndarray, seed: int | None = None) -> Episode:
    states = classic_states(observations)
    done = np.stack([task_completed(states, task) for task in ALL_TASKS], axis=1)  # (T, 7)
    first = {}
    for column, task in enumerate(ALL_TASKS):
        frames = np.flatnonzero(done[:, column])
        if len(frames) and frames[0] > 0:  # complete from the start: nothing was demonstrated
            first[task] = int(frames[0])
    order = sorted(first, key=first.get)
    length = len(states)
    last_completion = first[order[-1]] if order else length
    return Episode(
        states=states,
        actions=np.asarray(actions, dtype=np.float32),
        successes=np.arange(length) + 1 >= last_completion,  # every demonstrated subtask done after it
        key_frames=[first[task] for task in order] + [length - 1],
        key_frame_names=[*order, FINAL],
        seed=seed,
    )


def relay_kitchen_episodes(directory: Path) -> Iterator[Episode]:
    missing = [name for name in RELAY_FILES if not (directory / name).exists()]
    if missing:
        raise FileNotFoundError(
            f"--format=relay_kitchen reads a directory holding {list(RELAY_FILES)}; "
            f"{directory} lacks {missing}."
        )
    observations, actions, mask = (np.load(directory / name) for name in RELAY_FILES)
    if not (observations.shape[:2] == actions.shape[:2] == mask.shape):
        raise ValueError(
            f"relay_kitchen arrays disagree: observations {observations.shape}, actions {actions.shape}, "
            f"existence_mask {mask.shape}; expected (T, N, 60), (T, N, 9) and (T, N)."
        )
    lengths = mask.sum(axis=0).astype(int)
    is_prefix = np.array_equal(mask.astype(bool), np.arange(len(mask))[:, None] < lengths)
    # Episode-major arrays often pass the prefix test but then read as many 0- or 1-frame episodes.
    if not is_prefix or lengths.min() < 2:
        raise ValueError(
            "existence_mask must be a prefix of at least 2 ones per episode along axis 0: "
            "relay_kitchen arrays are time-major (T, N, ...); "
            "transpose episode-major (N, T, ...) arrays before converting."
        )
    for episode, length in enumerate(lengths):
        yield kitchen_episode(observations[:length, episode], actions[:length, episode])


def d4rl_kitchen_episodes(path: Path) -> Iterator[Episode]:
    with h5py.File(path, "r") as file:
        missing = [key for key in ("observations", "actions") if key not in file]
        if missing:
            raise KeyError(f"{path} is not a D4RL kitchen file: it has no {missing} (keys: {sorted(file)}).")
        observations, actions = np.asarray(file["observations"]), np.asarray(file["actions"])
        ends = np.zeros(len(actions), dtype=bool)
        for key in ("terminals", "timeouts"):
            if key in file:
                ends |= np.asarray(file[key], dtype=bool).reshape(-1)
    ends[-1] = True
    start = 0
    for end in np.flatnonzero(ends) + 1:
        yield kitchen_episode(observations[start:end], actions[start:end])
        start = end
