"""The distribution installs, LeRobot discovers it, and the shared dataset fixture works."""

import subprocess
import sys

from tests.conftest import STATE_DIM

DISCOVER = """
import sys
from lerobot.envs.configs import EnvConfig
from lerobot.utils.import_utils import register_third_party_plugins
register_third_party_plugins()
env_types = EnvConfig.get_known_choices()
print("lerobot_policy_maxmi" in sys.modules, "lerobot_maxmi" in sys.modules, "maniskill" in env_types)
"""


def test_lerobot_plugin_discovery_imports_our_package():
    result = subprocess.run([sys.executable, "-c", DISCOVER], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["True", "True", "True"], result.stdout + result.stderr


def test_state_dataset_fixture_round_trips(state_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    reloaded = LeRobotDataset(state_dataset.repo_id, root=state_dataset.root)
    assert reloaded.num_episodes == 3
    assert reloaded.num_frames == 75
    assert reloaded[0]["observation.state"].shape == (STATE_DIM,)
