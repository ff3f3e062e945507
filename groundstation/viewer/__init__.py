"""The viewer: what is drawn (:mod:`scene`, pure), how (:mod:`window`, :mod:`headless`), and the
bus-facing shell (``groundstation.runtime.workers.viewer``, ``groundstation view``). The viewer
only subscribes: it never sends anything others wait for, so it can neither block nor take down
the pipeline.

Submodules are not imported here: :mod:`scene` loads without Open3D or ZeroMQ.
"""
