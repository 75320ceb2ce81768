"""AWE waypoint selection (Shi et al., "Waypoint-Based Imitation Learning", CoRL 2023), over states.

AWE's dynamic program: the fewest waypoints such that every frame lies within `error_threshold`
of the straight segment between the waypoints around it (its geometric point-to-segment error,
maximum over frames). The `waypoint-extraction` wheel on PyPI cannot be used here: it imports
robosuite and wandb at import time and installs top-level `utils`/`act` packages. This is a
re-implementation of its `dp_waypoint_selection` with the position-only geometric error, on any
state vector; AWE's gripper open/close frames are not added (they need actions).
"""

import torch
from torch import Tensor


def segment_errors(points: Tensor, end: int) -> Tensor:
    """(end,): for each start k < end, the largest distance of points[k..end] to the segment k→end."""
    starts = points[:end]  # (k, D)
    segments = points[end] - starts  # (k, D)
    offsets = points[None, : end + 1] - starts[:, None]  # (k, j, D)
    squared_length = segments.square().sum(-1, keepdim=True).clamp_min(1e-12)  # (k, 1)
    along = ((offsets * segments[:, None]).sum(-1) / squared_length).clamp(0, 1)  # (k, j)
    distances = (offsets - along[..., None] * segments[:, None]).norm(dim=-1)  # (k, j)
    before_start = torch.arange(end + 1)[None, :] < torch.arange(end)[:, None]
    return distances.masked_fill(before_start, 0).amax(dim=1)


def dp_waypoints(points: Tensor, error_threshold: float) -> list[int]:
    """The fewest waypoints within the threshold; frame 0 is the implicit start, the last frame is kept."""
    length = len(points)
    count = torch.zeros(length)
    previous = torch.zeros(length, dtype=torch.long)
    for end in range(1, length):
        cost = (count[:end] + 1).masked_fill(segment_errors(points, end) > error_threshold, float("inf"))
        previous[end] = cost.argmin()  # adjacent frames always fit, so some start is feasible
        count[end] = cost[previous[end]]
    waypoints, frame = [], length - 1
    while frame > 0:
        waypoints.append(frame)
        frame = int(previous[frame])
    return waypoints[::-1]
