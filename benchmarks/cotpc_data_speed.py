"""CoTPC's training data path through LeRobot: the cost of one training sample; prints a table.

    .venv/bin/python benchmarks/cotpc_data_speed.py                  # the gpu profile: context 60, batch 256
    .venv/bin/python benchmarks/cotpc_data_speed.py --context_length=10 --batch_size=64 --steps=2500

lerobot-train gives CoTPC a window of `context_length` frames of the action and of every
`observation.*` column, `observation.key_states` included (LeRobot applies a policy's observation
delta indices to all of them). This times that read, one sample at a time in one process, as each
data-loader worker does it:
- map-style: `LeRobotDataset`, lerobot-train's default, at uniformly random indices;
- streaming: `StreamingLeRobotDataset` (`--dataset.streaming=true`), which reads frames in order
  through a shuffle buffer; it gives a worker one parquet file each, so a dataset in one file feeds
  one worker.
The dataset is synthetic, written once to a temporary folder (not timed): random walks shaped like a
PickCube annotation with K key states. From the time per sample the table derives what data loading
alone allows: batches per second per worker, and worker-hours of loading for `--steps` batches.
"""

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np
from discovery_speed import write_dataset  # benchmarks/ is this script's import root
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.streaming_dataset import StreamingLeRobotDataset
from run_table import machine

from lerobot_maxmi.policies.cotpc.configuration_cotpc import CotpcConfig

REPO_ID = "local/speed"


def map_style_seconds(root: Path, delta_timestamps: dict, samples: int) -> float:
    dataset = LeRobotDataset(REPO_ID, root=root, delta_timestamps=delta_timestamps)
    indices = np.random.default_rng(0).integers(0, len(dataset), samples + 1)
    dataset[int(indices[0])]  # loads the table
    start = time.perf_counter()
    for index in indices[1:]:
        dataset[int(index)]
    return (time.perf_counter() - start) / samples


def streaming_seconds(root: Path, delta_timestamps: dict, samples: int) -> float:
    """Timed from the first read: the stream fills its shuffle buffer (1,000 frames) before it yields."""
    dataset = StreamingLeRobotDataset(REPO_ID, root=root, delta_timestamps=delta_timestamps, max_num_shards=1)
    start = time.perf_counter()
    count = sum(1 for _ in itertools.islice(dataset, samples))
    return (time.perf_counter() - start) / count


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--length", type=int, default=30, help="frames per episode (PickCube demos: ~28)")
    parser.add_argument("--state_dim", type=int, default=42)
    parser.add_argument("--key_states", type=int, default=11, help="K_out of the annotation")
    parser.add_argument("--context_length", type=int, default=60)
    parser.add_argument("--batch_size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=50_000)
    parser.add_argument("--map_samples", type=int, default=100)
    parser.add_argument("--streaming_samples", type=int, default=5000)
    args = parser.parse_args()

    config = CotpcConfig(context_length=args.context_length)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "dataset"
        write_dataset(root, args.episodes, args.length, args.state_dim, args.key_states)
        delta_timestamps = resolve_delta_timestamps(config, LeRobotDataset(REPO_ID, root=root).meta)
        seconds = {
            "map-style (default)": map_style_seconds(root, delta_timestamps, args.map_samples),
            "streaming": streaming_seconds(root, delta_timestamps, args.streaming_samples),
        }

    print(
        f"\n{machine()}; {args.episodes} episodes x {args.length} frames, state {args.state_dim}-d, "
        f"{args.key_states} key states; windows of {args.context_length} frames of "
        f"{', '.join(delta_timestamps)}\n"
    )
    batch, steps = args.batch_size, args.steps
    print(f"| loader | ms / sample | batches of {batch} / s / worker | worker-hours for {steps} steps |")
    print("|---|---:|---:|---:|")
    for loader, per_sample in seconds.items():
        per_batch = per_sample * batch
        hours = per_batch * steps / 3600
        print(f"| {loader} | {1000 * per_sample:.2f} | {1 / per_batch:.2f} | {hours:.1f} |")


if __name__ == "__main__":
    main()
