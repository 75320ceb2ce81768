"""Shared fixtures. Tests never touch the network: the hub runs in offline mode."""

import importlib.util
import os
import sys
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"  # before any huggingface_hub / lerobot import

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

STATE_DIM = 6
ACTION_DIM = 3


@pytest.fixture
def state_dataset(tmp_path):
    """A small state-only LeRobotDataset (3 episodes of 20-30 frames) written to a temp dir."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
        "action": {"dtype": "float32", "shape": (ACTION_DIM,), "names": None},
    }
    dataset = LeRobotDataset.create(
        repo_id="local/test_states", fps=10, features=features, root=tmp_path / "dataset", use_videos=False
    )
    rng = np.random.default_rng(0)
    for length in (20, 25, 30):
        for state in np.cumsum(rng.normal(size=(length, STATE_DIM)), axis=0).astype(np.float32):
            dataset.add_frame(
                {
                    "observation.state": state,
                    "action": rng.normal(size=ACTION_DIM).astype(np.float32),
                    "task": "test",
                }
            )
        dataset.save_episode()
    dataset.finalize()
    return dataset


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(0)


def load_benchmark(name: str):
    """A script under `benchmarks/` (not a package) imported as a module."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    if str(path.parent) not in sys.path:  # benchmarks import each other, as they do when run as scripts
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
