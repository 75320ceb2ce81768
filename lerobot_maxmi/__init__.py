"""MaxMI for LeRobot.

Importing the package (LeRobot does it for every installed `lerobot_policy_*` distribution)
registers our env types, policy types and processor steps with LeRobot's registries.
"""

from lerobot_maxmi.discovery import processor as _discovery_processor  # noqa: F401  (step "maxmi_discovery")
from lerobot_maxmi.envs import configs as _env_configs  # noqa: F401  (env type "maniskill")
from lerobot_maxmi.policies import cotpc as _cotpc  # noqa: F401  (policy types "cotpc", "cotpc_maxmi")
