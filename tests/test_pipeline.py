"""The result-table runner's bookkeeping, with the command-line tools replaced by a recorder."""

import json
import subprocess
from pathlib import Path

import pytest

from lerobot_maxmi import pipeline
from tests.conftest import load_benchmark

run_table = load_benchmark("run_table")


class FakeTools:
    """Records each command; lerobot-eval writes an eval_info.json, `failing` tools exit non-zero."""

    def __init__(self, failing: str | None = None):
        self.commands: list[list[str]] = []
        self.failing = failing

    def __call__(self, name: str, *args: str) -> None:
        self.commands.append([name, *args])
        if name == self.failing:
            raise subprocess.CalledProcessError(1, name)
        if name == "lerobot-eval":
            flags = dict(arg.removeprefix("--").split("=", 1) for arg in args)
            seen = flags["seed"] == "0"
            overall = {
                "pc_success": 40.0 if seen else 20.0,
                "pc_milestones": {"grasp": 90.0, "success": 20.0},
            }
            Path(flags["output_dir"]).mkdir(parents=True)
            (Path(flags["output_dir"]) / "eval_info.json").write_text(json.dumps({"overall": overall}))

    def tools(self) -> list[str]:
        return [command[0] for command in self.commands]

    def flag(self, tool: str, name: str) -> list[str]:
        return [
            arg.split("=", 1)[1]
            for c in self.commands
            if c[0] == tool
            for arg in c
            if arg.startswith(name + "=")
        ]


def table_config(tmp_path, variants):
    return run_table.TableConfig(variants=variants, seeds=[0, 1], output_dir=tmp_path)


def test_variants_can_set_discoverys_k_and_mi_mode(monkeypatch, tmp_path):
    tools = FakeTools()
    monkeypatch.setattr(pipeline, "run_tool", tools)
    variants = ["maxmi", "maxmi_k10", "maxmi_k10_sliced"]
    run_table.run_table(run_table.TableConfig(variants=variants, output_dir=tmp_path))
    profile_k = str(run_table.PROFILES["cpu"].num_concepts)
    assert tools.flag("lerobot-maxmi-discover", "--discovery.num_concepts") == [profile_k, "10", "10"]
    assert tools.flag("lerobot-maxmi-discover", "--discovery.state_mi_mode") == ["sliced"]


def test_awe_gets_the_kitchens_threshold_and_only_there(monkeypatch, tmp_path):
    tools = FakeTools()
    monkeypatch.setattr(pipeline, "run_tool", tools)
    tasks = ["PickCube-v1", "FrankaKitchen-v1"]
    run_table.run_table(run_table.TableConfig(tasks=tasks, variants=["awe", "uniform"], output_dir=tmp_path))
    assert tools.flag("lerobot-maxmi-discover", "--selector") == ["awe", "uniform", "awe", "uniform"]
    assert tools.flag("lerobot-maxmi-discover", "--awe.error_threshold") == ["0.5"]  # kitchen AWE only


def test_cells_run_the_pipeline_per_variant_and_are_not_rerun(monkeypatch, tmp_path):
    tools = FakeTools()
    monkeypatch.setattr(pipeline, "run_tool", tools)
    tables = run_table.run_table(table_config(tmp_path, ["maxmi", "none"]))

    assert tools.tools().count("lerobot-train") == 4 and tools.tools().count("lerobot-eval") == 8
    assert tools.flag("lerobot-maxmi-discover", "--selector") == [
        "maxmi",
        "maxmi",
    ]  # "none" annotates nothing
    assert tools.flag("lerobot-train", "--policy.type") == ["cotpc_maxmi", "cotpc_maxmi", "cotpc", "cotpc"]
    assert set(tools.flag("lerobot-eval", "--seed")) == {"0", str(run_table.UNSEEN_SEED)}
    results = json.loads((tmp_path / "results.json").read_text())
    assert len(results) == 4 and all(
        cell["unseen"] == {"success": 20.0, "grasp": 90.0} for cell in results.values()
    )
    assert "| maxmi | 2 | 40 ± 0 / 20 ± 0 | 90 ± 0 / 90 ± 0 |" in tables
    assert (tmp_path / "tables.md").read_text().strip() == tables

    tools.commands.clear()
    run_table.run_table(table_config(tmp_path, ["maxmi", "none"]))
    assert "lerobot-train" not in tools.tools()  # every cell is done already


def test_cells_stored_by_a_parallel_runner_are_kept(monkeypatch, tmp_path):
    tools = FakeTools()
    config = run_table.cell_config("StackCube-v1", "none", 0, run_table.PROFILES["cpu"])
    foreign = {"config": config, "seen": {"success": 1.0}, "unseen": {"success": 2.0}, "wall_s": {}}

    def another_runner_stores_a_cell(name, *args):
        if name == "lerobot-train":
            (tmp_path / "results.json").write_text(json.dumps({run_table.cell_key(config): foreign}))
        tools(name, *args)

    monkeypatch.setattr(pipeline, "run_tool", another_runner_stores_a_cell)
    run_table.run_table(run_table.TableConfig(variants=["none"], output_dir=tmp_path))
    results = json.loads((tmp_path / "results.json").read_text())
    assert results[run_table.cell_key(config)] == foreign and len(results) == 2
    assert "### StackCube-v1" in (tmp_path / "tables.md").read_text()


@pytest.mark.parametrize(("profile", "streams"), [("cpu", False), ("gpu", True)])
def test_a_streaming_profile_records_a_file_per_episode_and_streams(monkeypatch, tmp_path, profile, streams):
    tools = FakeTools()
    monkeypatch.setattr(pipeline, "run_tool", tools)
    run_table.run_table(run_table.TableConfig(profile=profile, variants=["none"], output_dir=tmp_path))
    file_size = [str(pipeline.FILE_PER_EPISODE_MB)] if streams else []
    assert tools.flag("lerobot-maxmi-demos", "--data_files_size_in_mb") == file_size
    assert tools.flag("lerobot-train", "--dataset.streaming") == (["true"] if streams else [])


def test_cells_stored_before_the_loader_field_keep_their_keys():
    config = run_table.cell_config("PickCube-v1", "none", 0, run_table.PROFILES["cpu"])
    assert "loader" not in config  # the cpu cells in docs/RESULTS.md were stored without it
    gpu = run_table.cell_config("PickCube-v1", "none", 0, run_table.PROFILES["gpu"])
    assert gpu["loader"] == "streaming"


def test_a_failed_cell_is_not_recorded(monkeypatch, tmp_path):
    monkeypatch.setattr(pipeline, "run_tool", FakeTools(failing="lerobot-train"))
    with pytest.raises(subprocess.CalledProcessError):
        run_table.run_table(table_config(tmp_path, ["none"]))
    assert not (tmp_path / "results.json").exists()


def test_unknown_variant_is_named():
    with pytest.raises(ValueError, match=r"unknown variant \['maxmii'\]; choose from maxmi, maxmi_released"):
        run_table.TableConfig(variants=["maxmii"])


def test_kitchen_cells_use_the_kitchen_env(monkeypatch, tmp_path):
    tools = FakeTools()
    monkeypatch.setattr(pipeline, "run_tool", tools)
    config = run_table.TableConfig(tasks=["FrankaKitchen-v1"], variants=["none"], output_dir=tmp_path)
    run_table.run_table(config)
    for tool in ("lerobot-maxmi-demos", "lerobot-eval"):
        assert set(tools.flag(tool, "--env.type")) == {"franka_kitchen"}
    assert pipeline.env_flags("StackCube-v1") == ("--env.type=maniskill", "--env.task=StackCube-v1")


def test_act_reference_trains_on_a_copy_with_environment_state(monkeypatch, tmp_path):
    tools, copies = FakeTools(), []
    monkeypatch.setattr(pipeline, "run_tool", tools)
    monkeypatch.setattr(pipeline, "copy_with_environment_state", lambda *args: copies.append(args))
    run_table.run_table(run_table.TableConfig(variants=["act"], output_dir=tmp_path))
    demos, dataset, repo_id = copies[0]
    assert demos.name == "PickCube-v1_100" and repo_id == f"local/{dataset.name}"
    assert tools.flag("lerobot-train", "--policy.type") == ["act"]
    assert tools.flag("lerobot-train", "--dataset.root") == [str(dataset)]
    assert not tools.flag("lerobot-train", "--policy.context_length")  # a CoTPC option


def test_task_counts_are_means_not_percentages():
    cell = {
        "seen": {"tasks_ge_1": 15.0, "num_tasks_completed": 0.19},
        "unseen": {"tasks_ge_1": 13.0, "num_tasks_completed": 0.13},
    }
    row = run_table.variant_row("none", [cell], ["tasks_ge_1", "num_tasks_completed"])
    assert row == "| none | 1 | 15 / 13 | 0.19 / 0.13 |"
    assert run_table.unit("num_tasks_completed") == "(mean)" and run_table.unit("tasks_ge_1") == "%"


def test_all_tasks_side_by_side_rank_each_task_by_its_headline_metric():
    def cell(task, variant, seed, seen, unseen, metric="success"):
        config = {"task": task, "variant": variant, "seed": seed, "num_demos": 100}
        return {"config": config, "seen": {metric: seen}, "unseen": {metric: unseen}}

    cells = [
        cell("PickCube-v1", "maxmi", 0, 96.0, 37.0),
        cell("PickCube-v1", "maxmi", 1, 94.0, 41.0),
        cell("PickCube-v1", "none", 0, 99.0, 38.0),
        cell("FrankaKitchen-v1", "none", 0, 0.19, 0.13, run_table.NUM_TASKS_COMPLETED),
    ]
    tables = run_table.markdown_tables({str(i): c for i, c in enumerate(cells)})

    assert "| variant | FrankaKitchen-v1 num_tasks_completed (mean) | PickCube-v1 success % |" in tables
    assert "| maxmi | — | 95 ± 1 / 39 ± 3 (2 seeds) |" in tables
    assert "| none | 0.19 / 0.13 | 99 / 38 |" in tables


def test_differences_from_a_baseline_carry_a_welch_interval_over_seeds():
    def cell(variant, seed, unseen):
        config = {"task": "PickCube-v1", "variant": variant, "seed": seed}
        return {"config": config, "seen": {"success": 90.0}, "unseen": {"success": unseen}}

    maxmi, none = [37.0, 41.0, 32.0, 56.0, 44.0], [38.0, 43.0, 39.0, 28.0, 48.0]
    cells = [cell("maxmi", i, v) for i, v in enumerate(maxmi)] + [
        cell("none", i, v) for i, v in enumerate(none)
    ]
    cells.append(cell("uniform", 0, 59.0))
    tables = run_table.markdown_tables({str(i): c for i, c in enumerate(cells)})

    # By hand: difference 2.8, s.e. sqrt(81.5/5 + 54.7/5) = 5.22, 7.7 degrees of freedom, t(0.975) = 2.32.
    assert "### Unseen, minus none: mean difference [95% CI], Welch's t-test" in tables
    assert "| maxmi | +2.8 [-9.3, +14.9], p = 0.61 |" in tables
    assert "| uniform | — |" in tables  # one seed: no spread to test against
    assert "minus last_state" not in tables  # no such cells
