"""`lerobot-maxmi-demos`: record scripted-expert demonstrations as a LeRobotDataset with key frames.

    lerobot-maxmi-demos --env.type=maniskill --env.task=StackCube-v1 --num_episodes=500 \\
        --repo_id=local/maniskill_stackcube [--root=...] [--seed=0] [--num_workers=2] \\
        [--action_noise=0.05] [--resume=true | --overwrite=true] [--push_to_hub=true]

Attempt i runs the env seed `seed + i` with expert parameters and noise drawn from that seed; only
successful attempts become episodes, written in seed order whatever `num_workers` is. (States can
still differ at float precision, ~1e-6, between worker counts: PhysX keeps contact caches across
resets of one env.) `--resume=true` continues after the largest recorded seed, so no seed is used
twice, until the dataset holds `num_episodes`; Ctrl-C saves the episodes so far, ready to resume.
Each episode carries `episode_seed`, `gt/key_frames` and `gt/key_frame_names` (see `episode.py`).
"""

import functools
import itertools
import logging
import multiprocessing
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from lerobot.configs import parser
from lerobot.envs.configs import EnvConfig
from lerobot.utils.utils import init_logging
from tqdm import tqdm

import lerobot_maxmi  # noqa: F401  (registers --env.type=maniskill)
from lerobot_maxmi.demos.dataset_writer import DemoDatasetWriter, default_root, push_to_hub
from lerobot_maxmi.demos.kitchen_demos import KitchenDemoSource
from lerobot_maxmi.demos.rollout import Attempt, ManiSkillDemoSource

logger = logging.getLogger(__name__)


@dataclass
class RecordDemosConfig:
    env: EnvConfig
    repo_id: str
    num_episodes: int = 100  # successful episodes the dataset should hold (in total, when resuming)
    root: Path | None = None  # default: $HF_LEROBOT_HOME/<repo_id>
    seed: int = 0  # env seed of the first attempt
    action_noise: float = 0.0  # std of Gaussian noise on the normalized arm actions
    randomize_expert: bool = True  # draw the expert's heights, gains and grasp offset per episode
    num_workers: int = 1  # processes generating attempts; the main process writes the dataset
    max_attempts: int | None = None  # give up after this many attempts; default 2 x remaining episodes + 10
    # LeRobot starts a new parquet file past this size (default 100 MB). A value under one episode's size
    # (e.g. 0.001) writes a file per episode: `lerobot-train --dataset.streaming=true` keeps W loader
    # workers busy only with at least W x W files (docs/RESULTS.md, "CoTPC's data path through LeRobot").
    data_files_size_in_mb: float | None = None
    resume: bool = False
    overwrite: bool = False
    push_to_hub: bool = False

    def __post_init__(self):
        if self.resume and self.overwrite:
            raise ValueError("Choose one of --resume=true (add episodes) and --overwrite=true (start over).")
        if self.num_workers < 1:
            raise ValueError(f"--num_workers must be at least 1, got {self.num_workers}.")
        self.root = Path(self.root) if self.root else default_root(self.repo_id)


# A demo source yields `Attempt`s by seed and knows the dataset's fps, task string and robot type.
# Keyed by `--env.type`; new env types (e.g. franka_kitchen) register their own source here.
DEMO_SOURCES: dict[str, Callable[[EnvConfig, RecordDemosConfig], object]] = {
    "maniskill": lambda env_cfg, cfg: ManiSkillDemoSource(env_cfg, cfg.action_noise, cfg.randomize_expert),
    "franka_kitchen": lambda env_cfg, cfg: KitchenDemoSource(env_cfg, cfg.action_noise, cfg.randomize_expert),
}


def make_source_factory(cfg: RecordDemosConfig) -> Callable[[], object]:
    """A picklable zero-argument constructor of the demo source (worker processes call it)."""
    if cfg.env.type not in DEMO_SOURCES:
        raise ValueError(
            f"No demo generator for --env.type={cfg.env.type}; available: {', '.join(DEMO_SOURCES)}."
        )
    return functools.partial(_build_source, cfg)


def _build_source(cfg: RecordDemosConfig):
    return DEMO_SOURCES[cfg.env.type](cfg.env, cfg)


_worker_source = None


def _init_worker(source_factory: Callable[[], object]) -> None:
    global _worker_source
    _worker_source = source_factory()


def _attempt_in_worker(seed: int) -> Attempt:
    return _worker_source.attempt(seed)


def attempts_in_seed_order(
    source_factory: Callable[[], object], first_seed: int, num_workers: int
) -> Iterator[Attempt]:
    """Attempts for seeds first_seed, first_seed + 1, ... in order, computed by `num_workers` processes."""
    seeds = itertools.count(first_seed)
    if num_workers == 1:
        source = source_factory()
        yield from map(source.attempt, seeds)
        return
    pool = ProcessPoolExecutor(
        num_workers,
        mp_context=multiprocessing.get_context("spawn"),  # no forked simulator or torch state
        initializer=_init_worker,
        initargs=(source_factory,),
    )
    try:
        # Two seeds in flight per worker keeps them busy while results are consumed in order.
        pending = deque(
            pool.submit(_attempt_in_worker, seed) for seed in itertools.islice(seeds, 2 * num_workers)
        )
        while True:
            attempt = pending.popleft().result()
            pending.append(pool.submit(_attempt_in_worker, next(seeds)))
            yield attempt
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def record(cfg: RecordDemosConfig) -> Path:
    source_factory = make_source_factory(cfg)
    source = source_factory()  # validates the task and control mode before anything is written
    writer = DemoDatasetWriter.open(
        cfg.repo_id,
        cfg.root,
        source.fps,
        source.task,
        source.robot_type,
        overwrite=cfg.overwrite,
        resume=cfg.resume,
        data_files_size_in_mb=cfg.data_files_size_in_mb,
    )
    remaining = cfg.num_episodes - writer.num_episodes
    if remaining <= 0:
        logger.info("%s already holds %d episodes; nothing to record.", cfg.root, writer.num_episodes)
        writer.discard()
    else:
        first_seed = max([cfg.seed, *(seed + 1 for seed in writer.seeds)])
        attempts = attempts_in_seed_order(source_factory, first_seed, cfg.num_workers)
        _record_into(writer, attempts, cfg.num_episodes, cfg.max_attempts or 2 * remaining + 10)
    if cfg.push_to_hub:
        push_to_hub(cfg.repo_id, cfg.root)
    return cfg.root


def _record_into(writer: DemoDatasetWriter, attempts: Iterator[Attempt], target: int, max_attempts: int):
    """Write successful attempts until `target` episodes; publish the dataset, also on Ctrl-C."""
    progress = tqdm(total=target, initial=writer.num_episodes, unit="demo")
    tried = succeeded = 0
    last_failure = ""
    try:
        for attempt in attempts:
            tried += 1
            if attempt.episode is None:
                last_failure = f"seed {attempt.seed}: {attempt.failure}"
                logger.debug("Seed %d failed: %s", attempt.seed, attempt.failure)
            else:
                writer.add(attempt.episode)
                succeeded += 1
            progress.set_postfix(attempts=tried, success=f"{succeeded / tried:.1%}", refresh=False)
            progress.update(attempt.episode is not None)
            if writer.num_episodes >= target or tried >= max_attempts:
                break
    except KeyboardInterrupt:
        logger.warning("Interrupted: saving %d episodes; continue with --resume=true.", writer.num_episodes)
        _publish(writer, tried, succeeded)
        raise
    except BaseException:
        writer.discard()
        raise
    finally:
        attempts.close()
        progress.close()
    if writer.num_episodes == 0:
        writer.discard()
        raise RuntimeError(
            f"None of {tried} attempts succeeded, so nothing was written (last failure, {last_failure}). "
            "Check the task and control mode the scripted experts support (lerobot_maxmi/demos/experts.py) "
            "or raise --max_attempts."
        )
    _publish(writer, tried, succeeded)
    if writer.num_episodes < target:
        raise RuntimeError(
            f"Only {writer.num_episodes}/{target} episodes after {tried} attempts (the expert's success rate "
            f"was {succeeded / tried:.1%}); they are saved at {writer.root}. Add more with --resume=true "
            "and a larger --max_attempts."
        )


def _publish(writer: DemoDatasetWriter, tried: int, succeeded: int) -> None:
    root = writer.publish()
    rate = f"{succeeded / tried:.1%}" if tried else "n/a"
    logger.info(
        "%d episodes at %s (this run: %d/%d attempts succeeded, %s).",
        writer.num_episodes,
        root,
        succeeded,
        tried,
        rate,
    )


@parser.wrap()
def record_main(cfg: RecordDemosConfig) -> Path:
    return record(cfg)


def main() -> None:
    init_logging()
    record_main()


if __name__ == "__main__":
    main()
