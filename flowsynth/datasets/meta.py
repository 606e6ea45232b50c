"""What a stream's sample holds besides its outputs: ``index`` and ``seed`` always, the metadata keys only when asked.

The metadata keys are ``META_OUTPUTS``: ``K`` (3, 3) float32 [px] and ``cam_T_world`` (T, 4, 4) float32 (the
camera of a BouncingThings sample) and ``provenance`` (a JSON string of the sample's scene or draw, some KB a
sample). Name any of them in ``outputs``, or ``META`` ("meta") for all that the dataset's kind has: BouncingThings'
three, a Layers stream's ``provenance``, a mixture's keys every source has. ``ALL`` ("all") names everything: every
output the stream's config can make (for BouncingThings the stereo keys only with ``stereo_baseline`` > 0, the
per-pair keys only with two frames or more; for ``DeviceBatches`` what a batch renders) and the metadata keys.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["ALL", "ALWAYS_KEYS", "META", "META_OUTPUTS", "PROVENANCE", "split_meta"]

ALWAYS_KEYS = ("index", "seed")
"""Keys every sample holds: int64 scalars (a batch: (B,)), the sample's index and its dataset's seed."""
PROVENANCE = "provenance"
META_OUTPUTS = ("K", "cam_T_world", PROVENANCE)
"""The keys a sample holds only when ``outputs`` names them (module docstring)."""
META = "meta"
"""The name in ``outputs`` for every key of ``META_OUTPUTS`` the dataset's kind has."""
ALL = "all"
"""The name in ``outputs`` for every output the stream can make and every metadata key (module docstring)."""


def split_meta(outputs: Sequence[str], kind_meta: Sequence[str], every: Sequence[str] = ()) -> tuple[list[str], bool]:
    """``outputs`` with ``META`` replaced by ``kind_meta`` (the metadata keys of the dataset's kind), ``ALL`` by
    ``every`` (the outputs the stream can make) and ``kind_meta``, and ``provenance`` taken out: (the other keys in
    order, whether provenance was asked for). A string or a non-sequence comes back as it is (the stream's own check
    refuses it)."""
    if isinstance(outputs, str) or not isinstance(outputs, Sequence):
        return outputs, False
    keys: list[str] = []
    for k in outputs:
        keys += list(kind_meta) if k == META else [*every, *kind_meta] if k == ALL else [k]
    keys = list(dict.fromkeys(keys))
    return [k for k in keys if k != PROVENANCE], PROVENANCE in keys
