"""Reproducible train/val/test assignment of a campaign's recordings.

The split is a function of the recordings (their strata, normally the indenter),
the split counts and the seed only: the same campaign file gives the same split,
another seed gives another one.

How: the recordings of each stratum are shuffled (seeded), the strata are laid
end to end in a seeded order, and the sequence is dealt out so that every prefix
holds each split in proportion to its count (at each step the split furthest
behind its share takes the next recording). Totals are exact, and each stratum
gets its proportional share of every split to within one recording, so once a
stratum holds more than about ``n / count`` recordings it appears in that split.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence

import numpy as np

from labrig.dataset import SPLITS

#: The paper's split: 154/52/13 of 219 recordings.
PAPER_SPLIT: dict[str, float] = {"train": 154 / 219, "val": 52 / 219, "test": 13 / 219}


def split_counts(n: int, fractions: Mapping[str, float] = PAPER_SPLIT, *, at_least_one: bool = True) -> dict[str, int]:
    """Counts per split for ``n`` recordings from ``fractions`` (summing to 1).

    Largest remainders; with ``at_least_one`` every split with a positive
    fraction gets a recording when ``n`` allows it (taken from the largest split),
    so a 6-recording demo still has a test recording.
    """
    names = [s for s in SPLITS if s in fractions] + [s for s in fractions if s not in SPLITS]
    exact = {s: n * float(fractions[s]) for s in names}
    counts = {s: int(np.floor(exact[s] + 1e-9)) for s in names}
    by_remainder = sorted(names, key=lambda s: (-(exact[s] - counts[s]), names.index(s)))
    for s in by_remainder[: n - sum(counts.values())]:
        counts[s] += 1
    if at_least_one:
        wanted = [s for s in names if fractions[s] > 0]
        if n >= len(wanted):
            for s in wanted:
                if counts[s] == 0:
                    donor = max(names, key=lambda d: (counts[d], -names.index(d)))
                    counts[donor] -= 1
                    counts[s] += 1
    return counts


def assign_splits(strata: Sequence[Hashable], counts: Mapping[str, int], seed: int) -> list[str]:
    """The split of each item, given each item's stratum; ``sum(counts) == len(strata)``."""
    n = len(strata)
    names = list(counts)
    if sum(counts.values()) != n or any(c < 0 for c in counts.values()):
        raise ValueError(f"split counts {dict(counts)} do not cover {n} items")
    rng = np.random.default_rng(seed)
    groups: dict[Hashable, list[int]] = {}
    for i, key in enumerate(strata):
        groups.setdefault(key, []).append(i)
    order: list[int] = []
    keys = sorted(groups, key=repr)
    for k in rng.permutation(len(keys)):
        members = groups[keys[int(k)]]
        order.extend(members[int(j)] for j in rng.permutation(len(members)))
    out = [""] * n
    taken = dict.fromkeys(names, 0)
    for step, item in enumerate(order):
        behind = max(names, key=lambda s: ((step + 1) * counts[s] / n - taken[s], counts[s]))
        taken[behind] += 1
        out[item] = behind
    assert taken == dict(counts), (taken, counts)
    return out
