"""A ManiSkill task as one LeRobot evaluation sub-env (the `maniskill` env type builds these)."""

import gymnasium as gym
import numpy as np

from lerobot_maxmi.envs.maniskill_sim import (
    make_sim_env,
    restrict_faucet_models,
    subgoal_flags,
    task_spec,
)
from lerobot_maxmi.envs.milestones import MILESTONES_KEY
from lerobot_maxmi.envs.observation import state_observation, state_observation_space


class ManiSkillGymEnv(gym.Env):
    """One CPU ManiSkill env with the observation and info LeRobot's evaluation reads.

    Observation: the state (see `envs.observation`); info `is_success` and, under "milestones", the
    task's sub-goal flags at this step. Renders RGB frames where a Vulkan device exists; without
    one the simulation is physics-only and `render_mode` is None.
    """

    def __init__(
        self,
        task: str,
        control_mode: str = "pd_ee_delta_pose",
        obs_mode: str = "state",
        max_episode_steps: int | None = None,
        fps: int = 20,
        model_ids: list[str] | None = None,
    ):
        super().__init__()
        spec = task_spec(task)
        # make_sim_env drops the render mode where there is no Vulkan device.
        self._sim = make_sim_env(task, control_mode, obs_mode, max_episode_steps, "rgb_array")
        if model_ids is not None:
            restrict_faucet_models(self._sim, model_ids)
        self.task = task
        self.task_description = spec.description
        self.render_mode = self._sim.render_mode
        self._max_episode_steps = max_episode_steps or spec.episode_length
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": fps}
        self.action_space = self._sim.action_space
        self.observation_space = state_observation_space(self._sim.observation_space.shape)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        # `options` carries LeRobot's rollout markers, which mean nothing to ManiSkill.
        super().reset(seed=seed)
        state, _ = self._sim.reset(seed=seed)
        return state_observation(state), {"is_success": False}

    def step(self, action: np.ndarray):
        state, reward, terminated, truncated, sim_info = self._sim.step(action)
        flags = subgoal_flags(self._sim, sim_info)
        info = {"is_success": flags["success"], MILESTONES_KEY: flags}
        return state_observation(state), float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        return self._sim.render() if self.render_mode is not None else None

    def close(self) -> None:
        self._sim.close()
