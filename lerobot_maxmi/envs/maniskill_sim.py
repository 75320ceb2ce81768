"""ManiSkill 3 simulation shared by the env wrapper and the demo generator.

Three things live here: the task table (default episode length, the sub-goals the paper reports),
making a single-env CPU simulation that also works on machines without a Vulkan device, and
reading the sub-goal flags from the simulator's state.
"""

import functools
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TaskSpec:
    episode_length: int  # long enough for human/scripted demos; ManiSkill's own limits are shorter
    state_dim: int | None  # obs_mode="state"; None where it was never measured (assets unavailable)
    subgoals: tuple[str, ...]  # in the order they happen; "success" is always the last one
    description: str  # the language instruction policies receive as the task
    needs_downloaded_assets: bool = False


TASKS: dict[str, TaskSpec] = {
    "PickCube-v1": TaskSpec(100, 42, ("grasp", "success"), "Pick up the cube and move it to the goal."),
    "StackCube-v1": TaskSpec(
        150, 48, ("grasp", "a_on_b", "success"), "Pick up the red cube and stack it on the green cube."
    ),
    "PegInsertionSide-v1": TaskSpec(
        250, 43, ("grasp", "align", "success"), "Pick up the peg and insert it sideways into the hole."
    ),
    "TurnFaucet-v1": TaskSpec(
        250, None, ("success",), "Turn the faucet handle.", needs_downloaded_assets=True
    ),
}

FAUCET_TASK = "TurnFaucet-v1"

# Panda action sizes per controller (arm command + 1 gripper dimension).
ACTION_DIMS: dict[str, int] = {
    "pd_ee_delta_pose": 7,
    "pd_ee_delta_pos": 4,
    "pd_joint_delta_pos": 8,
    "pd_joint_pos": 8,
}

# Peg head and centre within this distance of the hole axis counts as aligned: ManiSkill's
# dense reward for PegInsertionSide uses the same test for its "pre-inserted" stage.
PEG_ALIGN_TOLERANCE = 0.01


def task_spec(task: str) -> TaskSpec:
    if task not in TASKS:
        raise ValueError(f"Unknown ManiSkill task {task!r}. Supported tasks: {', '.join(TASKS)}.")
    return TASKS[task]


@functools.cache
def has_render_device() -> bool:
    """Whether SAPIEN can open a Vulkan device (a GPU, or a software driver such as lavapipe)."""
    import sapien

    try:
        sapien.render.RenderMaterial()
    except RuntimeError:
        return False
    return True


class _InertRenderMaterial:
    """Stands in for sapien.render.RenderMaterial, which needs a device even when nothing renders."""

    def __init__(self, *args, **kwargs):
        pass

    def __getattr__(self, name):
        return lambda *args, **kwargs: None


# Modules that bind RenderMaterial at import time; each needs the stand-in.
_MODULES_HOLDING_RENDER_MATERIAL = (
    "sapien.render",
    "sapien.pysapien.render",
    "sapien.wrapper.renderer",
    "sapien.wrapper.urdf_loader",
    "mani_skill.utils.building._mjcf_loader",
)


@functools.cache
def use_physics_only_backend() -> None:
    """Let ManiSkill build scenes with no Vulkan device: physics is unchanged, nothing renders.

    ManiSkill already skips cameras, lights and visual shapes when render_backend="none"; only
    the material constructor still asks for a device, so it is replaced by an inert object.
    """
    import importlib

    for module in _MODULES_HOLDING_RENDER_MATERIAL:
        importlib.import_module(module).RenderMaterial = _InertRenderMaterial
    logger.warning("No Vulkan device found: ManiSkill runs physics-only (state observations, no rendering).")


def missing_assets(task: str) -> list[Path]:
    """Asset folders the task needs that are not on disk (only TurnFaucet downloads any)."""
    if not task_spec(task).needs_downloaded_assets:
        return []
    from mani_skill.utils import assets

    missing = []
    for source_id in assets.expand_data_group_into_individual_data_source_ids("partnet_mobility_faucet"):
        if not assets.is_data_source_downloaded(source_id):
            source = assets.DATA_SOURCES[source_id]
            missing.append(Path(source.output_dir) / source.target_path)
    return missing


def require_assets(task: str) -> None:
    missing = missing_assets(task)
    if missing:
        from mani_skill import ASSET_DIR

        raise FileNotFoundError(
            f"{task} needs PartNet-Mobility faucet models that are not on disk: {len(missing)} missing, "
            f"e.g. {missing[0]}. Download them with `python -m mani_skill.utils.download_asset "
            f"partnet_mobility_faucet` on a machine with network access, or point MS_ASSET_DIR at a "
            f"folder that already holds them (searched: {ASSET_DIR})."
        )


def restrict_faucet_models(env, model_ids: list[str]) -> None:
    """Make TurnFaucet sample its faucet from `model_ids` only (e.g. held-out faucets, zero-shot).

    TurnFaucetEnv draws a model from `all_model_ids` whenever it rebuilds its scene, which a single
    CPU env does on every reset; the scene built at construction is replaced by the first reset.
    """
    base = env.unwrapped
    unknown = sorted(set(model_ids) - set(base.train_info))
    if unknown:
        raise ValueError(
            f"Unknown {FAUCET_TASK} model ids {unknown}: choose from the {len(base.train_info)} ids in "
            f"{base.TRAIN_JSON}."
        )
    base.all_model_ids = np.array(model_ids)


def make_sim_env(
    task: str,
    control_mode: str = "pd_ee_delta_pose",
    obs_mode: str = "state",
    max_episode_steps: int | None = None,
    render_mode: str | None = None,
    **env_kwargs,
):
    """One CPU ManiSkill env with numpy, unbatched outputs (ManiSkill's CPUGymWrapper).

    Without a Vulkan device the scene is built physics-only and `render_mode` is dropped.
    """
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the tasks with gymnasium)
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    spec = task_spec(task)
    require_assets(task)
    if not has_render_device():
        use_physics_only_backend()
        env_kwargs["render_backend"] = "none"
        render_mode = None
    env = gym.make(
        task,
        obs_mode=obs_mode,
        control_mode=control_mode,
        sim_backend="physx_cpu",
        render_mode=render_mode,
        max_episode_steps=max_episode_steps or spec.episode_length,
        **env_kwargs,
    )
    return CPUGymWrapper(env)


def subgoal_flags(env, info: dict) -> dict[str, bool]:
    """The task's sub-goals at the current step, read from the simulator (privileged state)."""
    base = env.unwrapped
    task = base.spec.id
    success = _as_bool(info["success"])
    if task == "PickCube-v1":
        return {"grasp": _as_bool(info["is_grasped"]), "success": success}
    if task == "StackCube-v1":
        return {
            "grasp": _as_bool(info["is_cubeA_grasped"]),
            "a_on_b": _as_bool(info["is_cubeA_on_cubeB"]),
            "success": success,
        }
    if task == "PegInsertionSide-v1":
        return {
            "grasp": _as_bool(base.agent.is_grasping(base.peg, max_angle=20)),
            "align": _peg_aligned(base),
            "success": success,
        }
    return {"success": success}


def _peg_aligned(base) -> bool:
    import torch

    to_hole = base.goal_pose.inv()
    head_offset = (to_hole * base.peg_head_pose).p[:, 1:]
    centre_offset = (to_hole * base.peg.pose).p[:, 1:]
    aligned = (torch.linalg.norm(head_offset, dim=1) < PEG_ALIGN_TOLERANCE) & (
        torch.linalg.norm(centre_offset, dim=1) < PEG_ALIGN_TOLERANCE
    )
    return _as_bool(aligned)


def _as_bool(value) -> bool:
    return bool(np.asarray(value.cpu() if hasattr(value, "cpu") else value).reshape(-1)[0])
