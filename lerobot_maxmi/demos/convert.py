"""`lerobot-maxmi-convert`: existing demonstrations -> LeRobotDataset with ground-truth key frames.

    lerobot-maxmi-convert --format=maniskill_h5 --path=trajectory.state.pd_joint_delta_pos.h5 \\
        --repo_id=local/cotpc_stackcube [--root=...] [--task=StackCube-v1] [--overwrite=true]

Franka Kitchen formats (`relay_kitchen`, `d4rl_kitchen`) are described in `kitchen_convert.py`.

`maniskill_h5` reads ManiSkill2 / CoTPC `trajectory.*.h5` + `.json` files (the paper's data) and
ManiSkill 3 recordings: `traj_<i>/obs (T+1, D)`, `traj_<i>/actions (T, A)`, success flags and
optional per-step boolean flags (CoTPC stored `infos/is_grasped`, `infos/is_cubeA_on_cubeB`, ...).
Frames are obs[:T] with their actions; stored sub-goal flags become `gt/key_frames` with the same
conventions as recorded demos (`episode.py`); a flag that never fires points at the final frame, as
in CoTPC. Episodes that never succeed are skipped. Task names are mapped to ManiSkill 3 (-v0 -> -v1).
"""

import json
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from lerobot.configs import parser
from lerobot.utils.utils import init_logging

from lerobot_maxmi.demos.dataset_writer import UNKNOWN_SEED, DemoDatasetWriter, default_root, push_to_hub
from lerobot_maxmi.demos.episode import FINAL, Episode
from lerobot_maxmi.demos.kitchen_convert import d4rl_kitchen_episodes, relay_kitchen_episodes
from lerobot_maxmi.demos.kitchen_demos import demo_task
from lerobot_maxmi.envs.kitchen import FPS as KITCHEN_FPS

logger = logging.getLogger(__name__)


@dataclass
class ConvertConfig:
    # maniskill_h5: trajectory.h5 (with its .json); relay_kitchen: a directory; d4rl_kitchen: .hdf5
    path: Path
    repo_id: str
    format: str = "maniskill_h5"
    root: Path | None = None  # default: $HF_LEROBOT_HOME/<repo_id>
    task: str | None = None  # default: read from the source (maniskill_h5: json env_info.env_id)
    fps: int | None = None  # default: the source's control rate (ManiSkill 20, Franka Kitchen 12)
    data_files_size_in_mb: float | None = None  # as lerobot-maxmi-demos': 0.001 gives a file per episode
    overwrite: bool = False
    push_to_hub: bool = False

    def __post_init__(self):
        self.path = Path(self.path)
        self.root = Path(self.root) if self.root else default_root(self.repo_id)


@dataclass
class SourceDemos:
    task: str
    robot_type: str | None
    episodes: Iterator[Episode]
    fps: int = 20  # ManiSkill's control frequency


# ManiSkill2 (-v0) names of the tasks the paper uses, as ManiSkill 3 registers them.
V1_TASK_NAMES = {
    "PickCube-v0": "PickCube-v1",
    "StackCube-v0": "StackCube-v1",
    "PegInsertionSide-v0": "PegInsertionSide-v1",
    "TurnFaucet-v0": "TurnFaucet-v1",
}

# Stored per-step flags that mark each task's sub-goals, in the order they happen. Alternatives
# cover ManiSkill2's spelling (`is_cubaA_grasped`) and ManiSkill 3's.
SUBGOAL_FLAGS: dict[str, dict[str, tuple[str, ...]]] = {
    "PickCube-v1": {"grasp": ("is_grasped",)},
    "StackCube-v1": {"grasp": ("is_cubeA_grasped", "is_cubaA_grasped"), "a_on_b": ("is_cubeA_on_cubeB",)},
    "PegInsertionSide-v1": {"grasp": ("is_grasped",), "align": ("pre_inserted",)},
    "TurnFaucet-v1": {"contact": ("is_contacted",)},
}


def read_maniskill_h5(cfg: ConvertConfig) -> SourceDemos:
    json_path = cfg.path.with_suffix(".json")
    if not json_path.exists():
        raise FileNotFoundError(
            f"{cfg.path} needs its episode list {json_path} (written beside it by ManiSkill)."
        )
    meta = json.loads(json_path.read_text())
    source_task = cfg.task or meta["env_info"]["env_id"]
    task = V1_TASK_NAMES.get(source_task, source_task)
    seeds = {int(ep.get("episode_id", i)): _episode_seed(ep) for i, ep in enumerate(meta["episodes"])}
    return SourceDemos(task, "panda", _maniskill_episodes(cfg.path, task, seeds))


def _episode_seed(episode: dict) -> int:
    seed = episode.get("episode_seed", episode.get("reset_kwargs", {}).get("seed", UNKNOWN_SEED))
    return int(seed[0] if isinstance(seed, list) else seed)


def _maniskill_episodes(path: Path, task: str, seeds: dict[int, int]) -> Iterator[Episode]:
    with h5py.File(path, "r") as file:
        names = sorted((name for name in file if name.startswith("traj_")), key=lambda n: int(n[5:]))
        skipped = 0
        for name in names:
            episode = _maniskill_episode(file[name], name, path, task, seeds.get(int(name[5:]), UNKNOWN_SEED))
            if episode is None:
                skipped += 1
            else:
                yield episode
    if skipped:
        logger.info("Skipped %d/%d episodes of %s that never succeed.", skipped, len(names), path)


def _maniskill_episode(group: h5py.Group, name: str, path: Path, task: str, seed: int) -> Episode | None:
    if not isinstance(group.get("obs"), h5py.Dataset):
        problem = "has no `obs`" if "obs" not in group else "stores `obs` as a dict, not a flat state"
        raise ValueError(
            f"{path}:{name} {problem}. Replay it with state observations first, e.g. "
            f"`python -m mani_skill.trajectory.replay_trajectory --traj-path {path} -o state --save-traj` "
            "(ManiSkill2: `python -m mani_skill2.trajectory.replay_trajectory ... --obs-mode state`)."
        )
    actions = np.asarray(group["actions"], dtype=np.float32)
    length = len(actions)
    flags = _step_flags(group)
    successes = flags.get("success", np.zeros(length, dtype=bool))
    if not successes.any():
        return None
    names, frames = [], []
    for subgoal, candidates in SUBGOAL_FLAGS.get(task, {}).items():
        flag = next((flags[key] for key in candidates if key in flags), None)
        if flag is not None:
            names.append(subgoal)
            # The flag at step t describes obs[t + 1]; a flag that never fires points at the final frame.
            frames.append(min(int(np.argmax(flag)) + 1, length - 1) if flag.any() else length - 1)
    return Episode(
        states=np.asarray(group["obs"][:length], dtype=np.float32),
        actions=actions,
        successes=successes,
        key_frames=[*frames, length - 1],
        key_frame_names=[*names, FINAL],
        seed=seed,
    )


def _step_flags(group: h5py.Group) -> dict[str, np.ndarray]:
    """Per-step boolean arrays stored at the episode's top level or under `infos/` (CoTPC)."""
    length = len(group["actions"])
    candidates = list(group.items()) + (list(group["infos"].items()) if "infos" in group else [])
    return {
        key: np.asarray(value, dtype=bool).reshape(length)
        for key, value in candidates
        if isinstance(value, h5py.Dataset) and value.dtype == bool and value.shape[:1] == (length,)
    }


def _kitchen_reader(
    read_episodes: Callable[[Path], Iterator[Episode]],
) -> Callable[[ConvertConfig], SourceDemos]:
    return lambda cfg: SourceDemos(cfg.task or demo_task(), "franka", read_episodes(cfg.path), KITCHEN_FPS)


# Keyed by --format.
FORMATS: dict[str, Callable[[ConvertConfig], SourceDemos]] = {
    "maniskill_h5": read_maniskill_h5,
    "relay_kitchen": _kitchen_reader(relay_kitchen_episodes),
    "d4rl_kitchen": _kitchen_reader(d4rl_kitchen_episodes),
}


def convert(cfg: ConvertConfig) -> Path:
    if cfg.format not in FORMATS:
        raise ValueError(f"Unknown --format={cfg.format}; available: {', '.join(FORMATS)}.")
    if not cfg.path.exists():
        raise FileNotFoundError(f"No such file: {cfg.path}")
    source = FORMATS[cfg.format](cfg)
    writer = DemoDatasetWriter.open(
        cfg.repo_id,
        cfg.root,
        cfg.fps or source.fps,
        source.task,
        source.robot_type,
        overwrite=cfg.overwrite,
        data_files_size_in_mb=cfg.data_files_size_in_mb,
    )
    try:
        for episode in source.episodes:
            writer.add(episode)
        root = writer.publish()
    except BaseException:
        writer.discard()
        raise
    logger.info("Converted %d episodes of %s into %s.", writer.num_episodes, cfg.path, root)
    if cfg.push_to_hub:
        push_to_hub(cfg.repo_id, root)
    return root


@parser.wrap()
def convert_main(cfg: ConvertConfig) -> Path:
    return convert(cfg)


def main() -> None:
    init_logging()
    convert_main()


if __name__ == "__main__":
    main()
