"""Mutual-information estimation: `load_estimator(name)(x, y)` and `state_mi`."""

from lerobot_maxmi.mi.estimators import ESTIMATORS, MIEstimator, load_estimator, load_infonet
from lerobot_maxmi.mi.infonet import InfoNet
from lerobot_maxmi.mi.state_mi import STATE_MI_MODES, state_mi

__all__ = [
    "ESTIMATORS",
    "STATE_MI_MODES",
    "InfoNet",
    "MIEstimator",
    "load_estimator",
    "load_infonet",
    "state_mi",
]
