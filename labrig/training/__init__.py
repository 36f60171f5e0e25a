"""Training the depth network (``labrig train``): sampling, losses, the training loop and export.

* :mod:`data` -- a campaign's recordings and sidecars; random event windows as SAEs with
  the nearest ground truth (the paper's sampling); a torch ``IterableDataset``.
* :mod:`loss` -- contact-aware and uniform L1; depth errors in mm.
* :mod:`trainer` -- Adam, checkpoints and resume, validation, ONNX export with a model card.

See docs/depthnet.md.
"""

from labrig.training.loss import LOSSES, contact_aware_l1, depth_errors_mm, uniform_l1
from labrig.training.trainer import TrainConfig, output_paths, train

__all__ = ["LOSSES", "TrainConfig", "contact_aware_l1", "depth_errors_mm", "output_paths", "train", "uniform_l1"]
