"""The observation both env types return: the simulator state, under the two keys LeRobot reads.

`agent_pos` becomes `observation.state`, what CoTPC and discovery use. The same vector is also given as
`environment_state` (`observation.environment_state`): LeRobot's ACT and Diffusion policies need that
input when there are no images, so they train and evaluate on these tasks as outside references.
"""

import numpy as np
from gymnasium import spaces
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

STATE_KEYS = {
    "agent_pos": (FeatureType.STATE, OBS_STATE),
    "environment_state": (FeatureType.ENV, OBS_ENV_STATE),
}


def features_map() -> dict[str, str]:
    """Env observation key -> LeRobot feature name (an EnvConfig's `features_map`)."""
    return {ACTION: ACTION, **{key: name for key, (_, name) in STATE_KEYS.items()}}


def add_state_features(features: dict[str, PolicyFeature], state_dim: int) -> None:
    for key, (feature_type, _) in STATE_KEYS.items():
        features.setdefault(key, PolicyFeature(feature_type, (state_dim,)))


def state_observation_space(state_shape: tuple[int, ...]) -> spaces.Dict:
    box = spaces.Box(-np.inf, np.inf, shape=state_shape, dtype=np.float32)
    return spaces.Dict(dict.fromkeys(STATE_KEYS, box))


def state_observation(state: np.ndarray) -> dict[str, np.ndarray]:
    state = np.asarray(state, dtype=np.float32)
    return dict.fromkeys(STATE_KEYS, state)
