"""Losses for the depth network and its depth errors in mm.

Contact-aware L1 (the paper's): per map, the mean absolute error over the contact cells
(L_c) and over the rest (L_nc), combined as lambda_c L_c + (1 - lambda_c) L_nc, so a small
contact weighs as much as a large one. Over a batch, L_c is averaged over the maps that
have contact cells and L_nc over the maps that have non-contact cells (a map without
contact contributes no L_c term rather than a zero). Uniform L1: the plain mean over all
cells, for comparison.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

LOSSES = ("contact", "uniform")
DEFAULT_LAMBDA_C = 0.5


def contact_aware_l1(pred: Any, target: Any, contact: Any, lambda_c: float = DEFAULT_LAMBDA_C) -> Any:
    """(B, H, W) tensors (or (B, 1, H, W)); ``contact`` is 1 in contact. Returns a scalar tensor."""
    import torch

    err = (pred - target).abs().flatten(1)
    c = contact.flatten(1).to(err.dtype)
    nc = 1.0 - c
    n_c, n_nc = c.sum(1), nc.sum(1)
    has_c, has_nc = n_c > 0, n_nc > 0
    zero = err.new_zeros(())
    l_c = ((err * c).sum(1)[has_c] / n_c[has_c]).mean() if bool(has_c.any()) else zero
    l_nc = ((err * nc).sum(1)[has_nc] / n_nc[has_nc]).mean() if bool(has_nc.any()) else zero
    return torch.as_tensor(lambda_c, dtype=err.dtype) * l_c + (1.0 - lambda_c) * l_nc


def uniform_l1(pred: Any, target: Any, contact: Any = None) -> Any:
    """Plain L1 over every cell."""
    return (pred - target).abs().mean()


def loss_function(name: str, lambda_c: float = DEFAULT_LAMBDA_C) -> Any:
    if name == "contact":
        return lambda p, t, c: contact_aware_l1(p, t, c, lambda_c)
    if name == "uniform":
        return uniform_l1
    raise ValueError(f"loss must be one of {', '.join(LOSSES)}, not {name!r}")


def depth_errors_mm(pred_mm: npt.NDArray[np.floating], true_mm: npt.NDArray[np.floating],
                    contact: npt.NDArray[np.integer]) -> dict[str, float | int | None]:
    """Per-map mean absolute errors (mm) over all cells, contact cells and the rest: mean and std over maps.

    Maps without contact count in total and non-contact only (``n_contact_maps`` says how many had it).
    """
    err = np.abs(np.asarray(pred_mm, np.float64) - np.asarray(true_mm, np.float64)).reshape(len(pred_mm), -1)
    c = np.asarray(contact).reshape(len(pred_mm), -1) > 0
    total = err.mean(1)
    n_c = c.sum(1)
    in_c = np.array([e[m].mean() for e, m in zip(err, c) if m.any()])
    out_c = np.array([e[~m].mean() for e, m in zip(err, c) if (~m).any()])

    def stat(a: npt.NDArray[np.float64]) -> tuple[float | None, float | None]:
        return (round(float(a.mean()), 5), round(float(a.std()), 5)) if a.size else (None, None)

    (t_m, t_s), (c_m, c_s), (n_m, n_s) = stat(total), stat(in_c), stat(out_c)
    return {"total_mm": t_m, "total_std_mm": t_s, "contact_mm": c_m, "contact_std_mm": c_s,
            "noncontact_mm": n_m, "noncontact_std_mm": n_s, "maps": len(pred_mm),
            "n_contact_maps": int((n_c > 0).sum())}
