"""Scripted-expert demo generation speed: demos/minute, success rate, mean length, peak RSS per task.

    python benchmarks/demo_speed.py --tasks PickCube-v1 StackCube-v1 PegInsertionSide-v1 --attempts 50

Each task runs in its own process (so peak RSS is per task), one env, seeds 0..attempts-1, with the
recorder's defaults (randomized expert parameters, no action noise). Time excludes env creation and
the dataset writer; it includes resets (PegInsertionSide rebuilds its scene on every reset).
"""

import argparse
import multiprocessing
import resource
import time

from lerobot_maxmi.demos.experts import EXPERTS


def measure(task: str, control_mode: str, attempts: int, action_noise: float, randomize: bool) -> dict:
    from lerobot_maxmi.demos.experts import make_expert
    from lerobot_maxmi.demos.rollout import run_expert
    from lerobot_maxmi.envs.maniskill_sim import make_sim_env, task_spec

    max_steps = task_spec(task).episode_length
    env = make_sim_env(task, control_mode, max_episode_steps=max_steps + 1)
    expert = make_expert(task, control_mode)
    start = time.perf_counter()
    results = [run_expert(env, expert, seed, max_steps, action_noise, randomize) for seed in range(attempts)]
    seconds = time.perf_counter() - start
    lengths = [attempt.length for attempt in results if attempt.episode is not None]
    return {
        "task": task,
        "control_mode": control_mode,
        "successes": len(lengths),
        "attempts": attempts,
        "demos_per_minute": 60 * len(lengths) / seconds,
        "mean_length": sum(lengths) / max(len(lengths), 1),
        "failed_seeds": [attempt.seed for attempt in results if attempt.episode is None],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--tasks", nargs="+", default=list(EXPERTS), choices=list(EXPERTS))
    parser.add_argument("--control_mode", default="pd_ee_delta_pose")
    parser.add_argument("--attempts", type=int, default=30)
    parser.add_argument("--action_noise", type=float, default=0.0)
    parser.add_argument("--fixed_expert", action="store_true", help="default expert parameters")
    args = parser.parse_args()

    context = multiprocessing.get_context("spawn")
    rows = []
    for task in args.tasks:
        with context.Pool(1) as pool:
            rows.append(
                pool.apply(
                    measure,
                    (task, args.control_mode, args.attempts, args.action_noise, not args.fixed_expert),
                )
            )
    print(f"\n{'task':<22}{'mode':<18}{'success':>12}{'demos/min':>11}{'mean len':>10}{'peak RSS MB':>13}")
    for row in rows:
        success = f"{row['successes']}/{row['attempts']}"
        print(
            f"{row['task']:<22}{row['control_mode']:<18}{success:>12}{row['demos_per_minute']:>11.1f}"
            f"{row['mean_length']:>10.1f}{row['peak_rss_mb']:>13.0f}"
        )
        if row["failed_seeds"]:
            print(f"  failed seeds: {row['failed_seeds']}")


if __name__ == "__main__":
    main()
