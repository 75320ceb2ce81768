"""`make demo`: the whole MaxMI job on a small PickCube set, through the real command-line tools.

    scripted demos -> lerobot-maxmi-discover (MaxMI key states) -> lerobot-train cotpc_maxmi
    -> lerobot-eval on ManiSkill -> a printed summary

Everything is written under `--output_dir` (default `outputs/demo`); the demos are reused when
they are already there, the later stages start over. Scale any stage up from the command line,
e.g. `python -m lerobot_maxmi.demo --num_episodes=200 --train_steps=20000`.
"""

from dataclasses import dataclass
from pathlib import Path

import draccus

from lerobot_maxmi.discovery.processor import KEY_FRAMES
from lerobot_maxmi.discovery.quality import dataset_quality, evaluate_selectors, markdown_table
from lerobot_maxmi.discovery.selectors import AWEConfig
from lerobot_maxmi.discovery.train import DiscoveryConfig
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column
from lerobot_maxmi.pipeline import (
    annotate,
    cotpc_flags,
    evaluate_policy,
    rates,
    record_demos,
    timed,
    train_policy,
)

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


def key_state_table(source: Path, annotated: Path, num_concepts: int) -> str:
    """MaxMI's key frames (as written by the annotator) beside cheap baselines, against ground truth."""
    truth = read_episode_column(annotated, GT_KEY_FRAMES)
    found = read_episode_column(annotated, KEY_FRAMES)
    episodes = sorted(truth)
    lengths = [truth[i][-1] + 1 for i in episodes]  # gt ends with the final frame
    maxmi = dataset_quality([found[i] for i in episodes], [truth[i] for i in episodes], lengths)
    same_budget = DiscoveryConfig(num_concepts=num_concepts)  # uniform picks as many frames as MaxMI may
    baselines = evaluate_selectors(source, "observation.state", BASELINES, same_budget, AWEConfig())
    return markdown_table({"maxmi": maxmi} | baselines)


def eval_summary(overall: dict) -> str:
    return "\n".join(f"| {name} | {rate:.0f}% |" for name, rate in rates(overall).items())


@draccus.wrap()
def main(cfg: DemoConfig) -> None:
    out = cfg.output_dir
    source, annotated = out / "demos", out / "demos_maxmi"
    run_dir, eval_dir = out / "train", out / "eval"
    timings: dict[str, float] = {}
    discovery_flags = [
        f"--discovery.num_concepts={cfg.num_concepts}",
        f"--discovery.steps={cfg.discovery_steps}",
        f"--discovery.seed={cfg.seed}",
    ]
    timed(timings, "demos", record_demos, cfg.task, cfg.num_episodes, source, cfg.seed)
    timed(timings, "discovery", annotate, source, annotated, "maxmi", *discovery_flags)
    policy = cotpc_flags("cotpc_maxmi", cfg.context_length)
    training = (cfg.train_steps, cfg.batch_size, "cpu", cfg.seed)
    checkpoint = timed(timings, "training", train_policy, policy, annotated, run_dir, *training)
    # Seeds from 10000 on: initial configurations the demos never used.
    unseen = (cfg.eval_episodes, cfg.seed + 10_000, "cpu")
    overall = timed(timings, "evaluation", evaluate_policy, checkpoint, cfg.task, eval_dir, *unseen)
    summary = "\n\n".join(
        [
            f"# MaxMI demo: {cfg.task}, {cfg.num_episodes} scripted demos",
            "## Key frames vs ground truth (final frame excluded)\n\n"
            + key_state_table(source, annotated, cfg.num_concepts),
            f"## cotpc_maxmi after {cfg.train_steps} steps, {cfg.eval_episodes} unseen episodes\n\n"
            f"| rate | value |\n|---|---|\n{eval_summary(overall)}",
            "## Wall time\n\n| stage | seconds |\n|---|---|\n"
            + "\n".join(f"| {stage} | {seconds:.0f} |" for stage, seconds in timings.items()),
        ]
    )
    (out / "summary.md").write_text(summary + "\n")
    print(f"\n{summary}\n\n(written to {out / 'summary.md'})")


if __name__ == "__main__":
    main()
