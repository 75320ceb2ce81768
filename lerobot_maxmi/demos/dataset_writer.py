"""Writing demonstration episodes into a state-only LeRobotDataset v3, staged beside the final path.

Episodes are written to `<root>.incomplete` and renamed to `root` only once the dataset is finalized,
so `root` never holds a half-written dataset. Resuming copies the existing dataset into the staging
directory and appends there. Per-episode ground truth goes into `meta/episodes` columns
(`episode_metadata`): `episode_seed`, `gt/key_frames`, `gt/key_frame_names`.
"""

import logging
import shutil
from pathlib import Path

import datasets
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import ACTION, HF_LEROBOT_HOME, OBS_ENV_STATE, OBS_STATE

from lerobot_maxmi.demos.episode import Episode
from lerobot_maxmi.episode_metadata import (
    EPISODE_SEED,
    GT_KEY_FRAME_NAMES,
    GT_KEY_FRAMES,
    read_episode_column,
    write_episode_columns,
)
from lerobot_maxmi.frame_columns import add_frame_columns, vector_column

logger = logging.getLogger(__name__)

SUCCESS = "next.success"
STAGING_SUFFIX = ".incomplete"
UNKNOWN_SEED = -1  # converted episodes whose source did not record a seed


def default_root(repo_id: str) -> Path:
    return HF_LEROBOT_HOME / repo_id


def demo_features(state_dim: int, action_dim: int) -> dict:
    return {
        OBS_STATE: {"dtype": "float32", "shape": (state_dim,), "names": None},
        ACTION: {"dtype": "float32", "shape": (action_dim,), "names": None},
        SUCCESS: {"dtype": "bool", "shape": (1,), "names": None},
    }


class DemoDatasetWriter:
    """Appends `Episode`s to a staged dataset; `publish()` finalizes it and moves it to `root`.

    The dataset is created on the first episode (its arrays give the feature shapes).
    """

    def __init__(
        self,
        repo_id: str,
        root: Path,
        fps: int,
        task: str,
        robot_type: str | None = None,
        data_files_size_in_mb: float | None = None,
    ):
        self.repo_id, self.root, self.fps, self.task, self.robot_type = repo_id, root, fps, task, robot_type
        self.data_files_size_in_mb = data_files_size_in_mb  # None: LeRobot's default
        self.staging = root.with_name(root.name + STAGING_SUFFIX)
        self.dataset: LeRobotDataset | None = None
        self.columns: dict[str, list] = {EPISODE_SEED: [], GT_KEY_FRAMES: [], GT_KEY_FRAME_NAMES: []}
        datasets.disable_progress_bars()  # one "Map" bar per saved episode would bury the demo bar

    @classmethod
    def open(
        cls,
        repo_id: str,
        root: Path,
        fps: int,
        task: str,
        robot_type: str | None = None,
        *,
        overwrite: bool = False,
        resume: bool = False,
        data_files_size_in_mb: float | None = None,
    ) -> "DemoDatasetWriter":
        """A writer for a new dataset at `root`, or for appending to the one there when `resume`;
        `data_files_size_in_mb` applies to the files written from then on (None: LeRobot's default, or
        the resumed dataset's)."""
        if data_files_size_in_mb is not None and data_files_size_in_mb <= 0:
            raise ValueError(
                f"--data_files_size_in_mb must be positive, got {data_files_size_in_mb} "
                "(0.001 writes one file per episode; leave it out for LeRobot's 100 MB)."
            )
        if root.exists() and not (overwrite or resume):
            raise FileExistsError(
                f"A dataset already exists at {root}. Pass --resume=true to add episodes to it, "
                "--overwrite=true to replace it, or choose another --root/--repo_id."
            )
        writer = cls(repo_id, root, fps, task, robot_type, data_files_size_in_mb)
        if writer.staging.exists():
            logger.warning("Removing %s left behind by an interrupted run.", writer.staging)
            shutil.rmtree(writer.staging)
        root.parent.mkdir(parents=True, exist_ok=True)
        if resume and root.exists():
            writer._resume_from(root)
        return writer

    def _resume_from(self, root: Path) -> None:
        for name in self.columns:
            values = read_episode_column(root, name)
            self.columns[name] = [values[index] for index in sorted(values)]
        shutil.copytree(root, self.staging)
        self.dataset = LeRobotDataset.resume(self.repo_id, root=self.staging)
        if self.data_files_size_in_mb is not None:  # for the files written from now on
            self.dataset.meta.update_chunk_settings(data_files_size_in_mb=self.data_files_size_in_mb)
        recorded_tasks = set(self.dataset.meta.tasks.index)
        if recorded_tasks != {self.task}:
            raise ValueError(
                f"Cannot resume {root}: it holds demos of {sorted(recorded_tasks)}, not {self.task!r}."
            )

    @property
    def num_episodes(self) -> int:
        return len(self.columns[EPISODE_SEED])

    @property
    def seeds(self) -> list[int]:
        return list(self.columns[EPISODE_SEED])

    def add(self, episode: Episode) -> None:
        if self.dataset is None:
            self.dataset = LeRobotDataset.create(
                self.repo_id,
                fps=self.fps,
                features=demo_features(episode.states.shape[1], episode.actions.shape[1]),
                root=self.staging,
                robot_type=self.robot_type,
                use_videos=False,
                data_files_size_in_mb=self.data_files_size_in_mb,
            )
        for state, action, success in zip(episode.states, episode.actions, episode.successes, strict=True):
            self.dataset.add_frame(
                {OBS_STATE: state, ACTION: action, SUCCESS: np.array([success]), "task": self.task}
            )
        self.dataset.save_episode()
        self.columns[EPISODE_SEED].append(UNKNOWN_SEED if episode.seed is None else int(episode.seed))
        self.columns[GT_KEY_FRAMES].append([int(frame) for frame in episode.key_frames])
        self.columns[GT_KEY_FRAME_NAMES].append(list(episode.key_frame_names))

    def publish(self) -> Path:
        """Finalize the staged dataset, add the per-episode columns, and move it to `root`."""
        if self.dataset is None:
            raise RuntimeError(f"No episodes were written, so there is no dataset to save at {self.root}.")
        self.dataset.finalize()
        write_episode_columns(self.staging, self.columns)
        if self.root.exists():
            replaced = self.root.with_name(self.root.name + ".replaced")
            self.root.rename(replaced)
            self.staging.rename(self.root)
            shutil.rmtree(replaced)
        else:
            self.staging.rename(self.root)
        return self.root

    def discard(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)


def push_to_hub(repo_id: str, root: Path) -> None:
    """Push a finished local dataset; a failure (e.g. offline) says the local copy is complete."""
    try:
        LeRobotDataset(repo_id, root=root).push_to_hub()
    except Exception as error:  # any hub/network failure: the message matters, not the type
        raise RuntimeError(
            f"The dataset is complete at {root}, but pushing it to the Hub as {repo_id!r} failed: {error!r}. "
            f"Push it later with `LeRobotDataset({repo_id!r}, root={str(root)!r}).push_to_hub()` once "
            "online and logged in (`hf auth login`)."
        ) from error


def copy_with_environment_state(source_root: Path, output_root: Path, repo_id: str) -> LeRobotDataset:
    """A copy of the demos at `source_root` whose state is also stored as `observation.environment_state`:
    LeRobot's ACT and Diffusion need that input when there are no images (our env types observe it too).
    The source is only read."""
    source = LeRobotDataset(repo_id, root=source_root)
    copy_state = (lambda rows: vector_column(rows, OBS_STATE), source.meta.features[OBS_STATE])
    return add_frame_columns(source, {OBS_ENV_STATE: copy_state}, output_root, repo_id)
