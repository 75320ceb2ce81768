"""Discovery at dataset scale: train KSL-Net and annotate N episodes; prints wall time and peak memory.

    .venv/bin/python benchmarks/discovery_speed.py                  # 500 episodes x 150 frames, 43-d
    .venv/bin/python benchmarks/discovery_speed.py --episodes=100 --extra='--discovery.device=cuda'

The dataset is synthetic (random walks, the size of a PegInsertionSide state), written once to a
temporary folder; its creation is not timed. The timed part is one `lerobot-maxmi-discover` run,
exactly as a user would type it, in a child process: training, localization of every episode and
writing the annotated copy. Peak RSS is the child's. Targets (issue 4): <= 10 min and <= 4 GB on
2 CPU cores for 500 episodes of ~150 frames.
"""

import argparse
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from run_table import machine  # benchmarks/ is this script's import root


def write_dataset(
    root: Path,
    episodes: int,
    length: int,
    state_dim: int,
    key_states: int = 0,
    data_files_size_in_mb: float | None = None,
) -> None:
    """Random-walk states and random actions; with `key_states` > 0 also an `observation.key_states`
    column of that many states per episode, shaped as `lerobot-maxmi-discover` writes it.
    `data_files_size_in_mb`: LeRobot's size at which it starts a new parquet file (default 100)."""
    import datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    datasets.disable_progress_bars()  # a "Map" bar per data file
    features = {
        "observation.state": {"dtype": "float32", "shape": (state_dim,), "names": None},
        "action": {"dtype": "float32", "shape": (7,), "names": None},
    }
    if key_states:
        features["observation.key_states"] = {
            "dtype": "float32",
            "shape": (key_states * state_dim,),
            "names": None,
        }
    dataset = LeRobotDataset.create(
        "local/speed",
        fps=20,
        features=features,
        root=root,
        use_videos=False,
        data_files_size_in_mb=data_files_size_in_mb,
    )
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        states = np.cumsum(rng.normal(size=(length, state_dim)), axis=0).astype(np.float32)
        actions = rng.normal(size=(length, 7)).astype(np.float32)
        key_frames = np.linspace(0, length - 1, key_states).astype(int)
        extra = {"observation.key_states": states[key_frames].reshape(-1)} if key_states else {}
        for state, action in zip(states, actions, strict=True):
            dataset.add_frame({"observation.state": state, "action": action, "task": "synthetic", **extra})
        dataset.save_episode()
    dataset.finalize()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--length", type=int, default=150)
    parser.add_argument("--state_dim", type=int, default=43)
    parser.add_argument("--steps", type=int, default=1000, help="--discovery.steps")
    parser.add_argument("--extra", default="", help="more lerobot-maxmi-discover flags")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        source, output = Path(tmp) / "source", Path(tmp) / "annotated"
        write_dataset(source, args.episodes, args.length, args.state_dim)
        # The console script's own module, so this also runs where the package is importable but its
        # scripts are not installed beside this interpreter (e.g. PYTHONPATH on a GPU machine).
        cli = [sys.executable, "-m", "lerobot_maxmi.discovery.annotate"]
        flags = [f"--discovery.steps={args.steps}", *shlex.split(args.extra)]
        command = [
            *cli,
            "--dataset.repo_id=local/speed",
            f"--dataset.root={source}",
            "--output.repo_id=local/speed_maxmi",
            f"--output.root={output}",
            *flags,
        ]
        start = time.perf_counter()
        subprocess.run(command, check=True)
        seconds = time.perf_counter() - start
    peak_bytes = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024  # ru_maxrss is in KiB

    print(f"\nlerobot-maxmi-discover, {machine()}, flags: {' '.join(flags)}\n")
    print("| episodes x frames | state dim | training steps | wall time | peak RSS | targets |")
    print("|---|---:|---:|---:|---:|---|")
    print(
        f"| {args.episodes} x {args.length} | {args.state_dim} | {args.steps} | {seconds / 60:.1f} min "
        f"| {peak_bytes / 1e9:.2f} GB ({peak_bytes / 2**30:.2f} GiB) | <= 10 min, <= 4 GB |"
    )


if __name__ == "__main__":
    main()
