"""The shared physics core: what the virtual rig, ground truth, calibration and the pipeline all stand on.

* :mod:`~labrig.physics.camera`: the pinhole camera with OpenCV distortion.
* :mod:`~labrig.physics.mechanics`: contact mechanics of a rigid indenter on the gel
  (kernels, layer and half-space, normal and tangential solvers, contact tables).
* :mod:`~labrig.physics.geometry`: the nominal rig geometry (the gel in the machine frame).
* :mod:`~labrig.physics.grid`: the network grid (the ROI resized to the depth network's grid).
* :mod:`~labrig.physics.target`: the intrinsic-calibration target's geometry.

Pure: it imports numpy, scipy and, from labrig, only the configuration, frames,
errors and indenter definitions; never the simulator, devices or pipeline.
"""
