"""parq_runtime: run exported PARQ models with numpy and onnxruntime (never imports torch).

    from parq_runtime import Detector
    det = Detector("models/parq-demo")
    result = det.detect(images, intrinsics, cam_to_world, iters=2, queries=64)
"""

__version__ = "0.1.0"

from .errors import ParqError  # noqa: E402

__all__ = ["Detector", "DetectionResult", "ParqError", "__version__"]


def __getattr__(name):
    # Detector pulls in onnxruntime; importing it lazily keeps `parq_runtime.errors` and the
    # geometry light for parq_export and the tools.
    if name in ("Detector", "DetectionResult"):
        from . import detector
        return getattr(detector, name)
    raise AttributeError(f"module 'parq_runtime' has no attribute {name!r}")
