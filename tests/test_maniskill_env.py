"""The `maniskill` env type: ManiSkill tasks through LeRobot's env interface, and lerobot-eval's
sub-task (milestone) rates."""

import inspect
import json
import logging
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import draccus
import gymnasium as gym
import numpy as np
import pytest
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import NEW_ROLLOUT_OPTION

from lerobot_maxmi.demos.dataset_writer import copy_with_environment_state
from lerobot_maxmi.envs import eval_hooks
from lerobot_maxmi.envs.configs import ManiSkillEnvConfig
from lerobot_maxmi.envs.maniskill_sim import TASKS, has_render_device, missing_assets, restrict_faucet_models
from lerobot_maxmi.envs.milestones import (
    MILESTONES_KEY,
    RATES_KEY,
    add_milestone_rates,
    episodes_in_eval_order,
    make_vector_env,
    milestone_rates,
)

REPO = Path(__file__).resolve().parents[1]
CONFIG_FILES = sorted((REPO / "configs" / "env").glob("maniskill_*.json"))
NEW_ROLLOUT = {NEW_ROLLOUT_OPTION: True}


# ---- config ----------------------------------------------------------------------------------------


def test_config_defaults_follow_the_task():
    config = ManiSkillEnvConfig(task="StackCube-v1")
    assert config.control_mode == "pd_ee_delta_pose"
    assert config.episode_length == TASKS["StackCube-v1"].episode_length
    assert config.features["agent_pos"].shape == config.features["environment_state"].shape == (48,)
    assert config.features_map["environment_state"] == "observation.environment_state"
    assert config.features["action"].shape == (7,)
    assert ManiSkillEnvConfig(task="StackCube-v1", control_mode="pd_joint_delta_pos").features[
        "action"
    ].shape == (8,)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"task": "PushChair-v1"}, "Unknown ManiSkill task 'PushChair-v1'"),
        ({"sim_backend": "gpu"}, "--env.sim_backend=cpu"),
        ({"obs_mode": "rgb"}, "obs_mode='state'"),
        ({"control_mode": "pd_joint_vel"}, "Unsupported control_mode"),
        ({"task": "PickCube-v1", "model_ids": ["5014"]}, "only applies to TurnFaucet-v1"),
    ],
)
def test_config_rejects_unsupported_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ManiSkillEnvConfig(**kwargs)


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda path: path.stem)
def test_config_files_decode(path):
    raw = json.loads(path.read_text())
    config = draccus.decode(EnvConfig, raw)
    assert isinstance(config, ManiSkillEnvConfig)
    assert (config.task, config.episode_length) == (raw["task"], raw["episode_length"])


def test_config_file_passes_as_the_env_argument():
    """How the files are used on the command line: `--env="$(cat configs/env/<file>.json)"`."""
    from lerobot.configs.eval import EvalPipelineConfig

    text = (REPO / "configs/env/maniskill_stackcube.json").read_text()
    config = draccus.parse(
        EvalPipelineConfig, args=[f"--env={text}", "--env.episode_length=20", "--policy.type=act"]
    )
    assert (config.env.task, config.env.episode_length) == ("StackCube-v1", 20)
    assert len(CONFIG_FILES) == 4


# ---- real ManiSkill envs ----------------------------------------------------------------------------


@pytest.mark.parametrize("task", ["PickCube-v1", "StackCube-v1", "PegInsertionSide-v1"])
def test_create_envs_reset_step_close(task):
    spec = TASKS[task]
    config = ManiSkillEnvConfig(task=task, episode_length=3)
    envs = config.create_envs(n_envs=1)
    vector_env = envs["maniskill"][0]
    try:
        assert isinstance(vector_env, gym.vector.SyncVectorEnv)
        assert vector_env.metadata["render_fps"] == 20
        assert vector_env.call("_max_episode_steps") == (3,)
        assert vector_env.call("task") == (task,)
        assert vector_env.call("task_description") == (spec.description,)

        observation, _ = vector_env.reset(seed=[7], options=NEW_ROLLOUT)
        assert observation["agent_pos"].shape == (1, spec.state_dim)
        assert observation["agent_pos"].dtype == np.float32
        np.testing.assert_array_equal(observation["environment_state"], observation["agent_pos"])  # for ACT
        again, _ = vector_env.reset(seed=[7], options=NEW_ROLLOUT)
        np.testing.assert_array_equal(again["agent_pos"], observation["agent_pos"])

        action = np.zeros((1, *vector_env.single_action_space.shape), dtype=np.float32)
        for _ in range(3):
            _, _, _, truncated, info = vector_env.step(action)
        assert truncated.tolist() == [True]
        final = info["final_info"]  # SAME_STEP autoreset moves the terminal info here
        assert final["is_success"].dtype == bool
        assert [name for name in final[MILESTONES_KEY] if not name.startswith("_")] == list(spec.subgoals)
        # Two resets, one finished episode: one record each, nothing reached by standing still.
        assert vector_env.call("pop_episode_milestones") == ([dict.fromkeys(spec.subgoals, False)] * 2,)
    finally:
        vector_env.close()


@pytest.mark.skipif(not missing_assets("TurnFaucet-v1"), reason="faucet models are downloaded here")
def test_turnfaucet_without_assets_fails_at_create_envs_with_download_hint():
    with pytest.raises(FileNotFoundError, match="download_asset partnet_mobility_faucet"):
        ManiSkillEnvConfig(task="TurnFaucet-v1").create_envs(n_envs=1)


@pytest.mark.skipif(bool(missing_assets("TurnFaucet-v1")), reason="faucet models are not downloaded")
def test_turnfaucet_samples_only_the_requested_models():
    held_out = ["5014", "5037"]
    vector_env = ManiSkillEnvConfig(task="TurnFaucet-v1", model_ids=held_out).create_envs(1)["maniskill"][0]
    try:
        for seed in range(3):
            vector_env.reset(seed=[seed], options=NEW_ROLLOUT)
            faucet_names = [faucet.name for faucet in vector_env.envs[0].unwrapped._sim.unwrapped._faucets]
            assert faucet_names[0].split("-")[0] in held_out
        vector_env.step(np.zeros((1, 7), dtype=np.float32))
    finally:
        vector_env.close()


def test_restrict_faucet_models_checks_ids():
    base = SimpleNamespace(train_info={"5002": {}, "5014": {}}, TRAIN_JSON="info_faucet_train.json")
    env = SimpleNamespace(unwrapped=base)
    restrict_faucet_models(env, ["5014"])
    assert base.all_model_ids.tolist() == ["5014"]
    with pytest.raises(ValueError, match=r"Unknown TurnFaucet-v1 model ids \['9999'\]"):
        restrict_faucet_models(env, ["5014", "9999"])


# ---- milestone recording and aggregation, on scripted envs -------------------------------------------

# Per seed, the milestones reported at each step; an episode ends after its last step.
SCRIPTS = {
    0: [
        {"grasp": False, "success": False},
        {"grasp": True, "success": False},
        {"grasp": False, "success": False},
    ],
    1: [{"grasp": True, "success": False}, {"grasp": True, "success": True}],
    2: [{"grasp": False, "success": False}],
    3: [{"grasp": True, "success": False}, {"grasp": False, "success": False}],
}


class ScriptedEnv(gym.Env):
    metadata = {"render_fps": 10}
    observation_space = gym.spaces.Box(-1, 1, (1,), dtype=np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        self.script, self.t = SCRIPTS[seed], 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        flags = self.script[self.t]
        self.t += 1
        info = {"is_success": flags["success"], MILESTONES_KEY: flags}
        return np.zeros(1, np.float32), 0.0, flags["success"], self.t == len(self.script), info


def run_rollouts_like_lerobot(vector_env, n_rollouts):
    """LeRobot's rollout loop: seeded reset, then step every sub-env until all are done."""
    for rollout in range(n_rollouts):
        seeds = [rollout * vector_env.num_envs + i for i in range(vector_env.num_envs)]
        vector_env.reset(seed=seeds, options=NEW_ROLLOUT)
        done = np.zeros(vector_env.num_envs, dtype=bool)
        while not done.all():
            _, _, terminated, truncated, _ = vector_env.step(np.zeros((vector_env.num_envs, 1), np.float32))
            done |= terminated | truncated


def test_milestones_are_recorded_once_per_rollout_and_reached_at_any_step():
    vector_env = make_vector_env(ScriptedEnv, ("grasp", "success"), n_envs=2, use_async_envs=False)
    assert vector_env.metadata[MILESTONES_KEY] == ("grasp", "success")
    run_rollouts_like_lerobot(vector_env, n_rollouts=2)
    per_env = vector_env.call("pop_episode_milestones")
    assert per_env == (
        [{"grasp": True, "success": False}, {"grasp": False, "success": False}],  # seeds 0, 2
        [{"grasp": True, "success": True}, {"grasp": True, "success": False}],  # seeds 1, 3
    )
    assert vector_env.call("pop_episode_milestones") == ([], [])
    vector_env.close()


def test_episodes_are_numbered_like_lerobot_and_surplus_dropped():
    per_env = (["seed0", "seed2"], ["seed1", "seed3"])
    assert episodes_in_eval_order(per_env, n_episodes=3) == ["seed0", "seed1", "seed2"]


def test_milestone_rates_are_percentages_of_episodes():
    episodes = [
        {"grasp": True, "success": False},
        {"grasp": True, "success": True},
        {"grasp": False, "success": False},
    ]
    assert milestone_rates(episodes) == pytest.approx({"grasp": 200 / 3, "success": 100 / 3})


def test_rates_are_added_per_group_and_overall_only_where_recorded():
    def task(group, milestones=None):
        metrics = {"successes": [False]}
        if milestones is not None:
            metrics[MILESTONES_KEY] = milestones
        return {"task_group": group, "task_id": 0, "metrics": metrics}

    eval_info = {
        "per_task": [
            task("a", [{"grasp": True, "success": True}]),
            task("a", [{"grasp": False, "success": False}]),
            task("b", [{"grasp": True, "success": False}]),
            task("other"),
        ],
        "per_group": {"a": {}, "b": {}, "other": {}},
        "overall": {},
    }
    add_milestone_rates(eval_info)
    assert eval_info["per_group"]["a"][RATES_KEY] == {"grasp": 50.0, "success": 50.0}
    assert eval_info["per_group"]["b"][RATES_KEY] == {"grasp": 100.0, "success": 0.0}
    assert RATES_KEY not in eval_info["per_group"]["other"]
    assert eval_info["overall"][RATES_KEY] == pytest.approx({"grasp": 200 / 3, "success": 100 / 3})


# ---- the lerobot-eval wraps -------------------------------------------------------------------------


def fake_eval_one(env, **kwargs):
    """Stands in for lerobot_eval.eval_one: runs the rollouts, returns the task's metrics."""
    fake_eval_one.calls.append(kwargs)
    run_rollouts_like_lerobot(env, n_rollouts=2)
    return {"successes": [False] * kwargs["n_episodes"]}


def test_eval_one_wrap_collects_milestones_and_skips_videos_without_renderer(caplog):
    fake_eval_one.calls = []
    vector_env = make_vector_env(ScriptedEnv, ("grasp", "success"), n_envs=2, use_async_envs=False)
    assert vector_env.render_mode is None
    with caplog.at_level(logging.WARNING):
        metrics = eval_hooks._collecting_milestones(fake_eval_one)(
            vector_env, n_episodes=3, max_episodes_rendered=10
        )
    assert fake_eval_one.calls[0]["max_episodes_rendered"] == 0
    assert "evaluation videos are skipped" in caplog.text
    assert metrics[MILESTONES_KEY] == [
        {"grasp": True, "success": False},
        {"grasp": True, "success": True},
        {"grasp": False, "success": False},
    ]
    vector_env.close()


def test_eval_one_wrap_leaves_other_env_types_alone():
    calls = []

    def eval_one(env, **kwargs):
        calls.append(kwargs)
        return {"successes": []}

    vector_env = gym.vector.SyncVectorEnv([ScriptedEnv])
    metrics = eval_hooks._collecting_milestones(eval_one)(vector_env, n_episodes=2, max_episodes_rendered=10)
    assert calls[0]["max_episodes_rendered"] == 10
    assert metrics == {"successes": []}
    vector_env.close()


def test_hooks_install_once_and_only_on_supported_lerobot(monkeypatch):
    from lerobot.scripts import lerobot_eval

    assert eval_hooks._is_supported(lerobot_eval)
    monkeypatch.setattr(eval_hooks.lerobot, "__version__", "0.7.0")
    assert not eval_hooks._is_supported(lerobot_eval)
    monkeypatch.undo()

    # Start from LeRobot's own functions (earlier tests' create_envs may have wrapped them already);
    # monkeypatch restores whatever was there after the test.
    originals = tuple(inspect.unwrap(getattr(lerobot_eval, name)) for name in ("eval_one", "eval_policy_all"))
    monkeypatch.setattr(lerobot_eval, "eval_one", originals[0])
    monkeypatch.setattr(lerobot_eval, "eval_policy_all", originals[1])
    eval_hooks.install_eval_hooks()
    wrapped = lerobot_eval.eval_one, lerobot_eval.eval_policy_all
    assert wrapped[0] is not originals[0] and wrapped[1] is not originals[1]
    eval_hooks.install_eval_hooks()
    assert (lerobot_eval.eval_one, lerobot_eval.eval_policy_all) == wrapped
    assert getattr(lerobot_eval.eval_one, eval_hooks._INSTALLED)


# ---- end to end: lerobot-train, then lerobot-eval on our env, in subprocesses -----------------------


def make_pickcube_shaped_dataset(root: Path, num_episodes: int = 2):
    """PickCube-sized random episodes with the columns the demo recorder writes."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (42,), "names": None},
        "action": {"dtype": "float32", "shape": (7,), "names": None},
    }
    dataset = LeRobotDataset.create(
        repo_id="local/pickcube", fps=20, features=features, root=root, use_videos=False
    )
    rng = np.random.default_rng(0)
    for _ in range(num_episodes):
        for _ in range(10):
            frame = {"observation.state": rng.normal(size=42), "action": rng.uniform(-1, 1, size=7)}
            dataset.add_frame(
                {key: value.astype(np.float32) for key, value in frame.items()} | {"task": "pick"}
            )
        dataset.save_episode()
    dataset.finalize()
    return dataset


def run_cli(name: str, *args: str) -> str:
    command = [str(Path(sys.executable).with_name(name)), *args]
    env = os.environ | {"HF_HUB_OFFLINE": "1"}
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-5000:]
    return result.stdout + result.stderr


def evaluate_last_checkpoint(tmp_path: Path, episodes: int) -> dict:
    """lerobot-eval of the run under tmp_path/train on PickCube (10-step episodes); its eval_info.json."""
    run_cli(
        "lerobot-eval",
        f"--policy.path={tmp_path / 'train/checkpoints/last/pretrained_model'}",
        "--env.type=maniskill",
        "--env.task=PickCube-v1",
        "--env.episode_length=10",
        f"--eval.n_episodes={episodes}",
        "--eval.batch_size=1",
        "--policy.device=cpu",
        f"--output_dir={tmp_path / 'eval'}",
    )
    return json.loads((tmp_path / "eval/eval_info.json").read_text())


@pytest.mark.slow
def test_lerobot_eval_reports_success_and_subtask_rates(tmp_path):
    make_pickcube_shaped_dataset(tmp_path / "dataset")
    log = run_cli(
        "lerobot-train",
        "--dataset.repo_id=local/pickcube",
        f"--dataset.root={tmp_path / 'dataset'}",
        "--policy.type=cotpc",
        "--policy.context_length=4",
        "--policy.dim_model=16",
        "--policy.n_heads=2",
        "--policy.n_layers=1",
        "--policy.device=cpu",
        "--steps=2",
        "--batch_size=2",
        "--num_workers=0",
        "--save_freq=2",
        # evaluation in the training loop, on our env
        "--env.type=maniskill",
        "--env.task=PickCube-v1",
        "--env.episode_length=5",
        "--env_eval_freq=2",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        f"--output_dir={tmp_path / 'train'}",
    )
    assert "Eval policy at step 2" in log and RATES_KEY in log
    eval_info = evaluate_last_checkpoint(tmp_path, episodes=2)
    overall = eval_info["overall"]
    assert overall["n_episodes"] == 2
    assert 0 <= overall["pc_success"] <= 100
    assert 0 <= overall[RATES_KEY]["grasp"] <= 100
    assert eval_info["per_group"]["maniskill"][RATES_KEY].keys() == {"grasp", "success"}
    if not has_render_device():
        assert overall["video_paths"] == []  # skipped, not crashed


@pytest.mark.slow
def test_lerobot_eval_runs_a_builtin_act_checkpoint(tmp_path):
    """LeRobot's own ACT, trained a few steps on a 3-episode set, evaluated on PickCube through our env."""
    make_pickcube_shaped_dataset(tmp_path / "demos", num_episodes=3)
    copied = copy_with_environment_state(tmp_path / "demos", tmp_path / "dataset", "local/pickcube")
    np.testing.assert_array_equal(copied[7]["observation.environment_state"], copied[7]["observation.state"])
    tiny_act = {
        "chunk_size": 4, "n_action_steps": 4, "dim_model": 16, "n_heads": 2, "dim_feedforward": 32,
        "n_encoder_layers": 1, "n_decoder_layers": 1, "use_vae": "false",
    }  # fmt: skip
    run_cli(
        "lerobot-train",
        "--dataset.repo_id=local/pickcube",
        f"--dataset.root={tmp_path / 'dataset'}",
        "--policy.type=act",
        *(f"--policy.{name}={value}" for name, value in tiny_act.items()),
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--steps=2",
        "--batch_size=2",
        "--num_workers=0",
        "--env_eval_freq=0",
        "--save_freq=2",
        f"--output_dir={tmp_path / 'train'}",
    )
    overall = evaluate_last_checkpoint(tmp_path, episodes=1)["overall"]
    assert overall["n_episodes"] == 1
    assert overall[RATES_KEY].keys() == {"grasp", "success"}
