"""`lerobot-maxmi-discover`: annotate a LeRobotDataset with key states, as a new dataset.

    lerobot-maxmi-discover --dataset.repo_id=local/pick --dataset.root=data/pick \\
        --output.repo_id=local/pick_maxmi --output.root=data/pick_maxmi [--selector=maxmi] \\
        [--discovery.num_concepts=5 --discovery.steps=2000] [--push_to_hub=true] [--plot=true]

The output is the source dataset plus
- per-frame `observation.key_states`: the states at the episode's K_out key frames, flattened to
  (K_out · state_dim,), the same for every frame of an episode (CoTPC's prediction target);
- per-episode `maxmi/key_frames` (frame indices) and `maxmi/selector`;
- stats for the new column: `observation.state` stats tiled K_out times, so a normalizer scales
  key states exactly as it scales states;
- with the maxmi selector, the localizer under `<output root>/maxmi_localizer/` (a LeRobot
  pipeline holding the `maxmi_discovery` step), reusable through `--discovery.pretrained_path`.

K_out is the largest number of key frames any episode has. MaxMI keeps the same concepts in every
episode (NMS is decided dataset-wide), so all its episodes have K_out; selectors whose count varies
per episode (awe, ground_truth) pad an episode's list by repeating its last key state (the final
state), in the column only: `maxmi/key_frames` keeps the unpadded list.

The source is only read; the output is built in a temporary directory beside the target and
moved into place when complete.
"""

import logging
import shutil
import tempfile
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import httpx
import numpy as np
import pyarrow.parquet as pq
import torch
from accelerate import PartialState
from draccus.utils import ParsingError
from huggingface_hub import HfApi
from huggingface_hub.errors import OfflineModeIsEnabled
from lerobot.datasets.io_utils import write_stats
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils import constants
from lerobot.utils.utils import init_logging
from torch import Tensor
from tqdm import tqdm

from lerobot_maxmi.discovery.plots import plot_episode
from lerobot_maxmi.discovery.processor import KEY_FRAMES, KEY_STATES
from lerobot_maxmi.discovery.selectors import (
    LOCALIZER_DIR,
    SELECTORS,
    AWEConfig,
    SelectionContext,
    make_selector,
)
from lerobot_maxmi.discovery.train import DiscoveryConfig, check_episodes, cpu_process_group
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column, write_episode_columns
from lerobot_maxmi.frame_columns import add_frame_columns, episode_starts, vector_column

SELECTOR_COLUMN = "maxmi/selector"
PLOTS_DIR = "plots"
NON_STATE_DTYPES = ("video", "image", "string")
USER_ERRORS = (ValueError, FileExistsError, RuntimeError)  # reported without a traceback


@dataclass
class DatasetLocation:
    repo_id: str
    root: Path | None = None  # default: $HF_LEROBOT_HOME/<repo_id>

    def resolved_root(self) -> Path:
        return Path(self.root if self.root is not None else constants.HF_LEROBOT_HOME / self.repo_id)


@dataclass
class AnnotateConfig:
    dataset: DatasetLocation
    output: DatasetLocation
    selector: str = "maxmi"
    discovery: DiscoveryConfig = field(default_factory=DiscoveryConfig)
    awe: AWEConfig = field(default_factory=AWEConfig)
    state_key: str = constants.OBS_STATE
    overwrite: bool = False
    push_to_hub: bool = False
    plot: bool = False

    def __post_init__(self):
        if self.selector not in SELECTORS:
            raise ValueError(f"unknown selector {self.selector!r}; choose one of {', '.join(SELECTORS)}")
        source, output = self.dataset.resolved_root().resolve(), self.output.resolved_root().resolve()
        if output == source or source in output.parents or output in source.parents:
            raise ValueError(
                f"the output ({output}) must not be, contain or lie inside the source dataset ({source}); "
                "choose another --output.root / --output.repo_id"
            )


def check_state_feature(features: dict, state_key: str) -> int:
    """The state dim of `state_key`; a clear error if the dataset has no usable state."""
    numeric = [k for k, v in features.items() if v["dtype"] not in NON_STATE_DTYPES]
    visual = [k for k, v in features.items() if v["dtype"] in ("video", "image")]
    if state_key not in features:
        raise ValueError(
            f"the dataset has no {state_key!r} feature. MaxMI discovers key states from a low-dimensional "
            f"state vector; pass one with --state_key (numeric features: {numeric})"
            + (f"; video/image features ({visual}) cannot be used" if visual else "")
        )
    feature = features[state_key]
    if feature["dtype"] in NON_STATE_DTYPES or len(feature["shape"]) != 1:
        raise ValueError(
            f"{state_key!r} is a {feature['dtype']} feature of shape {feature['shape']}; key states need a "
            f"1-D numeric state vector (numeric features: {numeric})"
        )
    return int(feature["shape"][0])


def load_episode_states(root: Path, state_key: str) -> dict[int, Tensor]:
    """`{episode_index: (frames, D) states}`, read column-wise from the data files (no per-frame objects)."""
    pieces: dict[int, list[np.ndarray]] = defaultdict(list)
    for path in tqdm(sorted((root / "data").glob("*/*.parquet")), desc="read states"):
        table = pq.read_table(path, columns=[state_key, "episode_index", "frame_index"])
        states = vector_column(table, state_key)
        episode, frame = (table[name].to_numpy() for name in ("episode_index", "frame_index"))
        order = np.lexsort((frame, episode))
        states, episode = states[order], episode[order]
        starts = episode_starts(episode)
        for index, rows in zip(episode[starts], np.split(states, starts[1:]), strict=True):
            pieces[int(index)].append(rows)
    return {index: torch.from_numpy(np.concatenate(parts)) for index, parts in sorted(pieces.items())}


def padded_key_states(episodes: list[Tensor], frames: list[list[int]]) -> tuple[int, list[np.ndarray]]:
    """K_out (the most key frames of any episode) and each episode's flattened (K_out · D,) key states."""
    num_key_states = max(len(f) for f in frames)
    flattened = [
        states[f + [f[-1]] * (num_key_states - len(f))].flatten().numpy()
        for states, f in zip(episodes, frames, strict=True)
    ]
    return num_key_states, flattened


def key_state_feature(state_feature: dict, num_key_states: int) -> dict:
    """Feature info of the new column; its names carry K_out and the state's own dim names."""
    dim = state_feature["shape"][0]
    names = state_feature.get("names")
    dim_names = names if isinstance(names, list) and len(names) == dim else [f"dim{d}" for d in range(dim)]
    return {
        "dtype": "float32",
        "shape": (num_key_states * dim,),
        "names": [f"key{k}.{name}" for k in range(num_key_states) for name in dim_names],
    }


def tile_stat(name: str, value, times: int):
    """A state stat repeated for each key state; `count` stays the number of frames."""
    return value if name == "count" else np.tile(value, times)


def write_key_state_stats(source: LeRobotDataset, root: Path, state_key: str, num_key_states: int) -> None:
    """Global and per-episode stats of the key states, tiled from the state's, so LeRobot's
    normalizer (meta/stats.json) and its stats aggregation on split/merge (per-episode stats) agree."""
    if not source.meta.stats or state_key not in source.meta.stats:
        raise ValueError(f"the source dataset has no stats for {state_key!r}; run lerobot's recompute_stats")
    state_stats = source.meta.stats[state_key]
    key_stats = {name: tile_stat(name, value, num_key_states) for name, value in state_stats.items()}
    write_stats({**source.meta.stats, KEY_STATES: key_stats}, root)
    per_episode = {
        f"stats/{KEY_STATES}/{name}": {
            index: tile_stat(name, np.asarray(value), num_key_states)
            for index, value in read_episode_column(root, f"stats/{state_key}/{name}").items()
        }
        for name in state_stats
    }
    write_episode_columns(root, per_episode)


def write_plots(root: Path, states: dict[int, Tensor], frames: dict[int, list[int]], source_root: Path):
    try:
        truth = read_episode_column(source_root, GT_KEY_FRAMES)
    except KeyError:
        truth = {}
    (root / PLOTS_DIR).mkdir()
    for index in tqdm(states, desc="plot episodes"):
        path = root / PLOTS_DIR / f"episode_{index:06d}.png"
        plot_episode(states[index], frames[index], truth.get(index), path, f"episode {index}")


def select_key_frames(cfg: AnnotateConfig, source: LeRobotDataset):
    """Each episode's states and key frames (`{episode_index: ...}`), and the selector that chose them."""
    check_state_feature(source.meta.features, cfg.state_key)
    if KEY_STATES in source.meta.features:
        raise ValueError(
            f"the source already has {KEY_STATES!r} (it was annotated before); annotate the original dataset"
        )
    states = load_episode_states(source.root, cfg.state_key)
    episodes = list(states.values())
    check_episodes(episodes, 1)
    context = SelectionContext(source.root, list(states), cfg.discovery, cfg.awe)
    selector = make_selector(cfg.selector, context)
    return states, dict(zip(states, selector.select(episodes), strict=True)), selector


def build_output(cfg: AnnotateConfig, source: LeRobotDataset, staging: Path) -> Path:
    """Write the annotated dataset under `staging`; returns its root."""
    states, frames, selector = select_key_frames(cfg, source)
    episodes = list(states.values())
    state_dim = episodes[0].shape[-1]
    num_key_states, key_states = padded_key_states(episodes, list(frames.values()))
    by_episode = dict(zip(states, key_states, strict=True))
    logging.info("%d key states of dim %d per episode (selector %s)", num_key_states, state_dim, cfg.selector)

    root = staging / "dataset"
    feature = key_state_feature(source.meta.features[cfg.state_key], num_key_states)

    def episode_key_states(rows) -> np.ndarray:  # the same for every frame of an episode
        return np.stack([by_episode[episode] for episode in rows["episode_index"].to_pylist()])

    add_frame_columns(source, {KEY_STATES: (episode_key_states, feature)}, root, cfg.output.repo_id)
    write_episode_columns(root, {KEY_FRAMES: frames, SELECTOR_COLUMN: dict.fromkeys(frames, cfg.selector)})
    write_key_state_stats(source, root, cfg.state_key, num_key_states)
    selector.save(root)
    if cfg.plot:
        write_plots(root, states, frames, source.root)
    return root


def move_into_place(built: Path, target: Path, staging: Path) -> None:
    if target.exists():
        target.rename(staging / "replaced")  # removed with the staging directory
    built.rename(target)


def push(cfg: AnnotateConfig, root: Path) -> None:
    """Upload the dataset (and its localizer as a model repo of the same id, for `pretrained_path`)."""
    repo_id = cfg.output.repo_id
    try:
        LeRobotDataset(repo_id, root=root).push_to_hub(tags=["maxmi", "key-states"])
        if (root / LOCALIZER_DIR).is_dir():
            api = HfApi()
            api.create_repo(repo_id, repo_type="model", exist_ok=True)
            api.upload_folder(repo_id=repo_id, folder_path=root / LOCALIZER_DIR, repo_type="model")
    except (OfflineModeIsEnabled, httpx.HTTPError, OSError) as error:
        raise RuntimeError(
            f"the annotated dataset is complete at {root}, but pushing it to {repo_id} failed "
            f"({type(error).__name__}: {error}). Check the network / HF_HUB_OFFLINE and your token, then "
            f"push with LeRobotDataset({repo_id!r}, root={str(root)!r}).push_to_hub()"
        ) from error


def annotate(cfg: AnnotateConfig) -> Path | None:
    """Annotate `cfg.dataset` into a new dataset at the output root; returns that root (None in the worker
    processes of a multi-process `accelerate launch`, which only help train the localizer)."""
    target = cfg.output.resolved_root()
    if target.exists() and not cfg.overwrite:
        raise FileExistsError(f"{target} already exists; pass --overwrite=true to replace it")
    source = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root)
    if not PartialState(cpu=cpu_process_group()).is_main_process:  # an `accelerate launch` worker
        select_key_frames(cfg, source)
        return None
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        move_into_place(build_output(cfg, source, staging), target, staging)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    logging.info("annotated dataset written to %s", target)
    if cfg.push_to_hub:
        push(cfg, target)
    return target


@draccus.wrap()
def run(cfg: AnnotateConfig) -> None:
    annotate(cfg)


def main() -> None:
    init_logging()
    try:
        run()
    except (*USER_ERRORS, ParsingError) as error:
        # draccus wraps a config's own validation error; report that one.
        reason = error.__cause__ if isinstance(error, ParsingError) else error
        if not isinstance(reason, USER_ERRORS):
            raise
        raise SystemExit(f"lerobot-maxmi-discover: {reason}") from error


if __name__ == "__main__":
    main()
