"""Scripted ManiSkill demos: experts, key frames, the recorder's dataset contract, replay, converter."""

import json

import draccus
import h5py
import numpy as np
import pytest

from lerobot_maxmi.demos import record as record_module
from lerobot_maxmi.demos.convert import ConvertConfig, convert
from lerobot_maxmi.demos.episode import Episode
from lerobot_maxmi.demos.experts import make_expert
from lerobot_maxmi.demos.record import RecordDemosConfig, record
from lerobot_maxmi.demos.rollout import Attempt, key_frame_names, replay, run_expert
from lerobot_maxmi.envs.configs import ManiSkillEnvConfig
from lerobot_maxmi.envs.maniskill_sim import make_sim_env, subgoal_flags, task_spec
from lerobot_maxmi.episode_metadata import (
    EPISODE_SEED,
    GT_KEY_FRAME_NAMES,
    GT_KEY_FRAMES,
    read_episode_column,
)

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.mark.parametrize(
    ("task", "control_mode", "seeds"),
    [
        ("PickCube-v1", "pd_ee_delta_pose", (0, 1)),
        ("PickCube-v1", "pd_ee_delta_pos", (2,)),
        ("StackCube-v1", "pd_ee_delta_pose", (0, 1)),
        ("PegInsertionSide-v1", "pd_ee_delta_pose", (0,)),
    ],
)
def test_expert_solves_and_subgoals_fire_in_order(task, control_mode, seeds):
    max_steps = task_spec(task).episode_length
    env = make_sim_env(task, control_mode, max_episode_steps=max_steps + 1)
    expert = make_expert(task, control_mode)
    for seed in seeds:
        attempt = run_expert(env, expert, seed, max_steps, randomize_expert=True)
        assert attempt.failure is None, f"{task} seed {seed}: {attempt.failure}"
        episode = attempt.episode
        assert episode.key_frame_names == key_frame_names(task)
        assert episode.key_frames == sorted(episode.key_frames)
        assert episode.key_frames[-1] == len(episode.actions) - 1
        assert episode.states.dtype == episode.actions.dtype == np.float32
        # The final frame's observation is a success state: the step before it succeeded.
        assert episode.successes[-2]


def test_subgoal_key_frames_match_the_simulator():
    """Replaying up to each key frame lands on the first state where that sub-goal holds."""
    env = make_sim_env("StackCube-v1", max_episode_steps=151)
    attempt = run_expert(env, make_expert("StackCube-v1"), seed=3, max_steps=150)
    episode = attempt.episode
    env.reset(seed=3)
    held = {name: [] for name in episode.key_frame_names[:-1]}
    for action in episode.actions:
        _, _, _, _, info = env.step(action)
        for name, value in subgoal_flags(env, info).items():
            if name in held:
                held[name].append(value)
    for name, frame in zip(episode.key_frame_names[:-1], episode.key_frames, strict=False):
        # Flag after step t describes frame t + 1.
        assert held[name][frame - 1] and not any(held[name][: frame - 1])


def test_no_expert_and_unknown_task_errors():
    with pytest.raises(ValueError, match="lerobot-maxmi-convert"):
        make_expert("TurnFaucet-v1")
    with pytest.raises(ValueError, match="Unknown ManiSkill task"):
        task_spec("PushChair-v1")
    with pytest.raises(ValueError, match="control modes"):
        make_expert("PegInsertionSide-v1", "pd_ee_delta_pos")


@pytest.fixture(scope="module")
def pick_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("demos") / "pick"
    cfg = RecordDemosConfig(
        env=ManiSkillEnvConfig(task="PickCube-v1"), repo_id="local/pick", root=root, num_episodes=3
    )
    record(cfg)
    return cfg


def test_cli_parses_env_choice():
    cfg = draccus.parse(
        RecordDemosConfig,
        args=["--env.type=maniskill", "--env.task=StackCube-v1", "--repo_id=local/x", "--num_workers=2"],
    )
    assert isinstance(cfg.env, ManiSkillEnvConfig) and cfg.env.task == "StackCube-v1"
    assert cfg.num_workers == 2 and cfg.root.name == "x"


def test_dataset_round_trip(pick_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(pick_dataset.repo_id, root=pick_dataset.root)
    assert dataset.meta.total_episodes == 3 and dataset.fps == 20
    assert dataset.meta.features["observation.state"]["shape"] == (task_spec("PickCube-v1").state_dim,)
    assert dataset.meta.features["action"]["shape"] == (7,)
    frame = dataset[0]
    assert frame["task"] == "PickCube-v1" and not frame["next.success"].item()
    assert read_episode_column(pick_dataset.root, EPISODE_SEED) == {0: 0, 1: 1, 2: 2}
    key_frames = read_episode_column(pick_dataset.root, GT_KEY_FRAMES)
    assert set(map(tuple, read_episode_column(pick_dataset.root, GT_KEY_FRAME_NAMES).values())) == {
        ("grasp", "final")
    }
    lengths = dataset.meta.episodes["length"]
    for index, frames in key_frames.items():
        assert 0 < frames[0] < frames[1] == lengths[index] - 1
    assert not (pick_dataset.root.parent / "pick.incomplete").exists()


def test_refuses_to_overwrite(pick_dataset):
    with pytest.raises(FileExistsError, match="--overwrite=true"):
        record(pick_dataset)


class AlwaysFailing:
    fps, task, robot_type = 20, "PickCube-v1", "panda"

    def attempt(self, seed: int) -> Attempt:
        return Attempt(seed, 5, failure="cube out of reach")


def test_no_successful_attempt_names_the_failure_and_writes_nothing(monkeypatch, tmp_path):
    monkeypatch.setitem(record_module.DEMO_SOURCES, "maniskill", lambda env_cfg, cfg: AlwaysFailing())
    cfg = RecordDemosConfig(
        env=ManiSkillEnvConfig(), repo_id="local/none", root=tmp_path / "none", num_episodes=2, max_attempts=3
    )
    with pytest.raises(RuntimeError, match=r"None of 3 attempts succeeded.*seed 2: cube out of reach"):
        record(cfg)
    assert list(tmp_path.iterdir()) == []  # neither the dataset nor its staging folder is left


class AlwaysSucceeding(AlwaysFailing):
    def attempt(self, seed: int) -> Attempt:
        states = np.random.default_rng(seed).normal(size=(6, 3)).astype(np.float32)
        successes = np.arange(6) == 5
        episode = Episode(states, states[:, :2].copy(), successes, [2, 5], ["grasp", "final"], seed)
        return Attempt(seed, 6, episode=episode)


def test_small_data_files_give_a_parquet_file_per_episode_also_when_resuming(monkeypatch, tmp_path):
    """What lets a stream feed every loader worker (docs/RESULTS.md, "CoTPC's data path")."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    monkeypatch.setitem(record_module.DEMO_SOURCES, "maniskill", lambda env_cfg, cfg: AlwaysSucceeding())
    config = {"env": ManiSkillEnvConfig(), "num_episodes": 3}
    record(RecordDemosConfig(**config, repo_id="local/default", root=tmp_path / "default"))
    record(
        RecordDemosConfig(
            **config, repo_id="local/small", root=tmp_path / "small", data_files_size_in_mb=0.001
        )
    )
    assert len(list((tmp_path / "default").glob("data/*/*.parquet"))) == 1
    assert len(list((tmp_path / "small").glob("data/*/*.parquet"))) == 3

    more = {**config, "num_episodes": 5, "resume": True, "data_files_size_in_mb": 0.001}
    record(RecordDemosConfig(**more, repo_id="local/default", root=tmp_path / "default"))
    assert len(list((tmp_path / "default").glob("data/*/*.parquet"))) == 3  # the new episodes, a file each
    resumed = LeRobotDataset("local/default", root=tmp_path / "default")
    assert resumed.meta.total_episodes == 5 and len(resumed) == 30


def test_non_positive_data_file_size_is_refused_before_anything_is_written(monkeypatch, tmp_path):
    monkeypatch.setitem(record_module.DEMO_SOURCES, "maniskill", lambda env_cfg, cfg: AlwaysSucceeding())
    cfg = RecordDemosConfig(
        env=ManiSkillEnvConfig(), repo_id="local/x", root=tmp_path / "x", data_files_size_in_mb=0
    )
    with pytest.raises(ValueError, match="--data_files_size_in_mb must be positive"):
        record(cfg)
    assert list(tmp_path.iterdir()) == []


def test_resume_adds_new_seeds_only(pick_dataset, tmp_path):
    import shutil

    root = tmp_path / "pick"
    shutil.copytree(pick_dataset.root, root)
    cfg = RecordDemosConfig(
        env=ManiSkillEnvConfig(task="PickCube-v1"),
        repo_id="local/pick",
        root=root,
        num_episodes=5,
        resume=True,
    )
    record(cfg)
    seeds = read_episode_column(root, EPISODE_SEED)
    assert sorted(seeds.values()) == [0, 1, 2, 3, 4]
    assert len(read_episode_column(root, GT_KEY_FRAMES)) == 5


def test_replay_of_stored_actions_reproduces_the_episode(pick_dataset):
    """Open-loop replay of the dataset's float32 actions from the seed, in a fresh env."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(pick_dataset.repo_id, root=pick_dataset.root)
    episode = 2  # recorded after two other episodes in the same env
    start, end = (
        int(dataset.meta.episodes[key][episode]) for key in ("dataset_from_index", "dataset_to_index")
    )
    frames = dataset.hf_dataset.select(range(start, end))
    actions = np.stack([np.asarray(action) for action in frames["action"]])
    seed = read_episode_column(pick_dataset.root, EPISODE_SEED)[episode]
    states, successes = replay(make_sim_env("PickCube-v1"), seed, actions)
    # Float-level differences are possible: PhysX keeps contact caches across resets of one env.
    recorded = np.stack([np.asarray(state) for state in frames["observation.state"]])
    np.testing.assert_allclose(states, recorded, atol=1e-4)
    np.testing.assert_array_equal(successes, np.asarray(frames["next.success"]).reshape(-1))
    assert successes[-1]


def _write_trajectories(path, with_obs=True):
    """A ManiSkill2/CoTPC-style trajectory.h5 + .json: traj_0 and traj_1 succeed, traj_2 does not."""
    rng = np.random.default_rng(0)
    episodes = []
    with h5py.File(path, "w") as file:
        for index, (length, grasp_step, on_step) in enumerate([(10, 2, 6), (8, 3, 7), (6, 1, 4)]):
            group = file.create_group(f"traj_{index}")
            if with_obs:
                group["obs"] = rng.normal(size=(length + 1, 55))
            group["actions"] = rng.uniform(-1, 1, size=(length, 8))
            steps = np.arange(length)
            group["success"] = (steps >= length - 2) if index < 2 else np.zeros(length, bool)
            group["infos/is_cubaA_grasped"] = steps >= grasp_step
            group["infos/is_cubeA_on_cubeB"] = steps >= on_step
            group["infos/is_cubeA_static"] = np.ones(length, bool)
            episodes.append(
                {"episode_id": index, "episode_seed": 100 + index, "control_mode": "pd_joint_delta_pos"}
            )
    path.with_suffix(".json").write_text(
        json.dumps({"env_info": {"env_id": "StackCube-v0"}, "episodes": episodes})
    )


def test_converter_keeps_stored_flags_as_key_frames(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    source = tmp_path / "trajectory.state.pd_joint_delta_pos.h5"
    _write_trajectories(source)
    root = convert(ConvertConfig(path=source, repo_id="local/cotpc_stack", root=tmp_path / "out"))
    dataset = LeRobotDataset("local/cotpc_stack", root=root)
    assert dataset.meta.total_episodes == 2 and dataset.meta.total_frames == 18
    assert dataset[0]["task"] == "StackCube-v1"
    assert read_episode_column(root, EPISODE_SEED) == {0: 100, 1: 101}
    # Flag at step t -> frame t + 1 (clipped to the last frame); then the final frame.
    assert read_episode_column(root, GT_KEY_FRAMES) == {0: [3, 7, 9], 1: [4, 7, 7]}
    assert read_episode_column(root, GT_KEY_FRAME_NAMES)[0] == ["grasp", "a_on_b", "final"]
    assert len(list(root.glob("data/*/*.parquet"))) == 1

    small = ConvertConfig(
        path=source, repo_id="local/small", root=tmp_path / "small", data_files_size_in_mb=0.001
    )
    assert len(list(convert(small).glob("data/*/*.parquet"))) == 2  # a file per kept episode


def test_converter_without_obs_says_how_to_replay(tmp_path):
    source = tmp_path / "trajectory.h5"
    _write_trajectories(source, with_obs=False)
    with pytest.raises(ValueError, match="-o state"):
        convert(ConvertConfig(path=source, repo_id="local/x", root=tmp_path / "out"))
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.incomplete").exists()
