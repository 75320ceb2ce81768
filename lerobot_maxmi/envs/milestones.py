"""Sub-task ("milestone") success rates for evaluation.

lerobot-eval only counts `is_success`. The paper also reports how often each sub-task was reached
(ManiSkill: grasp, align, ...; Franka Kitchen: "at least k tasks completed"). The contract:

* a sub-env reports its milestones at every step as `info["milestones"] = {name: bool | number}`;
* `RecordMilestones` remembers, per episode, which milestones were reached at any step (numbers,
  e.g. Franka Kitchen's count of completed tasks: their largest value);
* after evaluation the per-episode records are collected (`collect_episode_milestones`) and turned
  into percentages of episodes, or means for numbers (`add_milestone_rates`); `eval_hooks` does
  both inside lerobot-eval.

An env type only has to emit the info key and build its vector env with `make_vector_env`.
"""

from collections import defaultdict
from collections.abc import Callable, Sequence
from functools import partial

import gymnasium as gym
import numpy as np
from lerobot.envs.utils import FreezeAfterEpisodeEnd

MILESTONES_KEY = "milestones"
RATES_KEY = "pc_milestones"  # next to LeRobot's "pc_success"


class RecordMilestones(gym.Wrapper):
    """Records, for each episode since the last collection, the milestones reached at any step.

    One record starts at every reset that reaches this wrapper. Placed under FreezeAfterEpisodeEnd,
    that is one record per rollout: a finished sub-env neither steps nor autoresets until the next
    rollout resets it.
    """

    def __init__(self, env: gym.Env, milestones: Sequence[str]):
        super().__init__(env)
        self.milestones = tuple(milestones)
        # The vector env copies the sub-env's metadata: this is how the eval hooks recognise it.
        self.metadata = {**env.metadata, MILESTONES_KEY: self.milestones}
        self._episodes: list[dict[str, bool]] = []

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        self._episodes.append(dict.fromkeys(self.milestones, False))
        return observation, info

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        episode = self._episodes[-1]
        for name, value in info[MILESTONES_KEY].items():
            # The new value first: max keeps the first of equals, so a count staying 0 stays a number.
            episode[name] = max(_as_milestone(value), episode[name])
        return observation, reward, terminated, truncated, info

    def pop_episode_milestones(self) -> list[dict[str, bool]]:
        episodes, self._episodes = self._episodes, []
        return episodes


def _as_milestone(value) -> bool | float:
    """Flags stay bool (and become percentages); numbers become float (and are averaged)."""
    return bool(value) if isinstance(value, bool | np.bool_) else float(value)


def _make_recorded_env(make_env: Callable[[], gym.Env], milestones: tuple[str, ...]) -> gym.Env:
    return FreezeAfterEpisodeEnd(RecordMilestones(make_env(), milestones))


def make_vector_env(
    make_env: Callable[[], gym.Env], milestones: Sequence[str], n_envs: int, use_async_envs: bool
) -> gym.vector.VectorEnv:
    """`n_envs` copies of `make_env()` in LeRobot's vector env setup (SAME_STEP autoreset)."""
    env_fns = [partial(_make_recorded_env, make_env, tuple(milestones))] * n_envs
    autoreset = gym.vector.AutoresetMode.SAME_STEP
    if use_async_envs and n_envs > 1:
        return gym.vector.AsyncVectorEnv(env_fns, context="forkserver", autoreset_mode=autoreset)
    return gym.vector.SyncVectorEnv(env_fns, autoreset_mode=autoreset)


def collect_episode_milestones(env: gym.vector.VectorEnv, n_episodes: int) -> list[dict[str, bool]]:
    """The first `n_episodes` records, in the order LeRobot numbers its episodes."""
    return episodes_in_eval_order(env.call("pop_episode_milestones"), n_episodes)


def episodes_in_eval_order(per_env: Sequence[list[dict]], n_episodes: int) -> list[dict]:
    """Interleave per-sub-env records: rollout b on sub-env e is LeRobot's episode b * n_envs + e.

    LeRobot runs whole batches and drops the surplus episodes of the last one, so do we.
    """
    by_rollout = zip(*per_env, strict=True)
    return [episode for rollout in by_rollout for episode in rollout][:n_episodes]


def milestone_rates(episodes: Sequence[dict[str, bool | float]]) -> dict[str, float]:
    """Percentage of episodes in which each flag was reached, and the mean of numeric milestones
    (names in first-seen order)."""
    names = list(dict.fromkeys(name for episode in episodes for name in episode))
    rates = {}
    for name in names:
        values = [episode[name] for episode in episodes if name in episode]
        is_flag = all(isinstance(value, bool) for value in values)
        rates[name] = float(np.mean(values) * (100 if is_flag else 1))
    return rates


def add_milestone_rates(eval_info: dict) -> dict:
    """Add milestone rates to the per-group and overall sections of `eval_policy_all`'s result.

    Reads the per-episode records that the hooks stored in each task's metrics; tasks without
    records (other env types) are left out, and sections with none are left untouched.
    """
    by_group: dict[str, list[dict[str, bool]]] = defaultdict(list)
    for task in eval_info["per_task"]:
        by_group[task["task_group"]].extend(task["metrics"].get(MILESTONES_KEY, []))
    for group, episodes in by_group.items():
        if episodes:
            eval_info["per_group"][group][RATES_KEY] = milestone_rates(episodes)
    all_episodes = [episode for episodes in by_group.values() for episode in episodes]
    if all_episodes:
        eval_info["overall"][RATES_KEY] = milestone_rates(all_episodes)
    return eval_info
