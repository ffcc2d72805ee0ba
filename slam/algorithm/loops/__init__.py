"""Loop closure: candidates, geometric verification and place descriptors, one detector per
sensor kind (:data:`slam.algorithm.loops.registry.LOOP_DETECTORS`).

The package itself imports nothing, so that reading its config (``loops.config``) costs no
detector's imports.
"""
