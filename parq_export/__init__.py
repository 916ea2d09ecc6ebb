"""parq_export: the PARQ model in PyTorch, checkpoint loading and ONNX export."""

from parq_runtime import __version__  # one version for the whole distribution

__all__ = ["__version__"]
