"""onnxruntime sessions for the two graphs, with the options the runtime uses.

Choices (measured in ``benchmarks/session_options.py``; see docs/speed.md):
* graph optimisation ORT_ENABLE_ALL: folds the frozen batch norms into the convolutions and
  picks the blocked (NCHWc) convolution kernels;
* intra-op threads: all physical cores unless ``threads`` says otherwise; inter-op 1 (the graphs
  are chains, there is nothing to run side by side);
* spinning (``session.intra_op.allow_spinning``) off unless asked for: two sessions share the
  cores, and a pool that spins after its run steals them from the other one (see Detector).
"""
from __future__ import annotations

import functools
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


# onnxruntime's CUDA provider multiplies fp32 in TF32 unless told otherwise; on an H200 that
# moved the authors' configuration's box centres by up to 6.3e-3 m and sizes by 5.2e-2 against
# the torch model (7.6e-6 m and 6.4e-5 with TF32 off in both; benchmarks/results/
# latency-gpu-2026-12-01.md).  A provider named without options gets these, so that every
# provider is exact; pass options to choose.
EXACT_PROVIDER_OPTIONS = {"CUDAExecutionProvider": {"use_tf32": "0"}}


def provider_name(provider) -> str:
    """A provider as onnxruntime takes it, a name or (name, options) -> the name."""
    return provider if isinstance(provider, str) else provider[0]


def resolve_providers(providers) -> list:
    """None -> CPU; names are checked against what this onnxruntime build offers; a provider
    named without options gets EXACT_PROVIDER_OPTIONS."""
    if providers is None:
        return ["CPUExecutionProvider"]
    if isinstance(providers, str):
        providers = [p.strip() for p in providers.split(",") if p.strip()]
    available = ort.get_available_providers()
    names = [provider_name(p) for p in providers]
    unknown = [n for n in names if n not in available]
    if unknown:
        raise ParqError(f"execution provider {', '.join(unknown)} is not available in this "
                        f"onnxruntime build (available: {', '.join(available)})")
    providers = [(p, dict(EXACT_PROVIDER_OPTIONS[p])) if isinstance(p, str)
                 and p in EXACT_PROVIDER_OPTIONS else p for p in providers]
    if "CPUExecutionProvider" not in names:
        providers = list(providers) + ["CPUExecutionProvider"]
    return list(providers)


def device(session) -> tuple:
    """Where a session's graph runs, as (device type, device id): ("cuda", its device_id) when
    its first provider is onnxruntime's CUDA provider, else ("cpu", 0); the names
    ``OrtValue.ortvalue_from_numpy`` and ``IOBinding.bind_output`` take."""
    first = session.get_providers()[0]
    if first != "CUDAExecutionProvider":
        return "cpu", 0
    return "cuda", int(session.get_provider_options().get(first, {}).get("device_id", 0))


@functools.cache
def _preload_cuda() -> None:
    """onnxruntime-gpu finds CUDA and cuDNN in the nvidia-* wheels only after
    ``preload_dlls`` (onnxruntime >= 1.21); a system-wide CUDA needs nothing.  Once per
    process: a Detector creates two sessions."""
    preload = getattr(ort, "preload_dlls", None)
    if preload is not None:
        try:
            preload()
        except Exception:  # noqa: BLE001 - best effort: the session reports what is missing
            pass


def create(path, threads=None, providers=None, spinning=False) -> ort.InferenceSession:
    if threads is not None and (int(threads) < 1 or int(threads) > 4 * (os.cpu_count() or 1)):
        raise ParqError(f"--threads {threads}: use 1 to {4 * (os.cpu_count() or 1)}")
    providers = resolve_providers(providers)
    if any(provider_name(p) == "CUDAExecutionProvider" for p in providers):
        _preload_cuda()
    try:
        return ort.InferenceSession(str(path), session_options(threads, spinning),
                                    providers=providers)
    except ParqError:
        raise
    except Exception as e:  # onnxruntime raises its own Fail/InvalidGraph/... types
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ParqError(f"{path}: onnxruntime cannot load it ({first})") from None
