"""Sets of flat pixel indices: O(n) de-duplication without sorting."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Index = npt.NDArray[np.int64]


def unique_indices(indices: Index, scratch: Index) -> Index:
    """Distinct values of ``indices`` (first-seen order not kept), in O(n) without sorting.

    ``scratch`` is a caller-owned int64 work array longer than the largest index;
    its contents are overwritten.
    """
    order = np.arange(indices.size, dtype=np.int64)
    scratch[indices] = order
    return indices[scratch[indices] == order]
