"""The paper's tables, one cell at a time, through the real CLIs; prints (and writes) markdown tables.

    .venv/bin/python benchmarks/run_table.py --profile=cpu --tasks='[PickCube-v1]' \
        --variants='[maxmi,ground_truth,last_state,none]' --seeds='[0]'

Tasks are ManiSkill task ids or `FrankaKitchen-v1` (the `franka_kitchen` env type).
A cell is (task, variant, seed) under a profile: demos -> lerobot-maxmi-discover -> lerobot-train ->
lerobot-eval on seen initial configurations (the demos' own seeds) and unseen ones (seeds from
1,000,000 on). Every finished cell is stored in `<output_dir>/results.json` under its full
configuration; a cell already there is skipped, so an interrupted run continues where it stopped.
Runners for different tasks may share an output directory and run at the same time.
A cell whose command fails is not stored. The tables (`<output_dir>/tables.md`: all tasks side by
side in the paper's Table 1/2 layout; each variant's unseen headline minus that of `none` and of
`last_state`, with a 95% confidence interval over seeds, where both have two or more; then every
rate per task) are regenerated from the JSON after every cell, and on their own with `--run=false`.
"""

import fcntl
import json
import os
import platform
import statistics
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path

import draccus
import torch
from scipy import stats

from lerobot_maxmi.envs.configs import NUM_TASKS_COMPLETED
from lerobot_maxmi.pipeline import (
    annotate,
    cotpc_flags,
    environment_state_copy,
    evaluate_policy,
    rates,
    record_demos,
    timed,
    train_policy,
)

UNSEEN_SEED = 1_000_000  # far above any demo seed
BASELINES = ("none", "last_state")  # what the paper's claim says MaxMI beats
MEAN_METRICS = {NUM_TASKS_COMPLETED}  # means over episodes; every other metric is a % of episodes


@dataclass(frozen=True)
class Variant:
    """How a cell gets its key states (a discovery selector, None: none) and which policy it trains."""

    selector: str | None
    discovery_flags: tuple[str, ...] = ()
    # A LeRobot policy instead of CoTPC, trained on the demos with their state as environment state.
    builtin_policy_flags: tuple[str, ...] = ()
    num_concepts: int | None = None  # discovery's K, when not the profile's

    def policy_flags(self, context_length: int) -> tuple[str, ...]:
        if self.builtin_policy_flags:
            return self.builtin_policy_flags
        return cotpc_flags("cotpc_maxmi" if self.selector == "maxmi" else "cotpc", context_length)


# LeRobot's ACT at CoTPC's width (128, 4x feed-forward; its default 512 takes ~6 s a step on 2 CPU
# cores), with chunks sized for 100-step episodes: 20 actions, re-planned every 5.
ACT_FLAGS = (
    "--policy.type=act",
    "--policy.dim_model=128",
    "--policy.dim_feedforward=512",
    "--policy.chunk_size=20",
    "--policy.n_action_steps=5",
)


VARIANTS = {
    "maxmi": Variant("maxmi"),
    "maxmi_released": Variant("maxmi", ("--discovery.objective=released",)),
    # The paper's K: discovery finds the sub-goals where the cpu profile's K = 4 misses them.
    "maxmi_k10": Variant("maxmi", num_concepts=10),
    # The setting that meets the discovery target on StackCube (docs/RESULTS.md, "sliced MI").
    "maxmi_k10_sliced": Variant("maxmi", ("--discovery.state_mi_mode=sliced",), num_concepts=10),
    # Sliced MI and spread concepts: docs/discovery.md's flags for ManiSkill-like tasks.
    "maxmi_k10_sliced_spread": Variant(
        "maxmi",
        ("--discovery.state_mi_mode=sliced", "--discovery.model.concept_start=spread"),
        num_concepts=10,
    ),
    "maxmi_mi_only": Variant("maxmi", ("--discovery.diversity_weight=0",)),
    "maxmi_diversity_only": Variant("maxmi", ("--discovery.mi_weight=0",)),
    "ground_truth": Variant("ground_truth"),
    "last_state": Variant("last_state"),
    "awe": Variant("awe"),
    "uniform": Variant("uniform"),
    "none": Variant(None),
    "act": Variant(None, builtin_policy_flags=ACT_FLAGS),  # the outside reference
}


# AWE's threshold where its default does not fit a task's state: the kitchen's noisy 30-d state
# keeps ~243 of ~280 frames at 0.1, 12.8 at 0.5 (docs/RESULTS.md, "Franka Kitchen: where the key
# frames sit").
AWE_FLAGS = {"FrankaKitchen-v1": ("--awe.error_threshold=0.5",)}


@dataclass(frozen=True)
class Profile:
    num_demos: int
    discovery_steps: int
    num_concepts: int
    train_steps: int
    batch_size: int
    context_length: int
    eval_episodes: int
    device: str
    loader: str = "map"  # lerobot-train's, one of pipeline.LOADERS


PROFILES = {
    # About 30 minutes of training per cell on 2 CPU cores (PickCube, with key states).
    "cpu": Profile(100, 1000, 4, 2500, 64, 10, 100, "cpu"),
    # The paper's context length and batch size on a GPU. Loading bounds it: LeRobot 0.6.1's map-style
    # loader would need ~165 worker-hours to read its samples, streaming ~5 (docs/RESULTS.md, "CoTPC's
    # data path through LeRobot").
    "gpu": Profile(500, 3000, 10, 50_000, 256, 60, 100, "cuda", loader="streaming"),
}


@dataclass
class TableConfig:
    profile: str = "cpu"
    tasks: list[str] = field(default_factory=lambda: ["PickCube-v1"])
    variants: list[str] = field(default_factory=lambda: ["maxmi", "ground_truth", "last_state", "none"])
    seeds: list[int] = field(default_factory=lambda: [0])
    output_dir: Path = Path("outputs/tables")
    run: bool = True  # false: only regenerate the tables from results.json

    def __post_init__(self):
        for name, chosen, valid in [
            ("profile", [self.profile], PROFILES),
            ("variant", self.variants, VARIANTS),
        ]:
            unknown = [value for value in chosen if value not in valid]
            if unknown:
                raise ValueError(f"unknown {name} {unknown}; choose from {', '.join(valid)}")


def cell_config(task: str, variant: str, seed: int, profile: Profile) -> dict:
    """The cell's key. A profile field at its default is left out, so that cells stored before the
    field existed keep their keys."""
    defaults = {f.name: f.default for f in fields(Profile) if f.default is not MISSING}
    sizes = {name: value for name, value in asdict(profile).items() if defaults.get(name, MISSING) != value}
    return {"task": task, "variant": variant, "seed": seed, **sizes}


def cell_key(config: dict) -> str:
    return json.dumps(config, sort_keys=True)


def run_cell(config: dict, profile: Profile, out: Path) -> dict:
    """One cell through the CLIs; returns its success / sub-task rates and the wall time per stage."""
    task, seed = config["task"], config["seed"]
    variant, timings = VARIANTS[config["variant"]], {}
    cell = out / "cells" / f"{task}_{config['variant']}_seed{seed}"

    demos = out / "demos" / f"{task}_{profile.num_demos}"  # every variant and seed trains on these
    timed(timings, "demos", record_demos, task, profile.num_demos, demos, loader=profile.loader)
    dataset = demos
    if variant.selector:
        dataset = cell / "dataset"
        discovery = (
            f"--discovery.num_concepts={variant.num_concepts or profile.num_concepts}",
            f"--discovery.steps={profile.discovery_steps}",
            f"--discovery.seed={seed}",
            f"--discovery.device={profile.device}",
            *variant.discovery_flags,
            *(AWE_FLAGS.get(task, ()) if variant.selector == "awe" else ()),
        )
        timed(timings, "discovery", annotate, demos, dataset, variant.selector, *discovery)
    if variant.builtin_policy_flags:
        dataset = cell / "dataset"
        timed(timings, "environment_state", environment_state_copy, demos, dataset)
    policy = variant.policy_flags(profile.context_length)
    training = (profile.train_steps, profile.batch_size, profile.device, seed)
    checkpoint = timed(
        timings, "training", train_policy, policy, dataset, cell / "train", *training, loader=profile.loader
    )
    # Seen: the demos' own initial configurations (their seeds start at 0); unseen: fresh seeds.
    splits = {
        "seen": (0, min(profile.eval_episodes, profile.num_demos)),
        "unseen": (UNSEEN_SEED, profile.eval_episodes),
    }
    result = {"config": config, "wall_s": timings}
    for split, (first_seed, episodes) in splits.items():
        eval_dir = cell / f"eval_{split}"
        overall = timed(
            timings,
            f"eval_{split}",
            evaluate_policy,
            checkpoint,
            task,
            eval_dir,
            episodes,
            first_seed,
            profile.device,
        )
        result[split] = rates(overall)
    return result


def load_results(path: Path) -> dict:
    return json.loads(path.read_text()) if path.exists() else {}


def store_cell(results_path: Path, key: str, cell: dict) -> dict:
    """Merge one finished cell into results.json under a lock; returns all results stored so far.

    Runners that share an output directory (different tasks in parallel) keep each other's cells.
    """
    results_path.parent.mkdir(parents=True, exist_ok=True)
    with open(results_path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        results = {**load_results(results_path), key: cell}
        save_text(results_path, json.dumps(results, indent=1))
    return results


def save_text(path: Path, text: str) -> None:
    """Write atomically, so an interrupted run never leaves a truncated file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def mean_spread(values: list[float], digits: int) -> str:
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def machine() -> str:
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{platform.machine()}, {os.cpu_count()} cores, {gpu}"


def unit(metric: str) -> str:
    return "(mean)" if metric in MEAN_METRICS else "%"


def seen_unseen(cells: list[dict], name: str) -> str:
    """One metric over the cells' seeds, "seen / unseen" (mean ± sd where several seeds ran)."""
    digits = 2 if name in MEAN_METRICS else 0
    seen, unseen = ([cell[split][name] for cell in cells] for split in ("seen", "unseen"))
    return f"{mean_spread(seen, digits)} / {mean_spread(unseen, digits)}"


def variant_row(variant: str, cells: list[dict], rate_names: list[str]) -> str:
    return row([variant, str(len(cells)), *(seen_unseen(cells, name) for name in rate_names)])


def headline(cells: list[dict]) -> str:
    """The metric a task is ranked by: success, or the kitchen's count of completed subtasks."""
    return NUM_TASKS_COMPLETED if NUM_TASKS_COMPLETED in cells[0]["unseen"] else "success"


def row(values: list[str]) -> str:
    return "| " + " | ".join(values) + " |"


def table(header: list[str], rows: list[str]) -> str:
    return "\n".join([row(header), "|" + "---|" * len(header), *rows])


def headline_metrics(by_task: dict[str, dict[str, list[dict]]]) -> dict[str, str]:
    return {task: headline(next(iter(by_variant.values()))) for task, by_variant in by_task.items()}


def task_header(metrics: dict[str, str]) -> list[str]:
    return ["variant", *(f"{task} {metric} {unit(metric)}" for task, metric in metrics.items())]


def all_variants(by_task: dict[str, dict[str, list[dict]]]) -> list[str]:
    return sorted({variant for by_variant in by_task.values() for variant in by_variant})


def summary_table(by_task: dict[str, dict[str, list[dict]]]) -> str:
    """The paper's Table 1/2 layout: a row per variant, a column per task, its headline metric."""
    metrics = headline_metrics(by_task)
    rows = []
    for variant in all_variants(by_task):
        values = []
        for task, metric in metrics.items():
            cells = by_task[task].get(variant)
            seeds = f" ({len(cells)} seeds)" if cells and len(cells) > 1 else ""
            values.append(seen_unseen(cells, metric) + seeds if cells else "—")
        rows.append(row([variant, *values]))
    return table(task_header(metrics), rows)


def unseen_difference(cells: list[dict], baseline_cells: list[dict], metric: str) -> str:
    """Unseen `metric`, cells minus baseline: mean difference [95% CI], Welch's p; "—" under 2 seeds a side.

    Seeds are the unit: each cell is one training run, so the spread between runs is the noise.
    """
    values, baseline = ([cell["unseen"][metric] for cell in group] for group in (cells, baseline_cells))
    if min(len(values), len(baseline)) < 2:
        return "—"
    test = stats.ttest_ind(values, baseline, equal_var=False)
    low, high = test.confidence_interval(0.95)
    digits = 2 if metric in MEAN_METRICS else 1
    difference = statistics.mean(values) - statistics.mean(baseline)
    return f"{difference:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}], p = {test.pvalue:.2f}"


def difference_table(by_task: dict[str, dict[str, list[dict]]], baseline: str) -> str:
    """A row per other variant, a column per task: its unseen headline metric minus the baseline's."""
    metrics = headline_metrics(by_task)
    rows = []
    for variant in all_variants(by_task):
        if variant != baseline:
            differences = (
                unseen_difference(by_task[task].get(variant, []), by_task[task].get(baseline, []), metric)
                for task, metric in metrics.items()
            )
            rows.append(row([variant, *differences]))
    return table(task_header(metrics), rows)


def task_table(by_variant: dict[str, list[dict]]) -> str:
    """A row per variant: success and sub-task rates, seen / unseen."""
    rate_names = list(next(iter(by_variant.values()))[0]["unseen"])
    header = ["variant", "seeds", *(f"{name} {unit(name)} (seen / unseen)" for name in rate_names)]
    rows = [variant_row(variant, cells, rate_names) for variant, cells in sorted(by_variant.items())]
    return table(header, rows)


def markdown_tables(results: dict) -> str:
    """Per profile (the cells' sizes): all tasks side by side, the differences from the baselines, then
    one table per task."""
    groups: dict[str, dict[str, dict[str, list[dict]]]] = {}
    for cell in results.values():
        config = cell["config"]
        sizes = ", ".join(
            f"{k} {v}" for k, v in sorted(config.items()) if k not in ("task", "variant", "seed")
        )
        by_task = groups.setdefault(sizes, {}).setdefault(config["task"], {})
        by_task.setdefault(config["variant"], []).append(cell)
    sections = [f"Machine: {machine()}"]
    for sizes, by_task in sorted(groups.items()):
        by_task = dict(sorted(by_task.items()))
        sections.append(f"## {sizes}\n\n### All tasks, seen / unseen\n\n{summary_table(by_task)}")
        sections += [
            f"### Unseen, minus {baseline}: mean difference [95% CI], Welch's t-test\n\n"
            + difference_table(by_task, baseline)
            for baseline in BASELINES
            if any(baseline in by_variant for by_variant in by_task.values())
        ]
        sections += [f"### {task}\n\n{task_table(by_variant)}" for task, by_variant in by_task.items()]
    return "\n\n".join(sections)


def run_table(cfg: TableConfig) -> str:
    """Run the cells not in results.json yet (storing each as it finishes); returns the tables."""
    results_path, tables_path = cfg.output_dir / "results.json", cfg.output_dir / "tables.md"
    results = load_results(results_path)
    profile = PROFILES[cfg.profile]
    configs = [
        cell_config(task, variant, seed, profile)
        for task in cfg.tasks
        for variant in cfg.variants
        for seed in cfg.seeds
    ]
    for config in configs if cfg.run else []:
        if cell_key(config) in results:
            print(f"done already: {config['task']} {config['variant']} seed {config['seed']}")
            continue
        results = store_cell(results_path, cell_key(config), run_cell(config, profile, cfg.output_dir))
        save_text(tables_path, markdown_tables(results) + "\n")
    tables = markdown_tables(results)
    save_text(tables_path, tables + "\n")
    return tables


@draccus.wrap()
def main(cfg: TableConfig) -> None:
    print(f"\n{run_table(cfg)}\n\n(written to {cfg.output_dir / 'tables.md'})")


if __name__ == "__main__":
    main()
