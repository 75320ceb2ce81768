"""Franka Kitchen demonstrations for `lerobot-maxmi-demos --env.type=franka_kitchen`.

Like the relay-kitchen data, each attempt chains `TASKS_PER_DEMO` distinct subtasks in a random
order drawn from `--env.tasks_to_complete` (the expert does all 7). An attempt succeeds when
every subtask of its chain is complete within `DEMO_MAX_STEPS` (longer than the 280-step evaluation
limit: the expert is slower than a teleoperator). Key frames: the first frame at which each subtask
is complete, named after it, in completion order; the last subtask completes on the final frame,
which is the last key frame (conventions: `episode.py`).
"""

import numpy as np

from lerobot_maxmi.demos.episode import FINAL, Episode
from lerobot_maxmi.demos.kitchen_expert import MUST_PRECEDE, KitchenExpert
from lerobot_maxmi.demos.rollout import Attempt
from lerobot_maxmi.envs.kitchen import FrankaKitchenGymEnv, task_completed

TASKS_PER_DEMO = 4
DEMO_MAX_STEPS = 400


def demo_task(num_subtasks: int = TASKS_PER_DEMO) -> str:
    """The dataset's task string (also used for converted relay / D4RL data, which chain 4 subtasks)."""
    return f"complete {num_subtasks} kitchen subtasks"


class KitchenDemoSource:
    """Expert attempts on Franka Kitchen, one seed at a time; the env is built on first use."""

    robot_type = "franka"

    def __init__(self, env_cfg, action_noise: float = 0.0, randomize_expert: bool = True):
        self.env_cfg, self.fps = env_cfg, env_cfg.fps
        self.action_noise, self.randomize_expert = action_noise, randomize_expert
        self.repertoire = list(env_cfg.tasks_to_complete)
        self.chain_length = min(TASKS_PER_DEMO, len(self.repertoire))
        self.task = demo_task(self.chain_length)
        self.env = None

    def chain(self, rng: np.random.Generator) -> list[str]:
        """A random ordered chain of distinct subtasks, reordered where one blocks another."""
        chain = [str(task) for task in rng.permutation(self.repertoire)[: self.chain_length]]
        for first, then in MUST_PRECEDE:
            if first in chain and then in chain and chain.index(then) < chain.index(first):
                i, j = chain.index(then), chain.index(first)
                chain[i], chain[j] = chain[j], chain[i]
        return chain

    def attempt(self, seed: int) -> Attempt:
        if self.env is None:
            self.env = FrankaKitchenGymEnv(
                self.env_cfg.tasks_to_complete, DEMO_MAX_STEPS + 1, self.env_cfg.state_layout, render=False
            )
        return run_kitchen_expert(self.env, seed, self, DEMO_MAX_STEPS)


def run_kitchen_expert(env: FrankaKitchenGymEnv, seed: int, source: KitchenDemoSource, max_steps: int):
    """Roll the expert through `source.chain(rng)` from `env.reset(seed=seed)` (a pure function of seed)."""
    rng = np.random.default_rng(seed)
    chain = source.chain(rng)
    observation, _ = env.reset(seed=seed)
    kitchen = env.simulation
    expert = KitchenExpert(kitchen.model, kitchen.data.qpos.copy())
    expert.reset(chain, rng if source.randomize_expert else np.random.default_rng(0))
    states, actions, successes, completed_at = [], [], [], {}
    all_done = False
    for step in range(max_steps + 1):  # + 1: the final frame's own action
        action = _with_arm_noise(expert.act(kitchen.data), source.action_noise, rng)
        states.append(observation["agent_pos"])
        actions.append(action)
        observation, _, _, _, _ = env.step(action)
        if all_done:
            successes.append(True)
            break
        for task in chain:
            if task not in completed_at and task_completed(kitchen.data.qpos[:30], task):
                completed_at[task] = step + 1  # the first frame whose state shows it complete
        all_done = len(completed_at) == len(chain)
        successes.append(all_done)
        if step + 1 == max_steps and not all_done:
            break
    length = len(actions)
    if len(completed_at) < len(chain):
        missing = [task for task in chain if task not in completed_at]
        failure = f"{missing} not completed within {max_steps} steps (chain {chain})"
        return Attempt(seed, length, failure=failure)
    # The subtask completed last is the success state, i.e. the final frame, which stands for it
    # (as for the ManiSkill tasks' success sub-goal).
    order = [task for task in sorted(completed_at, key=completed_at.get) if completed_at[task] < length - 1]
    episode = Episode(
        states=np.stack(states),
        actions=np.stack(actions),
        successes=np.array(successes, dtype=bool),
        key_frames=[completed_at[task] for task in order] + [length - 1],
        key_frame_names=[*order, FINAL],
        seed=seed,
    )
    return Attempt(seed, length, episode=episode)


def _with_arm_noise(action: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise on the 7 arm joints (not the fingers), clipped, as the float32 that is executed."""
    if noise > 0:
        action = action.copy()
        action[:7] += rng.normal(0.0, noise, size=7)
    return np.clip(action, -1.0, 1.0).astype(np.float32)
