"""One demonstration episode with its ground-truth key frames, as the dataset writer takes it.

Frame conventions (the recorder and the converter share them): frame t holds the observation before
action t, and `successes[t]` is the success flag after it. A sub-goal's key frame is the first frame
whose observation satisfies the sub-goal, i.e. one past the step whose flag first fired (CoTPC's
"+1"). The last key frame is always the episode's final frame, named "final".
"""

from dataclasses import dataclass

import numpy as np

FINAL = "final"


@dataclass
class Episode:
    states: np.ndarray  # (T, state_dim) float32
    actions: np.ndarray  # (T, action_dim) float32
    successes: np.ndarray  # (T,) bool: success after the frame's action
    key_frames: list[int]  # first frame of each sub-goal, then T - 1
    key_frame_names: list[str]  # sub-goal names, then FINAL
    seed: int | None = None  # env seed that reproduces the episode, when known
