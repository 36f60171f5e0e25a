"""The inference pipeline: its stages as pure functions on arrays, and the runtime that streams windows through them.

Stages:

* :mod:`labrig.pipeline.sae`: polarity-separated Surface of Active Events (sensor, ROI, network grid).
* :mod:`labrig.pipeline.tracking`: the paper's patch-centroid marker tracker and a circle-fit baseline.
* :mod:`labrig.pipeline.evetac`: Evetac's published dot tracker (a baseline).
* :mod:`labrig.pipeline.depthnet` and :mod:`labrig.pipeline.depth_sources`: the normal-displacement map per window;
  :mod:`labrig.pipeline.model_card`: the network's model card, read and checked once.
* :mod:`labrig.pipeline.displacement`: tracked pixels + normal displacement + camera -> 3D marker displacements.
* :mod:`labrig.pipeline.ifem`: the gel's condensed stiffness K at the markers (hex8, B-bar, cached).
* :mod:`labrig.pipeline.forces`: F = K U, net force, contact location.

Runtime:

* :mod:`labrig.pipeline.windows`: every way a stream is cut into windows (:class:`~labrig.pipeline.windows.WindowSpec`).
* :mod:`labrig.pipeline.runtime`: :class:`~labrig.pipeline.runtime.Pipeline` (front and back stages),
  in two threads through :mod:`labrig.pipeline.front_thread`.
* :mod:`labrig.pipeline.run_setup`: the camera, rest pixels and gel law of a run; :mod:`labrig.pipeline.results`: result files.

The live camera adapters are :mod:`labrig.live`, above this package and :mod:`labrig.protocol`.
"""
