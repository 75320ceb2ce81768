"""Running an expert for one episode, its ground-truth key frames, and open-loop replay.

Frame and key-frame conventions are in `episode.py`. An episode ends at the first frame whose
observation is a success state, reached after every sub-goal has held; that frame gets the expert's
next action, so the success state itself is in the data. It is the "final" key frame, so the last
sub-goal ("success", e.g. the inserted peg) is not listed separately: it would coincide with it.
"""

from dataclasses import dataclass, field

import numpy as np

from lerobot_maxmi.demos.episode import FINAL, Episode
from lerobot_maxmi.demos.experts import ExpertParams, ScriptedExpert, make_expert
from lerobot_maxmi.envs.maniskill_sim import make_sim_env, subgoal_flags, task_spec


@dataclass
class Attempt:
    """One seed's outcome: an episode worth keeping, or why there is none."""

    seed: int
    length: int
    episode: Episode | None = None
    failure: str | None = None


def key_frame_names(task: str) -> list[str]:
    return [name for name in task_spec(task).subgoals if name != "success"] + [FINAL]


@dataclass
class FirstFrames:
    """First frame index at which each sub-goal holds."""

    names: list[str]
    first: dict[str, int] = field(default_factory=dict)

    def update(self, frame: int, flags: dict[str, bool]) -> None:
        for name in self.names:
            if flags.get(name) and name not in self.first:
                self.first[name] = frame

    def all_held(self) -> bool:
        return len(self.first) == len(self.names)

    def key_frames(self, last_frame: int) -> tuple[list[int] | None, str | None]:
        """Key frames (sub-goals, then the final frame) once all_held(), or None and why they are unusable."""
        frames = [self.first[name] for name in self.names] + [last_frame]
        if frames != sorted(frames):
            return None, f"sub-goals out of order: {dict(zip([*self.names, FINAL], frames, strict=True))}"
        return frames, None


def run_expert(
    env,
    expert: ScriptedExpert,
    seed: int,
    max_steps: int,
    action_noise: float = 0.0,
    randomize_expert: bool = False,
) -> Attempt:
    """Roll the expert out from `env.reset(seed=seed)` until the first success frame or `max_steps`.

    Noise and expert parameters are drawn from a generator seeded by `seed`, so the attempt is a pure
    function of the seed (whichever process runs it).
    """
    rng = np.random.default_rng(seed)
    obs = reset_env(env, seed)
    expert.reset(env, ExpertParams.randomized(rng) if randomize_expert else ExpertParams())
    task = env.unwrapped.spec.id
    subgoals = FirstFrames(key_frame_names(task)[:-1])
    states, actions, successes = [], [], []
    reached_success = False
    for step in range(max_steps + 1):  # + 1: the success frame's own action
        action = _perturb(expert.act(env), action_noise, rng)
        states.append(np.asarray(obs, dtype=np.float32))
        actions.append(action)
        obs, _, _, _, info = env.step(action)
        flags = subgoal_flags(env, info)
        successes.append(flags["success"])
        if reached_success:
            break
        subgoals.update(step + 1, flags)
        # Success counts once every sub-goal has held: a PickCube goal can start inside the cube.
        reached_success = flags["success"] and subgoals.all_held()
        if step + 1 == max_steps and not reached_success:
            break
    length = len(actions)
    if not reached_success:
        return Attempt(seed, length, failure=f"no success within {max_steps} steps")
    key_frames, reason = subgoals.key_frames(last_frame=length - 1)
    if key_frames is None:
        return Attempt(seed, length, failure=reason)
    episode = Episode(
        states=np.stack(states),
        actions=np.stack(actions),
        successes=np.array(successes, dtype=bool),
        key_frames=key_frames,
        key_frame_names=key_frame_names(task),
        seed=seed,
    )
    return Attempt(seed, length, episode=episode)


# State entries that ManiSkill derives from contacts: at reset they still describe the previous
# episode's last physics step (PickCube's `is_grasped`, after qpos 9 + qvel 9). Nothing is grasped at
# reset (open gripper, away from the cube), so they are zeroed to make episodes history-independent.
CONTACT_STATE_INDICES: dict[str, tuple[int, ...]] = {"PickCube-v1": (18,)}


def reset_env(env, seed: int) -> np.ndarray:
    """`env.reset(seed=seed)`'s observation, independent of what the env ran before."""
    obs, _ = env.reset(seed=seed)
    obs = np.array(obs, dtype=np.float32)
    obs[list(CONTACT_STATE_INDICES.get(env.unwrapped.spec.id, ()))] = 0.0
    return obs


def _perturb(action: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise on the arm dimensions (not the gripper), clipped to the action box, as float32.

    The float32 cast happens before stepping, so the dataset holds exactly the executed actions.
    """
    if noise > 0:
        action = action.copy()
        action[:-1] += rng.normal(0.0, noise, size=action.shape[0] - 1)
    return np.clip(action, -1.0, 1.0).astype(np.float32)


def replay(env, seed: int, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop replay of recorded actions from `env.reset(seed=seed)`: (states, success flags).

    Bit-exact when `env` has the recording's history (e.g. fresh env, first episode); otherwise PhysX's
    contact caches carried across resets cause float-level differences (success still reproduced).

    States are the observations before each action, aligned with a recorded episode's frames.
    """
    obs = reset_env(env, seed)
    states, successes = [], []
    for action in actions:
        states.append(np.asarray(obs, dtype=np.float32))
        obs, _, _, _, info = env.step(action)
        successes.append(bool(np.asarray(info["success"]).reshape(-1)[0]))
    return np.stack(states), np.array(successes, dtype=bool)


class ManiSkillDemoSource:
    """Expert attempts for one ManiSkill task, one seed at a time; the env is built on first use."""

    robot_type = "panda"

    def __init__(self, env_cfg, action_noise: float = 0.0, randomize_expert: bool = True):
        self.task, self.control_mode = env_cfg.task, env_cfg.control_mode
        self.fps, self.max_steps = env_cfg.fps, env_cfg.episode_length
        self.action_noise, self.randomize_expert = action_noise, randomize_expert
        self.expert = make_expert(self.task, self.control_mode)  # fails early for tasks without one
        self.env = None

    def attempt(self, seed: int) -> Attempt:
        if self.env is None:
            # One step past the limit: the success frame's own action may come after it.
            self.env = make_sim_env(self.task, self.control_mode, max_episode_steps=self.max_steps + 1)
        return run_expert(
            self.env, self.expert, seed, self.max_steps, self.action_noise, self.randomize_expert
        )
