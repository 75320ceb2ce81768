"""CoTPC's training data path through LeRobot: the cost of its training samples; prints two tables.

    .venv/bin/python benchmarks/cotpc_data_speed.py                  # the gpu profile: context 60, batch 256
    .venv/bin/python benchmarks/cotpc_data_speed.py --context_length=10 --batch_size=64 --steps=2500

lerobot-train gives CoTPC a window of `context_length` frames of the action and of every
`observation.*` column, `observation.key_states` included (LeRobot applies a policy's observation
delta indices to all of them). This times that read, one sample at a time in one process, as each
data-loader worker does it:
- map-style: `LeRobotDataset`, lerobot-train's default, at uniformly random indices;
- streaming: `StreamingLeRobotDataset` (`--dataset.streaming=true`), which reads frames in order
  through a shuffle buffer.
From the time per sample the first table derives what data loading alone allows: batches per second
per worker, and worker-hours of loading for `--steps` batches.

The second table times whole batches through a torch DataLoader with `--workers` processes, built as
lerobot-train builds it (map-style: LeRobot's EpisodeAwareSampler; streaming: `max_num_shards` =
workers). Map-style reads scale with workers. A stream splits its parquet files among the workers
twice over (LeRobot into `max_num_shards` sub-streams, then `datasets` each sub-stream among the
workers), so it keeps W workers busy only when the dataset has at least W x W files: the table
streams the dataset as LeRobot writes it by default (one file) and written one file per episode.
The datasets are synthetic, written to a temporary folder (not timed): random walks shaped like a
PickCube annotation with K key states.
"""

import argparse
import itertools
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from discovery_speed import write_dataset  # benchmarks/ is this script's import root
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.sampler import EpisodeAwareSampler
from lerobot.datasets.streaming_dataset import StreamingLeRobotDataset
from lerobot.utils.utils import cycle
from run_table import machine
from torch.utils.data import DataLoader

from lerobot_maxmi.pipeline import FILE_PER_EPISODE_MB
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


def loader_samples_per_second(dataset, workers: int, batch_size: int, seconds: float) -> float:
    """Samples per second through a DataLoader as lerobot-train builds it, timed after each worker's
    first batch (its start-up and, for a stream, the filling of its shuffle buffer)."""
    sampler = None
    if isinstance(dataset, LeRobotDataset):
        bounds = dataset.meta.episodes
        sampler = EpisodeAwareSampler(bounds["dataset_from_index"], bounds["dataset_to_index"], shuffle=True)
    # lerobot-train's endless iterator: a new pass (new workers, a new shuffle buffer) at each end.
    batches = cycle(DataLoader(dataset, batch_size=batch_size, num_workers=workers, sampler=sampler))
    for _ in range(max(workers, 1)):
        next(batches)
    start, samples = time.perf_counter(), 0
    while (elapsed := time.perf_counter() - start) < seconds:
        samples += len(next(batches)["index"])
    return samples / elapsed


def data_files(root: Path) -> int:
    return len(list(root.glob("data/*/*.parquet")))


def print_per_sample_table(seconds: dict[str, float], batch: int, steps: int) -> None:
    print(f"| loader | ms / sample | batches of {batch} / s / worker | worker-hours for {steps} steps |")
    print("|---|---:|---:|---:|")
    for loader, per_sample in seconds.items():
        per_batch = per_sample * batch
        hours = per_batch * steps / 3600
        print(f"| {loader} | {1000 * per_sample:.2f} | {1 / per_batch:.2f} | {hours:.1f} |")


def print_loader_table(rates: dict[tuple[str, int], float], workers: int, batch: int, steps: int) -> None:
    print(f"\nThrough a DataLoader with {workers} workers:\n")
    print(f"| loader | data files | samples / s | hours of loading for {steps} steps of {batch} |")
    print("|---|---:|---:|---:|")
    for (loader, files), rate in rates.items():
        print(f"| {loader} | {files} | {rate:.0f} | {steps * batch / rate / 3600:.2f} |")


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
    parser.add_argument("--workers", type=int, default=os.cpu_count())
    parser.add_argument("--loader_seconds", type=float, default=60.0, help="timed per DataLoader row")
    args = parser.parse_args()

    config = CotpcConfig(context_length=args.context_length)
    shape = (args.episodes, args.length, args.state_dim, args.key_states)
    with tempfile.TemporaryDirectory() as tmp:
        one_file, file_per_episode = Path(tmp) / "one_file", Path(tmp) / "file_per_episode"
        write_dataset(one_file, *shape)
        write_dataset(file_per_episode, *shape, data_files_size_in_mb=FILE_PER_EPISODE_MB)
        delta_timestamps = resolve_delta_timestamps(config, LeRobotDataset(REPO_ID, root=one_file).meta)
        seconds = {
            "map-style (default)": map_style_seconds(one_file, delta_timestamps, args.map_samples),
            "streaming": streaming_seconds(one_file, delta_timestamps, args.streaming_samples),
        }
        workers = args.workers

        def rate(dataset) -> float:
            return loader_samples_per_second(dataset, workers, args.batch_size, args.loader_seconds)

        def stream(root: Path) -> StreamingLeRobotDataset:
            return StreamingLeRobotDataset(
                REPO_ID, root=root, delta_timestamps=delta_timestamps, max_num_shards=workers
            )

        rates = {
            ("map-style", data_files(one_file)): rate(
                LeRobotDataset(REPO_ID, root=one_file, delta_timestamps=delta_timestamps)
            ),
            ("streaming", data_files(one_file)): rate(stream(one_file)),
            ("streaming", data_files(file_per_episode)): rate(stream(file_per_episode)),
        }

    print(
        f"\n{machine()}; {args.episodes} episodes x {args.length} frames, state {args.state_dim}-d, "
        f"{args.key_states} key states; windows of {args.context_length} frames of "
        f"{', '.join(delta_timestamps)}\n"
    )
    print_per_sample_table(seconds, args.batch_size, args.steps)
    print_loader_table(rates, workers, args.batch_size, args.steps)


if __name__ == "__main__":
    main()
