"""Shared helpers of the benchmark scripts: the official-configuration model (seeded weights,
exported once into benchmarks/.cache), inputs, timing statistics and machine description."""
from __future__ import annotations

import os
import pathlib
import platform
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
CACHE = HERE / ".cache"
RESULTS = HERE / "results"
GOLDEN = ROOT / "tests" / "golden"


def official_checkpoint() -> pathlib.Path:
    """The authors' architecture with seeded weights (tests/golden/make_official_ckpt.py)."""
    CACHE.mkdir(exist_ok=True)
    path = CACHE / "official.ckpt"
    if not path.exists():
        subprocess.run([sys.executable, str(GOLDEN / "make_official_ckpt.py"), str(path),
                        "--seed", "0"], check=True)
    return path


EXPORTER_STAMP = ".exporter.sha256"


def exporter_digest() -> str:
    """sha256 of parq_export's source files: a cached export made by other code is stale even
    when its graphs have the same inputs and outputs."""
    import hashlib

    digest = hashlib.sha256()
    for path in sorted((ROOT / "parq_export").glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def stale(folder: pathlib.Path, sha256: str | None = None) -> bool:
    """Whether a cached model folder must be exported again: missing, in another model format
    than this package reads, naming other backbone outputs than the export writes now, made by
    other exporter code (:func:`exporter_digest`, stamped by :func:`export_cached`), or (given
    ``sha256``) exported from another checkpoint."""
    import json

    from parq_export.graphs import BACKBONE_GRAPH_OUTPUTS
    from parq_runtime.model_card import CARD_VERSION

    card, stamp = folder / "model.json", folder / EXPORTER_STAMP
    if not card.exists() or not stamp.exists():
        return True
    card = json.loads(card.read_text())
    return (card.get("format_version") != CARD_VERSION
            or card["graphs"]["backbone"]["outputs"] != list(BACKBONE_GRAPH_OUTPUTS)
            or stamp.read_text().strip() != exporter_digest()
            or (sha256 is not None and card["checkpoint"]["sha256"] != sha256))


def export_cached(checkpoint, out: pathlib.Path, **options) -> None:
    """Export ``checkpoint`` into the cache folder ``out`` and stamp it with the exporter's
    digest (see :func:`stale`)."""
    from parq_export.export import export

    export(checkpoint, out, overwrite=True, log=lambda *_: None, **options)
    (out / EXPORTER_STAMP).write_text(exporter_digest() + "\n")


def official_model() -> pathlib.Path:
    """The exported official checkpoint, exported again when :func:`stale`."""
    out = CACHE / "official_model"
    if stale(out):
        export_cached(official_checkpoint(), out)
    return out


def golden_snippet(size=(1296, 968)):
    """The golden case's three views, upscaled to ScanNet's colour size so that the
    preprocessing does what it does on real frames; intrinsics scaled to match."""
    from PIL import Image

    expected = np.load(GOLDEN / "official-case" / "expected.npz")
    images, w0, h0 = [], 320, 240
    for i in range(3):
        im = Image.open(GOLDEN / "official-case" / f"{i}.png").convert("RGB")
        w0, h0 = im.size
        images.append(np.asarray(im.resize(size, Image.BILINEAR)))
    K = expected["intrinsics"].copy()
    K[0] *= size[0] / w0
    K[1] *= size[1] / h0
    return images, K, expected["cam_to_world"]


def validation_arguments(parser) -> None:
    """--model (default the demo) and --val (validation folders, required): the options of
    the scripts that choose and score on validation scenes only."""
    parser.add_argument("--model", type=pathlib.Path, default=ROOT / "models" / "parq-demo")
    parser.add_argument("--val", type=pathlib.Path, nargs="+", required=True,
                        help="validation folders of scenes (data/val data/val2)")


def open_validation(args, prog: str) -> tuple:
    """(Detector of args.model, the scene folders of args.val); a bad folder exits with one
    line naming ``prog``."""
    from parq_runtime import Detector
    from parq_runtime.errors import ParqError
    from parq_train import validation_runs

    try:
        return Detector(args.model), validation_runs.validation_folders(args.val, None)
    except ParqError as e:
        sys.exit(f"{prog}: {e}")


def snippet_views(capture, card):
    """Yields (images, K (N, 3, 3), T_world_camera (N, 4, 4)) of each snippet that parq-run
    makes of ``capture`` at the card's run setting, images read from disk one snippet at a
    time."""
    from parq_runtime import scene

    _, snippets = scene.plan(capture, scene.resolved(scene.RunSettings(), card), card)
    for indices in snippets:
        frames = [capture.frames[i] for i in indices]
        yield ([f.load_image() for f in frames], np.stack([f.intrinsics for f in frames]),
               np.stack([f.cam_to_world for f in frames]))


def run_boxes(iteration, T_world_local, detector, up, mirrored: bool) -> list:
    """[(box, its local center)] of one snippet run's ``iteration``: every box above score 0
    after the card's NMS, in any region, reflected back when the run was ``mirrored``.  The
    local center is in the run's own snippet frame: a region is symmetric in x, so a mirrored
    run's center keeps what the plain run's would."""
    from parq_runtime import boxes as box_decoding
    from parq_runtime import geometry, mirror

    T_local_world = geometry.invert(T_world_local)
    found = box_decoding.detections(iteration, T_world_local, detector.classes, 0.0,
                                    detector.card.nms_iou, None, up)
    return [(mirror.unmirror_box(b, up) if mirrored else b,
             geometry.transform(T_local_world, b.center)) for b in found]


def write_report(out: pathlib.Path, lines: list, record) -> None:
    """Print the markdown ``lines`` and write them to ``out``.md, ``record`` to ``out``.json
    (folders made as needed)."""
    import json

    text = "\n".join(lines) + "\n"
    print(text)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text)
    out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")


def stats(values) -> dict:
    v = sorted(values)
    q = statistics.quantiles(v, n=4) if len(v) >= 2 else [v[0]] * 3
    return {"median": statistics.median(v), "p25": q[0], "p75": q[2], "min": v[0],
            "max": v[-1], "n": len(v)}


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    flags = ""
    try:
        flags = next(l for l in open("/proc/cpuinfo") if l.startswith("flags"))
    except (OSError, StopIteration):
        pass
    isa = [f for f in ("avx2", "avx512f", "avx512_vnni", "amx_tile") if f" {f}" in flags]
    import onnxruntime
    import torch
    return {"cpu": cpu, "cores": os.cpu_count(), "isa": isa, "python": platform.python_version(),
            "onnxruntime": onnxruntime.__version__, "torch": torch.__version__}


def matmul_peak(threads: int, n: int = 2048, runs: int = 15) -> float:
    """fp32 GFLOP/s of an n x n x n product in onnxruntime (MLAS, the kernels the graphs use):
    the fastest of ``runs`` after a warm-up.  A peak is the best the machine does; the median
    of 7 used before moved from 140 to 164 GFLOP/s between runs on a noisy 2-core machine, and
    once put the backbone at 108% of it."""
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper

    a = helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])
    b = helper.make_tensor_value_info("b", TensorProto.FLOAT, [n, n])
    c = helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])
    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "mm", [a, b],
                              [c])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    session = ort.InferenceSession(model.SerializeToString(), options,
                                   providers=["CPUExecutionProvider"])
    x = np.random.default_rng(0).standard_normal((n, n), dtype=np.float32)
    session.run(None, {"a": x, "b": x})
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        session.run(None, {"a": x, "b": x})
        times.append(time.perf_counter() - t)
    return 2 * n ** 3 / min(times) / 1e9


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM).  Not getrusage's ru_maxrss: that is
    preserved across execve, so a child started by a big benchmark reports its parent's."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
