"""The main job's stages through the real command-line tools, shared by `make demo` and the benchmarks.

    lerobot-maxmi-demos -> lerobot-maxmi-discover -> lerobot-train -> lerobot-eval

Each stage is one console script run in a subprocess from this environment, exactly as a user would
type it, so what the demo and the result tables measure is what users get.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lerobot_maxmi.demos.dataset_writer import copy_with_environment_state
from lerobot_maxmi.envs.configs import KITCHEN_TASK


def timed(timings: dict[str, float], stage: str, work: Callable, *args, **kwargs):
    """work(*args, **kwargs), with its wall time in seconds stored as timings[stage]."""
    start = time.perf_counter()
    value = work(*args, **kwargs)
    timings[stage] = round(time.perf_counter() - start, 1)
    return value


def run_tool(name: str, *args: str) -> None:
    """Run one of the installed console scripts (ours or LeRobot's), failing loudly if it fails."""
    command = [str(Path(sys.executable).parent / name), *args]
    print(f"\n$ {name} {' '.join(args)}", flush=True)
    subprocess.run(command, check=True)


def env_flags(task: str) -> tuple[str, ...]:
    """The flags selecting `task`'s env: Franka Kitchen, or else a ManiSkill task."""
    env_type = "franka_kitchen" if task == KITCHEN_TASK else "maniskill"
    return (f"--env.type={env_type}", f"--env.task={task}")


FILE_PER_EPISODE_MB = 0.001  # under one episode's size: LeRobot starts a new parquet file for each


@dataclass(frozen=True)
class Loader:
    """How lerobot-train reads a dataset, and how demos are laid out for it."""

    demo_flags: tuple[str, ...] = ()
    train_flags: tuple[str, ...] = ()


# "map": lerobot-train's default; random access, each sample's windows converted row by row.
# "streaming": in file order through a shuffle buffer, ~30x cheaper a sample, but W loader workers all
# get files only from at least W x W parquet files, so its demos get a file per episode.
# docs/RESULTS.md, "CoTPC's data path through LeRobot".
LOADERS = {
    "map": Loader(),
    "streaming": Loader((f"--data_files_size_in_mb={FILE_PER_EPISODE_MB}",), ("--dataset.streaming=true",)),
}


def record_demos(task: str, num_episodes: int, root: Path, seed: int = 0, loader: str = "map") -> None:
    """Scripted demos of `task` at `root`, topped up (never duplicated) when some are already there;
    laid out for `loader` (one of LOADERS)."""
    run_tool(
        "lerobot-maxmi-demos",
        *env_flags(task),
        f"--num_episodes={num_episodes}",
        f"--repo_id=local/{root.name}",
        f"--root={root}",
        f"--seed={seed}",
        f"--resume={str(root.exists()).lower()}",
        *LOADERS[loader].demo_flags,
    )


def annotate(source: Path, output: Path, selector: str, *discovery_flags: str) -> None:
    """Key states from `selector` written into a new dataset at `output` (replacing an old one)."""
    run_tool(
        "lerobot-maxmi-discover",
        f"--dataset.repo_id=local/{source.name}",
        f"--dataset.root={source}",
        f"--output.repo_id=local/{output.name}",
        f"--output.root={output}",
        f"--selector={selector}",
        *discovery_flags,
        "--overwrite=true",
    )


def train_policy(
    policy_flags: tuple[str, ...],
    dataset: Path,
    run_dir: Path,
    steps: int,
    batch_size: int,
    device: str,
    seed: int,
    loader: str = "map",
) -> Path:
    """Train with lerobot-train (`policy_flags`: --policy.type and its options) reading `dataset` with
    `loader` (one of LOADERS); returns the last checkpoint's pretrained_model directory."""
    shutil.rmtree(run_dir, ignore_errors=True)  # lerobot-train refuses an existing run directory
    run_tool(
        "lerobot-train",
        *policy_flags,
        f"--policy.device={device}",
        "--policy.push_to_hub=false",
        f"--dataset.repo_id=local/{dataset.name}",
        f"--dataset.root={dataset}",
        f"--steps={steps}",
        f"--batch_size={batch_size}",
        f"--save_freq={steps}",
        f"--log_freq={max(steps // 10, 1)}",
        f"--seed={seed}",
        f"--num_workers={min(4, os.cpu_count() or 1)}",  # LeRobot's default 4 oversubscribes small machines
        f"--output_dir={run_dir}",
        *LOADERS[loader].train_flags,
    )
    return run_dir / "checkpoints" / "last" / "pretrained_model"


def cotpc_flags(policy_type: str, context_length: int) -> tuple[str, ...]:
    return (f"--policy.type={policy_type}", f"--policy.context_length={context_length}")


def environment_state_copy(demos: Path, output: Path) -> None:
    """The demos with their state also as `observation.environment_state` (for ACT / Diffusion)."""
    shutil.rmtree(output, ignore_errors=True)
    copy_with_environment_state(demos, output, f"local/{output.name}")


def evaluate_policy(
    checkpoint: Path, task: str, eval_dir: Path, num_episodes: int, seed: int, device: str
) -> dict:
    """lerobot-eval on `task`, one env at a time from episode seed `seed` on; its overall metrics."""
    shutil.rmtree(eval_dir, ignore_errors=True)
    run_tool(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        f"--policy.device={device}",
        *env_flags(task),
        f"--eval.n_episodes={num_episodes}",
        "--eval.batch_size=1",
        f"--seed={seed}",
        f"--output_dir={eval_dir}",
    )
    return json.loads((eval_dir / "eval_info.json").read_text())["overall"]


def rates(overall: dict) -> dict[str, float]:
    """Success and sub-task rates (%) from lerobot-eval's overall metrics; success is LeRobot's own."""
    milestones = overall.get("pc_milestones", {})
    return {"success": overall["pc_success"], **{k: v for k, v in milestones.items() if k != "success"}}
