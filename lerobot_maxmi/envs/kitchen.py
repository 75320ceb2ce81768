"""Franka Kitchen (gymnasium-robotics `FrankaKitchen-v1`) as one LeRobot evaluation sub-env.

The score of the benchmark is the number of subtasks completed in an episode (any order). Each step
reports it as milestones: `tasks_ge_k` (at least k tasks done, k = 1..number of tasks) and the count
`num_tasks_completed`, which lerobot-eval's output aggregates into percentages and a mean.
"""

import logging
import os
from functools import cache

# Headless rendering: MuJoCo picks its GL backend from MUJOCO_GL when it is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium_robotics.envs.franka_kitchen.kitchen_env import (  # noqa: E402
    BONUS_THRESH,
    OBS_ELEMENT_GOALS,
    OBS_ELEMENT_INDICES,
)

from lerobot_maxmi.envs.configs import KITCHEN_TASK, NUM_TASKS_COMPLETED  # noqa: E402
from lerobot_maxmi.envs.milestones import MILESTONES_KEY  # noqa: E402
from lerobot_maxmi.envs.observation import state_observation, state_observation_space  # noqa: E402

logger = logging.getLogger(__name__)

GYM_ID = KITCHEN_TASK
ALL_TASKS = tuple(OBS_ELEMENT_GOALS)  # the 7 subtasks, in gymnasium-robotics' order
FPS = 12  # one env step is 0.08 s (12.5 Hz); LeRobot needs an integer rate
RENDER_SIZE = 224

# Observation layouts of the 59-d `observation`: [robot qpos 9, robot qvel 9, object qpos 21, object qvel 20].
# "classic" is the 30-d D4RL / relay-kitchen state, i.e. (noisy) qpos[0:30].
STATE_LAYOUTS = {
    "classic": np.r_[0:9, 18:39],
    "full": np.r_[0:59],
}


def check_tasks(tasks) -> tuple[str, ...]:
    unknown = [task for task in tasks if task not in ALL_TASKS]
    if unknown:
        raise ValueError(f"Unknown Franka Kitchen subtask(s) {unknown}; choose from {list(ALL_TASKS)}.")
    if not tasks or len(set(tasks)) != len(tasks):
        raise ValueError(f"tasks_to_complete must name distinct subtasks, got {list(tasks)}.")
    return tuple(tasks)


def check_state_layout(layout: str) -> str:
    if layout not in STATE_LAYOUTS:
        raise ValueError(f"Unknown state_layout {layout!r}; choose one of {sorted(STATE_LAYOUTS)}.")
    return layout


def task_completed(qpos: np.ndarray, task: str) -> bool:
    """The benchmark's completion test on the first 30 qpos (robot 9 + objects 21, the classic state)."""
    distance = np.linalg.norm(qpos[..., OBS_ELEMENT_INDICES[task]] - OBS_ELEMENT_GOALS[task], axis=-1)
    return distance < BONUS_THRESH


def count_milestones(num_completed: int, num_tasks: int) -> dict:
    flags = {f"tasks_ge_{k}": num_completed >= k for k in range(1, num_tasks + 1)}
    return {**flags, NUM_TASKS_COMPLETED: num_completed}


def milestone_names(num_tasks: int) -> list[str]:
    return list(count_milestones(0, num_tasks))


@cache
def can_render() -> bool:
    """Whether MuJoCo can open an offscreen GL context (EGL or OSMesa, per MUJOCO_GL)."""
    try:
        import mujoco

        context = mujoco.GLContext(8, 8)
        context.make_current()
        context.free()
        return True
    except Exception as error:  # any GL failure means the same: no renderer here
        logger.warning("MuJoCo cannot render (MUJOCO_GL=%s): %r.", os.environ.get("MUJOCO_GL"), error)
        return False


def make_kitchen(tasks, max_episode_steps: int, render_mode: str | None = None) -> gym.Env:
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    size = {"width": RENDER_SIZE, "height": RENDER_SIZE} if render_mode else {}
    return gym.make(
        GYM_ID,
        tasks_to_complete=list(tasks),
        max_episode_steps=max_episode_steps,
        render_mode=render_mode,
        disable_env_checker=True,
        **size,
    )


def _fast_software_rendering(env: gym.Env) -> None:
    """Shadows, reflections and 8x multisampling make software GL render at about 1 fps; drop them."""
    import mujoco

    kitchen = env.unwrapped
    kitchen.model.vis.quality.offsamples = 0
    viewer = kitchen.robot_env.mujoco_renderer._get_viewer("rgb_array")
    viewer.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    viewer.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0


class FrankaKitchenGymEnv(gym.Env):
    """Observation: the state (see `envs.observation`); info `is_success` (all tasks done), the number of
    completed tasks and its milestones. Renders RGB frames where MuJoCo has a headless GL backend."""

    def __init__(
        self,
        tasks_to_complete=ALL_TASKS,
        max_episode_steps: int = 280,
        state_layout: str = "classic",
        fps: int = FPS,
        render: bool = True,
    ):
        super().__init__()
        self.tasks = check_tasks(tasks_to_complete)
        self.state_indices = STATE_LAYOUTS[check_state_layout(state_layout)]
        self.render_mode = "rgb_array" if render and can_render() else None
        self._kitchen = make_kitchen(self.tasks, max_episode_steps, self.render_mode)
        if self.render_mode:
            _fast_software_rendering(self._kitchen)
        self.task = ", ".join(self.tasks)
        self.task_description = f"complete the kitchen subtasks: {self.task}"
        self._max_episode_steps = max_episode_steps
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": fps}
        self.action_space = self._kitchen.action_space
        self.observation_space = state_observation_space(self.state_indices.shape)

    @property
    def simulation(self):
        """The underlying KitchenEnv (MuJoCo `model` and `data`), for scripted experts."""
        return self._kitchen.unwrapped

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        # `options` carries LeRobot's rollout markers, which mean nothing to the kitchen.
        super().reset(seed=seed)
        observation, _ = self._kitchen.reset(seed=seed)
        return self._observation(observation), {"is_success": False, NUM_TASKS_COMPLETED: 0}

    def step(self, action: np.ndarray):
        observation, reward, terminated, truncated, kitchen_info = self._kitchen.step(action)
        num_completed = len(kitchen_info["episode_task_completions"])
        info = {
            "is_success": num_completed == len(self.tasks),
            NUM_TASKS_COMPLETED: num_completed,
            MILESTONES_KEY: count_milestones(num_completed, len(self.tasks)),
        }
        return self._observation(observation), float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        return self._kitchen.render() if self.render_mode is not None else None

    def close(self) -> None:
        self._kitchen.close()

    def _observation(self, observation: dict) -> dict[str, np.ndarray]:
        return state_observation(observation["observation"][self.state_indices])
