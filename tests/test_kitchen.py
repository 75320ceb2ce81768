"""Franka Kitchen: env type, count milestones in lerobot-eval's output, scripted demos, converters."""

import json
from pathlib import Path

import draccus
import gymnasium as gym
import h5py
import numpy as np
import pytest
from lerobot.envs.configs import EnvConfig

from lerobot_maxmi.demos.convert import ConvertConfig, convert
from lerobot_maxmi.demos.episode import FINAL
from lerobot_maxmi.demos.kitchen_demos import DEMO_MAX_STEPS, KitchenDemoSource, demo_task
from lerobot_maxmi.demos.record import RecordDemosConfig, record
from lerobot_maxmi.envs.configs import ALL_KITCHEN_TASKS, FrankaKitchenEnvConfig
from lerobot_maxmi.envs.kitchen import (
    ALL_TASKS,
    NUM_TASKS_COMPLETED,
    FrankaKitchenGymEnv,
    can_render,
    count_milestones,
    milestone_names,
    task_completed,
)
from lerobot_maxmi.envs.milestones import (
    MILESTONES_KEY,
    RATES_KEY,
    RecordMilestones,
    add_milestone_rates,
    milestone_rates,
)
from lerobot_maxmi.episode_metadata import GT_KEY_FRAME_NAMES, GT_KEY_FRAMES, read_episode_column

REPO = Path(__file__).resolve().parents[1]
# Seeds whose 4-subtask chains together cover all seven subtasks: three carry the kettle, and each
# opens the microwave, whose door is then in the way, before later subtasks.
GOOD_SEEDS = (1, 2, 3, 7)


def test_config_defaults_and_features():
    cfg = FrankaKitchenEnvConfig()
    assert cfg.type == "franka_kitchen" and cfg.episode_length == 280
    assert tuple(cfg.tasks_to_complete) == ALL_KITCHEN_TASKS == ALL_TASKS
    assert cfg.features["agent_pos"].shape == (30,) and cfg.features["action"].shape == (9,)
    assert FrankaKitchenEnvConfig(state_layout="full").features["agent_pos"].shape == (59,)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"tasks_to_complete": ["microwave", "toaster"]},
            r"Unknown Franka Kitchen subtask\(s\) \['toaster'\]",
        ),
        ({"tasks_to_complete": ["kettle", "kettle"]}, "distinct"),
        ({"state_layout": "pixels"}, "Unknown state_layout"),
    ],
)
def test_config_rejects_bad_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrankaKitchenEnvConfig(**kwargs)


@pytest.mark.parametrize("path", sorted((REPO / "configs/env").glob("franka_kitchen*.json")))
def test_config_files_decode(path):
    cfg = draccus.decode(EnvConfig, json.loads(path.read_text()))
    assert isinstance(cfg, FrankaKitchenEnvConfig)


def test_create_envs_reset_step_close():
    cfg = FrankaKitchenEnvConfig(tasks_to_complete=["microwave", "kettle"], episode_length=5)
    vector_env = cfg.create_envs(n_envs=2)["franka_kitchen"][0]
    observation, info = vector_env.reset(seed=[0, 1])
    assert observation["agent_pos"].shape == (2, 30) and observation["agent_pos"].dtype == np.float32
    np.testing.assert_array_equal(observation["environment_state"], observation["agent_pos"])  # for ACT
    assert not info["is_success"].any()
    for _ in range(5):
        observation, _, terminated, truncated, info = vector_env.step(np.zeros((2, 9)))
    assert truncated.all() and not terminated.any()
    milestones = info["final_info"][MILESTONES_KEY]
    assert set(milestones) >= {"tasks_ge_1", "tasks_ge_2", NUM_TASKS_COMPLETED}
    assert vector_env.call("_max_episode_steps") == (5, 5)
    if can_render():
        assert vector_env.call("render")[0].shape == (224, 224, 3)
    vector_env.close()


def test_without_a_gl_backend_the_env_runs_unrendered(monkeypatch, caplog):
    import mujoco

    from lerobot_maxmi.envs import kitchen

    def no_context(*_args):
        raise RuntimeError("no EGL display")

    monkeypatch.setattr(mujoco, "GLContext", no_context)
    assert not can_render.__wrapped__()  # the uncached check
    assert "MuJoCo cannot render" in caplog.text and "no EGL display" in caplog.text
    monkeypatch.setattr(kitchen, "can_render", lambda: False)
    env = FrankaKitchenGymEnv(["microwave"], max_episode_steps=5)
    assert env.render_mode is None and env.render() is None  # lerobot-eval then skips videos
    env.reset(seed=0)
    env.step(np.zeros(9))
    env.close()


def test_env_reports_completed_tasks():
    env = FrankaKitchenGymEnv(["microwave", "slide cabinet"], max_episode_steps=10, render=False)
    env.reset(seed=0)
    env.simulation.data.qpos[19] = 0.37  # the slide cabinet is open; the step's check sees it
    _, _, terminated, _, info = env.step(np.zeros(9))
    assert info[NUM_TASKS_COMPLETED] == 1 and not info["is_success"] and not terminated
    assert info[MILESTONES_KEY] == {"tasks_ge_1": True, "tasks_ge_2": False, NUM_TASKS_COMPLETED: 1}
    env.close()


def test_count_milestones_aggregate_into_fractions_and_mean():
    # What RecordMilestones keeps per episode, for episodes completing 0, 1, 3 and 4 of 5 tasks.
    episodes = []
    for count in (0, 1, 3, 4):
        recorder = RecordMilestones(_CountingEnv(count), milestone_names(5))
        recorder.reset()
        for _ in range(count + 1):
            recorder.step(None)
        episodes.extend(recorder.pop_episode_milestones())
    rates = milestone_rates(episodes)
    assert rates == pytest.approx(
        {
            "tasks_ge_1": 75.0,
            "tasks_ge_2": 50.0,
            "tasks_ge_3": 50.0,
            "tasks_ge_4": 25.0,
            "tasks_ge_5": 0.0,
            NUM_TASKS_COMPLETED: 2.0,
        }
    )
    eval_info = {
        "per_task": [{"task_group": "franka_kitchen", "metrics": {MILESTONES_KEY: episodes}}],
        "per_group": {"franka_kitchen": {}},
        "overall": {},
    }
    assert add_milestone_rates(eval_info)["overall"][RATES_KEY][NUM_TASKS_COMPLETED] == 2.0


class _CountingEnv(gym.Env):
    """Completes one more task per step, up to `final_count` of 5."""

    def __init__(self, final_count: int):
        self.final_count, self.count = final_count, 0

    def reset(self, **kwargs):
        self.count = 0
        return None, {}

    def step(self, action):
        info = {MILESTONES_KEY: count_milestones(self.count, 5)}
        self.count = min(self.count + 1, self.final_count)
        return None, 0.0, False, False, info


def test_demo_source_chains_only_the_configured_subtasks():
    source = KitchenDemoSource(FrankaKitchenEnvConfig(tasks_to_complete=["kettle"]))
    assert source.chain(np.random.default_rng(0)) == ["kettle"] and source.task == demo_task(1)
    attempt = source.attempt(0)
    assert attempt.failure is None, attempt.failure
    assert attempt.episode.key_frame_names == [FINAL] and attempt.episode.key_frames == [attempt.length - 1]


def test_expert_completes_four_subtask_chains_with_action_noise():
    source = KitchenDemoSource(FrankaKitchenEnvConfig(), action_noise=0.02)
    covered = set()
    for seed in GOOD_SEEDS:
        attempt = source.attempt(seed)
        assert attempt.failure is None, attempt.failure
        assert attempt.length < DEMO_MAX_STEPS
        assert attempt.episode.key_frames[-2] < attempt.episode.key_frames[-1]  # no duplicate final frame
        covered.update(source.chain(np.random.default_rng(seed)))
    assert covered == set(ALL_TASKS)


def test_recorded_demos_round_trip_with_key_frames(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    cfg = RecordDemosConfig(
        env=FrankaKitchenEnvConfig(), repo_id="local/kitchen", root=tmp_path / "kitchen",
        num_episodes=2, seed=GOOD_SEEDS[0], max_attempts=2, action_noise=0.02,
    )  # fmt: skip
    root = record(cfg)
    dataset = LeRobotDataset("local/kitchen", root=root)
    assert dataset.num_episodes == 2 and dataset.fps == 12
    key_frames, names = (
        read_episode_column(root, GT_KEY_FRAMES),
        read_episode_column(root, GT_KEY_FRAME_NAMES),
    )
    for episode in range(2):
        tasks = names[episode][:-1]
        assert len(tasks) >= 3 and names[episode][-1] == FINAL and set(tasks) <= set(ALL_TASKS)
        start = dataset.meta.episodes["dataset_from_index"][episode]
        length = dataset.meta.episodes["length"][episode]
        assert key_frames[episode][-1] == length - 1
        for task, frame in zip(tasks, key_frames[episode], strict=False):
            state = dataset[start + frame]["observation.state"].numpy()
            before = dataset[start + frame - 1]["observation.state"].numpy()
            assert task_completed(state, task) and not task_completed(before, task)


# ---- converters on synthetic files in the published layouts -----------------------------------------

REST = np.zeros(30)
REST[23:30] = [-0.269, 0.35, 1.62, 1.0, 0.0, 0.0, 0.0]  # the kettle at rest; everything else closed


def synthetic_episode(length: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """60-d observations in which the microwave opens at frame 4 and the slide cabinet at frame 7."""
    states = np.tile(REST, (length, 1)) + rng.normal(0, 1e-3, size=(length, 30))
    states[4:, 22] = -0.75
    states[7:, 19] = 0.37
    observations = np.concatenate([states, np.zeros((length, 30))], axis=1)
    return observations.astype(np.float32), rng.uniform(-1, 1, size=(length, 9)).astype(np.float32)


def check_converted(root: Path, lengths: list[int]):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset("local/converted", root=root)
    assert dataset.num_episodes == len(lengths) and dataset.fps == 12
    assert dataset[0]["observation.state"].shape == (30,)
    key_frames = read_episode_column(root, GT_KEY_FRAMES)
    names = read_episode_column(root, GT_KEY_FRAME_NAMES)
    for episode, length in enumerate(lengths):
        assert names[episode] == ["microwave", "slide cabinet", FINAL]
        assert key_frames[episode] == [4, 7, length - 1]


def test_relay_kitchen_converter(tmp_path):
    rng = np.random.default_rng(0)
    lengths = [12, 9]
    observations = np.zeros((12, 2, 60), np.float32)
    actions, mask = np.zeros((12, 2, 9), np.float32), np.zeros((12, 2), np.float32)
    for n, length in enumerate(lengths):
        observations[:length, n], actions[:length, n] = synthetic_episode(length, rng)
        mask[:length, n] = 1
    source = tmp_path / "relay_kitchen"
    source.mkdir()
    for name, array in [
        ("observations_seq", observations),
        ("actions_seq", actions),
        ("existence_mask", mask),
    ]:
        np.save(source / f"{name}.npy", array)
    convert(
        ConvertConfig(path=source, repo_id="local/converted", format="relay_kitchen", root=tmp_path / "out")
    )
    check_converted(tmp_path / "out", lengths)
    # Episode-major arrays are refused with the fix.
    for name, array in [
        ("observations_seq", observations),
        ("actions_seq", actions),
        ("existence_mask", mask),
    ]:
        np.save(source / f"{name}.npy", np.swapaxes(array, 0, 1))
    with pytest.raises(ValueError, match="time-major"):
        convert(ConvertConfig(path=source, repo_id="x/y", format="relay_kitchen", root=tmp_path / "bad"))


def test_d4rl_kitchen_converter(tmp_path):
    rng = np.random.default_rng(1)
    lengths = [10, 8]
    episodes = [synthetic_episode(length, rng) for length in lengths]
    terminals = np.concatenate([np.arange(length) == length - 1 for length in lengths])
    path = tmp_path / "kitchen_complete.hdf5"
    with h5py.File(path, "w") as file:
        file["observations"] = np.concatenate([observations for observations, _ in episodes])
        file["actions"] = np.concatenate([actions for _, actions in episodes])
        file["rewards"] = np.zeros(len(terminals), np.float32)
        file["terminals"] = terminals
        file["timeouts"] = np.zeros_like(terminals)
    convert(ConvertConfig(path=path, repo_id="local/converted", format="d4rl_kitchen", root=tmp_path / "out"))
    check_converted(tmp_path / "out", lengths)
