"""onnxruntime sessions for the two graphs, with the options the runtime uses.

Choices (measured in ``benchmarks/session_options.py``; see the README):
* graph optimisation ORT_ENABLE_ALL: folds the frozen batch norms into the convolutions and
  picks the blocked (NCHWc) convolution kernels;
* intra-op threads: all physical cores unless ``threads`` says otherwise; inter-op 1 (the graphs
  are chains, there is nothing to run side by side);
* spinning (``session.intra_op.allow_spinning``) off unless asked for: two sessions share the
  cores, and a pool that spins after its run steals them from the other one (see Detector).
"""
from __future__ import annotations

import os

import onnxruntime as ort

from .errors import ParqError

GRAPH_OPTIMIZATION = ort.GraphOptimizationLevel.ORT_ENABLE_ALL


def session_options(threads: int | None = None, spinning: bool = False) -> ort.SessionOptions:
    options = ort.SessionOptions()
    options.graph_optimization_level = GRAPH_OPTIMIZATION
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    if threads is not None:
        options.intra_op_num_threads = int(threads)
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    options.log_severity_level = 3
    return options


def resolve_providers(providers) -> list:
    """None -> CPU; names are checked against what this onnxruntime build offers."""
    if providers is None:
        return ["CPUExecutionProvider"]
    if isinstance(providers, str):
        providers = [p.strip() for p in providers.split(",") if p.strip()]
    available = ort.get_available_providers()
    names = [p if isinstance(p, str) else p[0] for p in providers]
    unknown = [n for n in names if n not in available]
    if unknown:
        raise ParqError(f"execution provider {', '.join(unknown)} is not available in this "
                        f"onnxruntime build (available: {', '.join(available)})")
    if "CPUExecutionProvider" not in names:
        providers = list(providers) + ["CPUExecutionProvider"]
    return list(providers)


def create(path, threads=None, providers=None, spinning=False) -> ort.InferenceSession:
    if threads is not None and (int(threads) < 1 or int(threads) > 4 * (os.cpu_count() or 1)):
        raise ParqError(f"--threads {threads}: use 1 to {4 * (os.cpu_count() or 1)}")
    try:
        return ort.InferenceSession(str(path), session_options(threads, spinning),
                                    providers=resolve_providers(providers))
    except ParqError:
        raise
    except Exception as e:  # onnxruntime raises its own Fail/InvalidGraph/... types
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ParqError(f"{path}: onnxruntime cannot load it ({first})") from None
