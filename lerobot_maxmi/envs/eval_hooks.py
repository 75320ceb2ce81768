"""Two small wraps that put milestone rates into lerobot-eval's output (LeRobot 0.6.x only).

LeRobot's evaluation keeps nothing from `info` but `is_success`, and it renders up to 10 episodes
whether or not the env can render. Our env types record milestones themselves (`milestones.py`);
these wraps only carry the records through and skip videos for envs without a renderer:

* `eval_one` (runs one task on one vector env, which is closed right after): collect the sub-envs'
  per-episode records into the task's metrics, and render nothing when the env has no renderer.
* `eval_policy_all` (aggregates all tasks): add `pc_milestones` to "per_group" and "overall",
  which eval_main prints and writes to eval_info.json.

Both leave env types that record no milestones untouched (they carry no `milestones` metadata).
They are installed when one of our env types creates its envs, which lerobot-eval and
lerobot-train do before evaluating; both functions are looked up by module global at call time.
"""

import functools
import inspect
import logging
import sys

import lerobot

from lerobot_maxmi.envs.milestones import MILESTONES_KEY, add_milestone_rates, collect_episode_milestones

logger = logging.getLogger(__name__)

SUPPORTED_LEROBOT = "0.6."
_EVAL_ONE_PARAMETERS = {"env", "n_episodes", "max_episodes_rendered"}
_INSTALLED = "_lerobot_maxmi_milestones"  # marks our wraps so installing twice is a no-op


def install_eval_hooks() -> None:
    from lerobot.scripts import lerobot_eval

    if getattr(lerobot_eval.eval_one, _INSTALLED, False):
        return
    if not _is_supported(lerobot_eval):
        logger.warning(
            "lerobot %s is not supported by lerobot_maxmi's evaluation hooks (needs %sx): lerobot-eval "
            "will report final success only, without sub-task (milestone) rates.",
            lerobot.__version__,
            SUPPORTED_LEROBOT,
        )
        return
    lerobot_eval.eval_one = _collecting_milestones(lerobot_eval.eval_one)
    aggregate = _adding_milestone_rates(lerobot_eval.eval_policy_all)
    lerobot_eval.eval_policy_all = aggregate
    # lerobot-train imported eval_policy_all by name for its in-training evaluation.
    lerobot_train = sys.modules.get("lerobot.scripts.lerobot_train")
    if lerobot_train is not None:
        lerobot_train.eval_policy_all = aggregate


def _is_supported(lerobot_eval) -> bool:
    parameters = set(inspect.signature(lerobot_eval.eval_one).parameters)
    return lerobot.__version__.startswith(SUPPORTED_LEROBOT) and _EVAL_ONE_PARAMETERS.issubset(parameters)


def _collecting_milestones(eval_one):
    @functools.wraps(eval_one)
    def wrapper(env, **kwargs):
        if MILESTONES_KEY not in env.metadata:
            return eval_one(env, **kwargs)
        if kwargs["max_episodes_rendered"] > 0 and env.render_mode is None:
            logger.warning("No renderer (physics-only simulation): evaluation videos are skipped.")
            kwargs["max_episodes_rendered"] = 0
        metrics = eval_one(env, **kwargs)
        metrics[MILESTONES_KEY] = collect_episode_milestones(env, kwargs["n_episodes"])
        return metrics

    setattr(wrapper, _INSTALLED, True)
    return wrapper


def _adding_milestone_rates(eval_policy_all):
    @functools.wraps(eval_policy_all)
    def wrapper(*args, **kwargs):
        return add_milestone_rates(eval_policy_all(*args, **kwargs))

    setattr(wrapper, _INSTALLED, True)
    return wrapper
