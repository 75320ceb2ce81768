"""`lerobot-maxmi-discover` end to end on tiny state-only datasets (tiny KSL-Net, few steps)."""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import draccus
import numpy as np
import pytest
import torch

from lerobot_maxmi.discovery import annotate as annotate_module
from lerobot_maxmi.discovery.annotate import AnnotateConfig, annotate, check_state_feature
from lerobot_maxmi.discovery.processor import KEY_FRAMES, KEY_STATES, load_localizer
from lerobot_maxmi.episode_metadata import GT_KEY_FRAMES, read_episode_column, write_episode_columns
from lerobot_maxmi.pipeline import FILE_PER_EPISODE_MB

TINY = [
    "--discovery.num_concepts=3",
    "--discovery.steps=3",
    "--discovery.batch_size=5",
    "--discovery.estimator=gaussian",
    "--discovery.model.embed_dim=4",
    "--discovery.model.encoder_dims=[16]",
    "--discovery.model.head_dims=[16]",
]


def make_dataset(
    root: Path, lengths=(20, 25, 30, 22, 27), state_dim=4, nan_episode=None, gt=True, file_size_mb=None
):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {"observation.state": {"dtype": "float32", "shape": (state_dim,), "names": None}}
    dataset = LeRobotDataset.create(
        repo_id="local/src",
        fps=10,
        features=features,
        root=root,
        use_videos=False,
        data_files_size_in_mb=file_size_mb,
    )
    rng = np.random.default_rng(0)
    for episode, length in enumerate(lengths):
        states = np.cumsum(rng.normal(size=(length, state_dim)), axis=0).astype(np.float32)
        if episode == nan_episode:
            states[3, 0] = np.nan
        for state in states:
            dataset.add_frame({"observation.state": state, "task": "test"})
        dataset.save_episode()
    dataset.finalize()
    if gt:
        write_episode_columns(root, {GT_KEY_FRAMES: [[n // 2, n - 1] for n in lengths]})
    return root


def config(source: Path, output: Path, *args: str) -> AnnotateConfig:
    return draccus.parse(
        AnnotateConfig,
        args=[
            "--dataset.repo_id=local/src",
            f"--dataset.root={source}",
            "--output.repo_id=local/out",
            f"--output.root={output}",
            *TINY,
            *args,
        ],
    )


def fingerprint(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.md5(p.read_bytes()).hexdigest()
        for p in root.rglob("*")
        if p.is_file()
    }


def load(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset("local/out", root=root)


@pytest.fixture
def source(tmp_path):
    return make_dataset(tmp_path / "src")


def test_maxmi_annotation_writes_key_states_metadata_stats_localizer_and_plots(source, tmp_path):
    before = fingerprint(source)
    out = annotate(config(source, tmp_path / "out", "--plot=true"))
    assert fingerprint(source) == before  # the source is only read

    dataset = load(out)
    frames = read_episode_column(out, KEY_FRAMES)
    assert set(read_episode_column(out, "maxmi/selector").values()) == {"maxmi"}
    num_key_states = len(frames[0])
    assert all(len(f) == num_key_states for f in frames.values())  # same concepts in every episode
    feature = dataset.meta.features[KEY_STATES]
    assert feature["shape"] == (num_key_states * 4,) and feature["names"][:2] == ["key0.dim0", "key0.dim1"]

    states = torch.stack([dataset[i]["observation.state"] for i in range(len(dataset))])
    key_states = torch.stack([dataset[i][KEY_STATES] for i in range(len(dataset))])
    episode = torch.tensor([int(dataset[i]["episode_index"]) for i in range(len(dataset))])
    for index, episode_frames in frames.items():
        rows = (episode == index).nonzero().flatten()
        expected = states[rows[0] + torch.tensor(episode_frames)].flatten()
        assert torch.equal(key_states[rows], expected.expand(len(rows), -1))  # same for every frame
        assert episode_frames[-1] == len(rows) - 1  # the final frame closes the list

    state_stats, key_stats = dataset.meta.stats["observation.state"], dataset.meta.stats[KEY_STATES]
    np.testing.assert_allclose(key_stats["mean"], np.tile(state_stats["mean"], num_key_states))
    np.testing.assert_allclose(key_stats["std"], np.tile(state_stats["std"], num_key_states))
    assert (out / "maxmi_localizer" / "maxmi_localizer.json").is_file()
    record = json.loads((out / "maxmi_localizer" / "discovery_config.json").read_text())
    assert record["discovery"]["num_concepts"] == 3 and record["discovery"]["model"]["encoder_dims"] == [16]
    assert record["torch_threads"] == torch.get_num_threads() and record["processes"] == 1
    assert sorted(p.name for p in (out / "plots").iterdir()) == [f"episode_{i:06d}.png" for i in range(5)]


def test_same_seed_same_key_frames_and_saved_localizer_annotates_without_training(
    source, tmp_path, monkeypatch
):
    first = annotate(config(source, tmp_path / "a"))
    second = annotate(config(source, tmp_path / "b"))
    assert read_episode_column(first, KEY_FRAMES) == read_episode_column(second, KEY_FRAMES)

    def no_training(*_args, **_kwargs):
        raise AssertionError("a saved localizer must not be retrained")

    monkeypatch.setattr("lerobot_maxmi.discovery.train.train_localizer", no_training)
    reused = annotate(
        config(source, tmp_path / "c", f"--discovery.pretrained_path={first / 'maxmi_localizer'}")
    )
    assert read_episode_column(reused, KEY_FRAMES) == read_episode_column(first, KEY_FRAMES)
    assert not (reused / "maxmi_localizer" / "discovery_config.json").exists()  # nothing was trained


def test_saved_step_runs_in_a_lerobot_pipeline(source, tmp_path):
    from lerobot.processor import DataProcessorPipeline, TransitionKey, create_transition

    out = annotate(config(source, tmp_path / "out"))
    step = load_localizer(out / "maxmi_localizer")
    pipeline = DataProcessorPipeline(steps=[step], to_transition=lambda t: t, to_output=lambda t: t)
    states = load(out).hf_dataset.with_format("torch")["observation.state"][:20]  # episode 0
    result = pipeline(create_transition(observation={"observation.state": states}))
    frames = read_episode_column(out, KEY_FRAMES)[0]
    assert result[TransitionKey.COMPLEMENTARY_DATA][KEY_FRAMES] == frames
    assert torch.equal(result[TransitionKey.OBSERVATION][KEY_STATES], states[frames].flatten())


@pytest.mark.parametrize(
    ("selector", "expected"),
    [
        ("last_state", {0: [19], 1: [24], 2: [29], 3: [21], 4: [26]}),
        (
            "uniform",
            {
                0: [5, 10, 14, 19],
                1: [6, 12, 18, 24],
                2: [7, 14, 22, 29],
                3: [5, 10, 16, 21],
                4: [6, 13, 20, 26],
            },
        ),
        ("ground_truth", {0: [10, 19], 1: [12, 24], 2: [15, 29], 3: [11, 21], 4: [13, 26]}),
    ],
)
def test_baseline_selectors_write_the_same_format(source, tmp_path, selector, expected):
    out = annotate(config(source, tmp_path / selector, f"--selector={selector}"))
    assert read_episode_column(out, KEY_FRAMES) == expected
    assert load(out).meta.features[KEY_STATES]["shape"] == (len(expected[0]) * 4,)


def test_variable_counts_are_padded_with_the_last_key_state(source, tmp_path):
    out = annotate(config(source, tmp_path / "awe", "--selector=awe", "--awe.error_threshold=0.3"))
    frames = read_episode_column(out, KEY_FRAMES)
    num_key_states = max(len(f) for f in frames.values())
    dataset = load(out)
    assert dataset.meta.features[KEY_STATES]["shape"] == (num_key_states * 4,)
    shortest = min(frames, key=lambda i: len(frames[i]))
    start = int(dataset.meta.episodes["dataset_from_index"][shortest])
    key_states = dataset[start][KEY_STATES].view(num_key_states, 4)
    final_state = dataset[start + frames[shortest][-1]]["observation.state"]
    assert torch.equal(key_states[-1], final_state) and torch.equal(
        key_states[len(frames[shortest]) - 1], final_state
    )


def test_a_file_per_episode_stays_a_file_per_episode(tmp_path):
    """The layout a stream needs to feed several loader workers (docs/cotpc.md, "Speed") survives."""
    source = make_dataset(tmp_path / "src", file_size_mb=FILE_PER_EPISODE_MB)
    out = annotate(config(source, tmp_path / "out", "--selector=ground_truth"))
    assert len(list(out.glob("data/*/*.parquet"))) == len(list(source.glob("data/*/*.parquet"))) == 5
    dataset, frames = load(out), read_episode_column(out, KEY_FRAMES)
    for episode, start in enumerate(dataset.meta.episodes["dataset_from_index"]):
        key_states = dataset[int(start)][KEY_STATES].view(-1, 4)
        expected = torch.stack([dataset[int(start) + f]["observation.state"] for f in frames[episode]])
        assert torch.equal(key_states, expected)


def test_ground_truth_selector_needs_ground_truth(tmp_path):
    source = make_dataset(tmp_path / "src", gt=False)
    with pytest.raises(ValueError, match="needs per-episode 'gt/key_frames'"):
        annotate(config(source, tmp_path / "out", "--selector=ground_truth"))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("dataset_kwargs", "args", "message"),
    [
        ({}, ["--state_key=observation.joints"], "no 'observation.joints' feature"),
        ({"lengths": (20, 2, 30, 22, 27)}, [], "episode 1 has 2 frames, fewer than the 3 key states"),
        ({"nan_episode": 1}, [], "episode 1 has NaN or inf states"),
        ({"lengths": (20, 25, 30)}, [], "MaxMI estimates MI across episodes and needs batches of at least 4"),
    ],
)
def test_bad_input_fails_clearly_and_leaves_everything_untouched(tmp_path, dataset_kwargs, args, message):
    source = make_dataset(tmp_path / "src", **dataset_kwargs)
    before = fingerprint(source)
    with pytest.raises(ValueError, match=message):
        annotate(config(source, tmp_path / "out", *args))
    assert fingerprint(source) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no output, no staging left behind


def test_video_only_dataset_is_rejected():
    features = {"observation.images.top": {"dtype": "video", "shape": (3, 8, 8), "names": None}}
    with pytest.raises(ValueError, match="video/image features .* cannot be used"):
        check_state_feature(features, "observation.state")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--discovery.num_concepts=0"], "num_concepts must be >= 1"),
        (["--output.root={source}"], "must not be, contain or lie inside the source"),
        (["--selector=clip"], "unknown selector 'clip'"),
    ],
)
def test_bad_arguments_fail_clearly(source, tmp_path, args, message):
    with pytest.raises(draccus.utils.ParsingError) as raised:
        config(source, tmp_path / "out", *[a.format(source=source) for a in args])
    assert isinstance(raised.value.__cause__, ValueError)
    assert message in str(raised.value.__cause__)


def test_existing_output_needs_overwrite(source, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="--overwrite=true"):
        annotate(config(source, out, "--selector=last_state"))
    assert (out / "old.txt").read_text() == "keep me"
    annotate(config(source, out, "--selector=last_state", "--overwrite=true"))
    assert not (out / "old.txt").exists() and read_episode_column(out, KEY_FRAMES)[0] == [19]


def test_an_annotated_dataset_is_not_annotated_again(source, tmp_path):
    out = annotate(config(source, tmp_path / "out", "--selector=last_state"))
    with pytest.raises(ValueError, match="already has 'observation.key_states'"):
        annotate(
            draccus.parse(
                AnnotateConfig,
                args=[
                    "--dataset.repo_id=local/out",
                    f"--dataset.root={out}",
                    "--output.repo_id=local/again",
                    f"--output.root={tmp_path / 'again'}",
                ],
            )
        )


def test_cli_reports_errors_without_a_traceback(source, tmp_path, monkeypatch):
    argv = ["lerobot-maxmi-discover", "--dataset.repo_id=local/src", f"--dataset.root={source}"]
    argv += ["--output.repo_id=local/out", f"--output.root={source}"]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit, match="lerobot-maxmi-discover: the output"):
        annotate_module.main()


def test_push_uploads_dataset_and_localizer(source, tmp_path, monkeypatch):
    from huggingface_hub import HfApi
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    calls = []
    monkeypatch.setattr(
        LeRobotDataset, "push_to_hub", lambda self, **kw: calls.append(("dataset", self.repo_id))
    )
    monkeypatch.setattr(HfApi, "create_repo", lambda self, repo_id, **kw: calls.append(("create", repo_id)))
    monkeypatch.setattr(
        HfApi,
        "upload_folder",
        lambda self, **kw: calls.append((kw["repo_type"], kw["repo_id"], kw["folder_path"])),
    )
    out = annotate(config(source, tmp_path / "out", "--push_to_hub=true"))
    assert calls == [
        ("dataset", "local/out"),
        ("create", "local/out"),
        ("model", "local/out", out / "maxmi_localizer"),
    ]


def test_push_offline_fails_clearly_after_the_dataset_is_complete(source, tmp_path):
    with pytest.raises(RuntimeError, match="complete at .*out, but pushing it to local/out failed"):
        annotate(config(source, tmp_path / "out", "--selector=last_state", "--push_to_hub=true"))
    assert read_episode_column(tmp_path / "out", KEY_FRAMES)[0] == [19]


@pytest.mark.slow
def test_accelerate_launch_trains_in_two_processes_and_writes_once(source, tmp_path):
    """`accelerate launch --num_processes=2 lerobot-maxmi-discover ...`, on CPU processes (gloo) so that
    it runs anywhere: both processes train, only the main one writes the dataset."""
    bin_dir = Path(sys.executable).parent
    output = tmp_path / "launched" / "out"
    command = [
        str(bin_dir / "accelerate"), "launch", "--multi_gpu", "--num_processes=2", "--num_machines=1",
        "--mixed_precision=no", "--dynamo_backend=no", str(bin_dir / "lerobot-maxmi-discover"),
        "--dataset.repo_id=local/src", f"--dataset.root={source}", "--output.repo_id=local/out",
        f"--output.root={output}", *TINY,
    ]  # fmt: skip
    environment = {**os.environ, "CUDA_VISIBLE_DEVICES": "", "OMP_NUM_THREADS": "1"}
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env=environment)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "(2 process(es), 1 torch thread(s) each)" in result.stderr  # the main process's training log
    assert result.stderr.count("annotated dataset written") == 1
    assert sorted(p.name for p in output.parent.iterdir()) == ["out"]  # no staging left behind
    assert len(read_episode_column(output, KEY_FRAMES)) == 5
    record = json.loads((output / "maxmi_localizer" / "discovery_config.json").read_text())
    assert (record["processes"], record["torch_threads"]) == (2, 1)
