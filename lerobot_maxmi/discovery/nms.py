"""Non-maximum suppression of localized concepts (MaxMI §3.4).

Concepts that land close together in time describe the same key state: keep the most confident
one, drop the others, and sort the survivors by time.
"""

from collections.abc import Sequence


def suppress_nearby(frames: Sequence[int], scores: Sequence[float], radius: float) -> list[int]:
    """Greedy NMS: highest score first; a frame within `radius` of a kept frame is dropped."""
    kept: list[int] = []
    for i in sorted(range(len(frames)), key=lambda i: -scores[i]):
        if all(abs(frames[i] - frame) > radius for frame in kept):
            kept.append(frames[i])
    return sorted(kept)


def key_frames(
    frames: Sequence[int],
    scores: Sequence[float],
    episode_length: int,
    radius_fraction: float,
    append_final: bool,
) -> list[int]:
    """An episode's key frames: NMS with a radius relative to its length, plus (optionally) its last frame."""
    kept = suppress_nearby(frames, scores, radius_fraction * episode_length)
    final = episode_length - 1
    if append_final:
        kept = [f for f in kept if final - f > radius_fraction * episode_length] + [final]
    return kept
