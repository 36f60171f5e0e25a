"""The inference pipeline's stages as pure functions on arrays.

* :mod:`labrig.pipeline.sae`: polarity-separated Surface of Active Events (sensor, ROI, network grid).
* :mod:`labrig.pipeline.tracking`: the paper's patch-centroid marker tracker and an Evetac-style baseline.
* :mod:`labrig.pipeline.displacement`: tracked pixels + normal displacement + camera -> 3D marker displacements.
* :mod:`labrig.pipeline.ifem`: the gel's condensed stiffness K at the markers (hex8, B-bar, cached).
* :mod:`labrig.pipeline.forces`: F = K U, net force, contact location.
"""
