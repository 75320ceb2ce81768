"""Non-maximum suppression of localized concepts (MaxMI §3.4).

Concepts that land close together in time describe the same key state: keep the most confident
one, drop the others, and sort the survivors by time.
"""

from collections.abc import Sequence


def kept_indices(positions: Sequence[float], scores: Sequence[float], radius: float) -> list[int]:
    """Greedy NMS, highest score first; returns the indices of the survivors, sorted by position."""
    kept: list[int] = []
    for i in sorted(range(len(positions)), key=lambda i: -scores[i]):
        if all(abs(positions[i] - positions[j]) > radius for j in kept):
            kept.append(i)
    return sorted(kept, key=lambda i: positions[i])


def kept_concepts(
    positions: Sequence[float], scores: Sequence[float], radius: float, end: float | None
) -> list[int]:
    """Indices of the concepts NMS keeps; with an `end` (the final frame is appended as a key state),
    also drop those within `radius` of it, since the final frame stands for them."""
    kept = kept_indices(positions, scores, radius)
    return kept if end is None else [i for i in kept if end - positions[i] > radius]


def shared_concepts(
    fractions: Sequence[float], scores: Sequence[float], radius_fraction: float, append_final: bool
) -> list[int]:
    """The concepts kept for a whole dataset, in time order.

    A concept is one dataset-wide entity (one concept embedding shared by every episode), so which
    concepts are duplicates is decided once, on each concept's typical position (`fractions`, a
    fraction of the episode in [0, 1]) and confidence. Every episode then gets the same concepts in
    the same slots, which is what a policy predicting key state k needs.
    """
    return kept_concepts(fractions, scores, radius_fraction, 1.0 if append_final else None)
