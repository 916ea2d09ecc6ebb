"""parq_runtime: run exported PARQ models with numpy and onnxruntime (never imports torch)."""

__version__ = "0.1.0"

from .errors import ParqError  # noqa: E402

__all__ = ["ParqError", "__version__"]
