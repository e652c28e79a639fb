"""Hand detector: RGB-D frames -> 21 3-D hand landmarks with per-landmark visibility.

MediaPipe's palm-detection and hand-landmark models (Apache-2.0, converted to ONNX by
``handkse models prepare``) on ONNX Runtime, depth back-projection and a visibility estimate
(paper section III.A.1). Library: :class:`services.detector.pipeline.HandPipeline`; services:
``handkse detector`` (:mod:`services.detector.service`) and ``handkse camera``
(:mod:`services.detector.camera`). Nothing heavy is imported here.
"""
