"""Entry point LeRobot auto-imports (distribution name prefix ``lerobot_policy_``)."""

import lerobot_maxmi  # noqa: F401  (importing registers every policy, env and processor step)
