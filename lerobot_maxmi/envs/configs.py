"""Env types LeRobot's CLIs pick with `--env.type=...` (registered on import of lerobot_maxmi).

Heavy dependencies (ManiSkill, SAPIEN) are imported only when envs are created.
"""

from dataclasses import dataclass, field
from functools import partial

import gymnasium as gym
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION

from lerobot_maxmi.envs.maniskill_sim import ACTION_DIMS, FAUCET_TASK, task_spec
from lerobot_maxmi.envs.observation import add_state_features, features_map

# The subtasks of gymnasium-robotics' FrankaKitchen-v1, listed here so importing configs stays light.
ALL_KITCHEN_TASKS = (
    "bottom burner", "top burner", "light switch", "slide cabinet", "hinge cabinet", "microwave", "kettle",
)  # fmt: skip

SUPPORTED_SIM_BACKENDS = ("cpu",)
KITCHEN_TASK = "FrankaKitchen-v1"  # the gymnasium-robotics id, and the kitchen's task name in our tools
NUM_TASKS_COMPLETED = "num_tasks_completed"  # the kitchen's score, a milestone that is a count


@EnvConfig.register_subclass("maniskill")
@dataclass
class ManiSkillEnvConfig(EnvConfig):
    """A ManiSkill 3 task on the CPU simulator, state observations.

    `model_ids` (TurnFaucet only) restricts which faucet models are sampled, e.g. to evaluate on
    faucets held out from training; ids are the keys of ManiSkill's `info_faucet_train.json`.
    """

    task: str | None = "PickCube-v1"
    fps: int = 20  # ManiSkill's control frequency
    control_mode: str = "pd_ee_delta_pose"
    obs_mode: str = "state"
    episode_length: int | None = None  # None: the task's default (TASKS in maniskill_sim)
    sim_backend: str = "cpu"
    model_ids: list[str] | None = None
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=features_map)

    def __post_init__(self):
        spec = task_spec(self.task)
        if self.control_mode not in ACTION_DIMS:
            raise ValueError(
                f"Unsupported control_mode {self.control_mode!r}; choose one of {sorted(ACTION_DIMS)}."
            )
        if self.obs_mode != "state":
            raise ValueError(f"Only obs_mode='state' is supported, got {self.obs_mode!r}.")
        if self.sim_backend not in SUPPORTED_SIM_BACKENDS:
            raise ValueError(
                f"sim_backend={self.sim_backend!r} is not supported yet: the maniskill env type runs one "
                "CPU simulation per sub-env. Use --env.sim_backend=cpu (--eval.batch_size runs several)."
            )
        if self.model_ids is not None and self.task != FAUCET_TASK:
            raise ValueError(
                f"model_ids selects faucet models and only applies to {FAUCET_TASK}, not {self.task}."
            )
        if self.episode_length is None:
            self.episode_length = spec.episode_length
        self.features.setdefault(ACTION, PolicyFeature(FeatureType.ACTION, (ACTION_DIMS[self.control_mode],)))
        if spec.state_dim is not None:
            add_state_features(self.features, spec.state_dim)

    @property
    def gym_kwargs(self) -> dict:
        """Keyword arguments of ManiSkillGymEnv."""
        return {
            "task": self.task,
            "control_mode": self.control_mode,
            "obs_mode": self.obs_mode,
            "max_episode_steps": self.episode_length,
            "fps": self.fps,
            "model_ids": self.model_ids,
        }

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        from lerobot_maxmi.envs.eval_hooks import install_eval_hooks
        from lerobot_maxmi.envs.maniskill import ManiSkillGymEnv
        from lerobot_maxmi.envs.maniskill_sim import require_assets
        from lerobot_maxmi.envs.milestones import make_vector_env

        require_assets(self.task)  # here, not in a sub-env or worker process, so the message is seen
        install_eval_hooks()
        make_one = partial(ManiSkillGymEnv, **self.gym_kwargs)
        vector_env = make_vector_env(make_one, task_spec(self.task).subgoals, n_envs, use_async_envs)
        return {self.type: {0: vector_env}}


@EnvConfig.register_subclass("franka_kitchen")
@dataclass
class FrankaKitchenEnvConfig(EnvConfig):
    """Franka Kitchen (gymnasium-robotics FrankaKitchen-v1), state observations, joint-velocity actions.

    The default evaluates all 7 subtasks in any order (BeT / MaxMI), which is what "at least 5 tasks"
    needs; `--env.tasks_to_complete='[microwave,kettle,light switch,slide cabinet]'` is D4RL's
    kitchen-complete set. `state_layout`: "classic" is the 30-d D4RL state (robot qpos 9 + object
    qpos 21), "full" the env's 59-d observation (with velocities).
    """

    task: str | None = KITCHEN_TASK
    fps: int = 12  # one env step is 0.08 s
    tasks_to_complete: list[str] = field(default_factory=lambda: list(ALL_KITCHEN_TASKS))
    episode_length: int = 280
    state_layout: str = "classic"
    render: bool = True  # videos where MuJoCo has a headless GL backend (EGL / OSMesa via MUJOCO_GL)
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=features_map)

    def __post_init__(self):
        from lerobot_maxmi.envs.kitchen import STATE_LAYOUTS, check_state_layout, check_tasks

        self.tasks_to_complete = list(check_tasks(self.tasks_to_complete))
        state_dim = len(STATE_LAYOUTS[check_state_layout(self.state_layout)])
        self.features.setdefault(ACTION, PolicyFeature(FeatureType.ACTION, (9,)))
        add_state_features(self.features, state_dim)

    @property
    def gym_kwargs(self) -> dict:
        """Keyword arguments of FrankaKitchenGymEnv."""
        return {
            "tasks_to_complete": list(self.tasks_to_complete),
            "max_episode_steps": self.episode_length,
            "state_layout": self.state_layout,
            "fps": self.fps,
            "render": self.render,
        }

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        from lerobot_maxmi.envs.eval_hooks import install_eval_hooks
        from lerobot_maxmi.envs.kitchen import FrankaKitchenGymEnv, milestone_names
        from lerobot_maxmi.envs.milestones import make_vector_env

        install_eval_hooks()
        make_one = partial(FrankaKitchenGymEnv, **self.gym_kwargs)
        milestones = milestone_names(len(self.tasks_to_complete))
        return {self.type: {0: make_vector_env(make_one, milestones, n_envs, use_async_envs)}}
