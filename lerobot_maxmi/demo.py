"""`make demo`: the whole MaxMI job on a small PickCube set, through the real command-line tools.

    scripted demos -> lerobot-maxmi-discover (MaxMI key states) -> lerobot-train cotpc_maxmi
    -> lerobot-eval on ManiSkill -> a printed summary

Everything is written under `--output_dir` (default `outputs/demo`); the demos are reused when
they are already there, the later stages start over. Scale any stage up from the command line,
e.g. `python -m lerobot_maxmi.demo --num_episodes=200 --train_steps=20000`.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import draccus

from lerobot_maxmi.discovery.quality import dataset_quality, evaluate_selectors, markdown_table
from lerobot_maxmi.discovery.selectors import AWEConfig
from lerobot_maxmi.discovery.train import DiscoveryConfig
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column

KEY_FRAMES = "maxmi/key_frames"
BASELINES = ["uniform", "awe", "last_state"]


@dataclass
class DemoConfig:
    task: str = "PickCube-v1"
    output_dir: Path = Path("outputs/demo")
    num_episodes: int = 60
    discovery_steps: int = 300
    num_concepts: int = 4
    train_steps: int = 1000
    batch_size: int = 64
    context_length: int = 10
    eval_episodes: int = 20
    seed: int = 0


def run_tool(name: str, *args: str) -> None:
    """Run one of the installed console scripts (ours or LeRobot's) from this environment."""
    command = [str(Path(sys.executable).parent / name), *args]
    print(f"\n$ {' '.join(command[:1] + [a for a in args])}", flush=True)
    subprocess.run(command, check=True)


def timed(timings: dict[str, float], stage: str, work) -> None:
    start = time.perf_counter()
    work()
    timings[stage] = time.perf_counter() - start


def record_demos(cfg: DemoConfig, root: Path) -> None:
    run_tool(
        "lerobot-maxmi-demos",
        "--env.type=maniskill",
        f"--env.task={cfg.task}",
        f"--num_episodes={cfg.num_episodes}",
        f"--repo_id=local/demo_{cfg.task}",
        f"--root={root}",
        f"--seed={cfg.seed}",
        f"--resume={str(root.exists()).lower()}",
    )


def discover(cfg: DemoConfig, source: Path, annotated: Path) -> None:
    run_tool(
        "lerobot-maxmi-discover",
        f"--dataset.repo_id=local/demo_{cfg.task}",
        f"--dataset.root={source}",
        f"--output.repo_id=local/demo_{cfg.task}_maxmi",
        f"--output.root={annotated}",
        f"--discovery.num_concepts={cfg.num_concepts}",
        f"--discovery.steps={cfg.discovery_steps}",
        f"--discovery.seed={cfg.seed}",
        "--overwrite=true",
    )


def train(cfg: DemoConfig, annotated: Path, run_dir: Path) -> None:
    shutil.rmtree(run_dir, ignore_errors=True)  # lerobot-train refuses an existing run directory
    run_tool(
        "lerobot-train",
        "--policy.type=cotpc_maxmi",
        f"--policy.context_length={cfg.context_length}",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        f"--dataset.repo_id=local/demo_{cfg.task}_maxmi",
        f"--dataset.root={annotated}",
        f"--steps={cfg.train_steps}",
        f"--batch_size={cfg.batch_size}",
        f"--num_workers={min(4, os.cpu_count() or 1)}",  # LeRobot's default 4 oversubscribes small machines
        f"--save_freq={cfg.train_steps}",
        f"--log_freq={max(cfg.train_steps // 10, 1)}",
        f"--seed={cfg.seed}",
        f"--output_dir={run_dir}",
    )


def evaluate(cfg: DemoConfig, run_dir: Path, eval_dir: Path) -> None:
    shutil.rmtree(eval_dir, ignore_errors=True)
    run_tool(
        "lerobot-eval",
        f"--policy.path={run_dir / 'checkpoints' / 'last' / 'pretrained_model'}",
        "--policy.device=cpu",
        "--env.type=maniskill",
        f"--env.task={cfg.task}",
        f"--eval.n_episodes={cfg.eval_episodes}",
        "--eval.batch_size=1",
        f"--seed={cfg.seed + 10_000}",  # initial configurations the demos never used
        f"--output_dir={eval_dir}",
    )


def key_state_table(source: Path, annotated: Path, num_concepts: int) -> str:
    """MaxMI's key frames (as written by the annotator) beside cheap baselines, against ground truth."""
    truth = read_episode_column(annotated, GT_KEY_FRAMES)
    found = read_episode_column(annotated, KEY_FRAMES)
    lengths = {i: frames[-1] + 1 for i, frames in truth.items()}  # gt ends with the final frame
    episodes = sorted(truth)
    results = {
        "maxmi": dataset_quality(
            [found[i] for i in episodes], [truth[i] for i in episodes], [lengths[i] for i in episodes]
        )
        | {"key_frames_per_episode": sum(len(found[i]) for i in episodes) / len(episodes)}
    }
    same_budget = DiscoveryConfig(num_concepts=num_concepts)  # uniform picks as many frames as MaxMI may
    baselines = evaluate_selectors(source, "observation.state", BASELINES, same_budget, AWEConfig())
    return markdown_table(results | baselines)


def eval_summary(eval_dir: Path) -> str:
    overall = json.loads((eval_dir / "eval_info.json").read_text())["overall"]
    rates = {"success": overall["pc_success"], **overall.get("pc_milestones", {})}
    return "\n".join(f"| {name} | {rate:.0f}% |" for name, rate in rates.items())


@draccus.wrap()
def main(cfg: DemoConfig) -> None:
    out = cfg.output_dir
    source, annotated = out / "demos", out / "demos_maxmi"
    run_dir, eval_dir = out / "train", out / "eval"
    timings: dict[str, float] = {}
    timed(timings, "demos", lambda: record_demos(cfg, source))
    timed(timings, "discovery", lambda: discover(cfg, source, annotated))
    timed(timings, "training", lambda: train(cfg, annotated, run_dir))
    timed(timings, "evaluation", lambda: evaluate(cfg, run_dir, eval_dir))
    summary = "\n\n".join(
        [
            f"# MaxMI demo: {cfg.task}, {cfg.num_episodes} scripted demos",
            "## Key frames vs ground truth (final frame excluded)\n\n"
            + key_state_table(source, annotated, cfg.num_concepts),
            f"## cotpc_maxmi after {cfg.train_steps} steps, {cfg.eval_episodes} unseen episodes\n\n"
            f"| rate | value |\n|---|---|\n{eval_summary(eval_dir)}",
            "## Wall time\n\n| stage | seconds |\n|---|---|\n"
            + "\n".join(f"| {stage} | {seconds:.0f} |" for stage, seconds in timings.items()),
        ]
    )
    (out / "summary.md").write_text(summary + "\n")
    print(f"\n{summary}\n\n(written to {out / 'summary.md'})")


if __name__ == "__main__":
    main()
