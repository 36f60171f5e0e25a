"""The inference pipeline on a live camera: adapters above :mod:`labrig.pipeline` and :mod:`labrig.protocol`.

* :mod:`labrig.live.sources`: what the live runner reads (a camera, or a :class:`~labrig.live.sources.ChunkTap`
  on a rig session's camera pump).
* :mod:`labrig.live.runner`: :class:`~labrig.live.runner.LiveRunner`, the pipeline in real time
  (skip and late policy, :class:`~labrig.live.runner.LiveStats`).
* :mod:`labrig.live.rig`: the rig file's camera alone, or one probing run alongside; the live
  forces against the F/T sensor.
"""
