"""The paper's efficiency table (Table 6) on an NVIDIA GPU, beside the paper's own numbers.

The grid of benchmarks/latency.py with both systems on the GPU, in one process and
interleaved, run after run:

* reference: this package's torch model on CUDA, run the authors' way (eager; every iteration
  recomputes the cross-attention keys and values), with their preprocessing (PIL, on the host);
* runtime: parq_runtime.Detector with onnxruntime's CUDA execution provider (exact fp32, its
  default: TF32 off), in each exact attention form.  numpy drives the loop on the host; a
  snippet's keys, values and factors stay on the device (parq_runtime.loop.LayerRunner).  The
  form the runtime picks by itself ("auto") counts multiply-adds, which is what matters on a
  CPU; both are timed here, and the picked form once more with TF32 allowed ("tf32").

The paper's Table 6 was measured on an NVIDIA A5000: 105 ms at 32 queries and 2 iterations,
290 ms at 256 and 8.  Also measured: the two systems' agreement on the GPU (max abs error over
all 8 iterations at 256 queries) with TF32 as each library allows it by default, and with TF32
off in both.

    python benchmarks/latency_gpu.py [--runs 10] [--warmup 3] [--model DIR --checkpoint CKPT]

Needs onnxruntime-gpu and a CUDA build of torch; CI never runs it.  Writes
results/latency-gpu.{md,json}.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

import common
import latency

PAPER_MS = {(32, 2): 105, (256, 8): 290}     # Table 6, NVIDIA A5000
SYSTEMS = ("reference", "cached", "folded", "tf32")
OUTPUTS = ("center", "size", "rotation", "logits")


def parity(model, model_dir, images, K, T, tf32: bool) -> dict:
    """Max abs error of the runtime (each form) against the torch model, both on the GPU,
    over all iterations at 256 queries x 8 iterations."""
    import torch

    from parq_runtime import Detector

    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.backends.cudnn.allow_tf32 = tf32
    det = Detector(model_dir, providers=[("CUDAExecutionProvider",
                                          {"use_tf32": "1" if tf32 else "0"})])
    net, cam, _, T_lc = det.prepare(images, K, T)
    reference = det.reference_points(256)
    with torch.no_grad():
        expected = model(torch.from_numpy(net).permute(0, 3, 1, 2)[None].float().cuda() / 255,
                         torch.from_numpy(cam).float()[None].cuda(),
                         torch.from_numpy(T_lc).float()[None].cuda(), iterations=8,
                         reference_points=torch.from_numpy(reference).float().cuda())
    errors = {}
    for form in ("cached", "folded"):
        got = det.detect(images, K, T, iters=8, queries=256, form=form, score_threshold=0.0)
        errors[form] = {name: max(float(np.abs(getattr(g, name) - e[name][0].cpu().numpy())
                                        .max()) for g, e in zip(got.iterations, expected))
                        for name in OUTPUTS}
    torch.backends.cudnn.allow_tf32 = True      # torch's defaults again
    torch.backends.cuda.matmul.allow_tf32 = False
    return errors


def ms(stats: dict) -> str:
    return f"{1e3 * stats['median']:.1f} [{1e3 * stats['p25']:.1f}, {1e3 * stats['p75']:.1f}]"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=10,
                   help="timed runs per setting after warm-up (default 10)")
    p.add_argument("--warmup", type=int, default=3,
                   help="untimed warm-up runs per setting (default 3)")
    p.add_argument("--model", type=pathlib.Path, default=None,
                   help="exported authors' configuration (default: benchmarks/.cache, "
                        "exported here)")
    p.add_argument("--checkpoint", type=pathlib.Path, default=None,
                   help="the checkpoint --model was exported from (default: the seeded one "
                        "of tests/golden/make_official_ckpt.py)")
    p.add_argument("--out", default=str(common.RESULTS / "latency-gpu"),
                   help="output stem: .md, .json (default results/latency-gpu)")
    args = p.parse_args()

    import onnxruntime as ort
    import torch

    from parq_export import checkpoint
    from parq_runtime import Detector
    from parq_runtime.detector import choose_form

    if "CUDAExecutionProvider" not in ort.get_available_providers() \
            or not torch.cuda.is_available():
        sys.exit("latency_gpu.py: needs onnxruntime-gpu (CUDAExecutionProvider) and torch "
                 "with a CUDA device")
    model_dir = args.model or common.official_model()
    model = checkpoint.load(args.checkpoint or common.official_checkpoint()).model()
    model = model.to("cuda").eval()
    det = Detector(model_dir, providers="CUDAExecutionProvider")
    det_tf32 = Detector(model_dir, providers=[("CUDAExecutionProvider", {"use_tf32": "1"})])
    if det.backbone.get_providers()[0] != "CUDAExecutionProvider":
        sys.exit(f"latency_gpu.py: onnxruntime fell back to {det.backbone.get_providers()}")
    images, K, T = common.golden_snippet()
    card = det.card
    rows = []
    for queries, iters in latency.GRID:
        points = det.reference_points(queries)
        samples = {s: [] for s in SYSTEMS}
        for run in range(args.warmup + args.runs):
            for system in (SYSTEMS if run % 2 == 0 else SYSTEMS[::-1]):
                if system == "reference":
                    timings = latency.reference_run(model, images, K, T, iters, points, "cuda")
                elif system == "tf32":
                    timings = det_tf32.detect(images, K, T, iters=iters,
                                              queries=queries).timings
                else:
                    timings = det.detect(images, K, T, iters=iters, queries=queries,
                                         form=system).timings
                if run >= args.warmup:
                    samples[system].append(latency.summarise(timings))
        row = {"queries": queries, "iterations": iters,
               "auto": choose_form(3, card.feature_size, card.feature_dim, card.heads,
                                   queries, iters)}
        for system, runs in samples.items():
            row[system] = {stage: common.stats([r[stage] for r in runs]) for stage in runs[0]}
        rows.append(row)
        print(f"{queries:4d} x {iters}: reference {ms(row['reference']['total'])} ms, "
              f"cached {ms(row['cached']['total'])}, folded {ms(row['folded']['total'])}, "
              f"tf32 {ms(row['tf32']['total'])}",
              file=sys.stderr, flush=True)
    errors = {"tf32 default": parity(model, model_dir, images, K, T, True),
              "tf32 off": parity(model, model_dir, images, K, T, False)}
    print(json.dumps(errors), file=sys.stderr)

    gpu = torch.cuda.get_device_name()
    host = common.machine()
    lines = [f"GPU: {gpu}; host {host['cpu']}, {host['cores']} cores; onnxruntime "
             f"{ort.__version__} (CUDA execution provider), torch {torch.__version__}. "
             f"Medians of {args.runs} runs after {args.warmup} warm-ups, milliseconds "
             "[quartiles]; end to end (preprocessing of three 1296x968 frames on the host, "
             "backbone, loop, post-processing).", "",
             "| queries | iterations | paper, A5000 | reference | runtime cached | runtime "
             "folded | auto form | speed-up, auto | speed-up, faster form | runtime auto, "
             "TF32 |", "|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
    for r in rows:
        ref = r["reference"]["total"]["median"]
        best = min(r["cached"]["total"]["median"], r["folded"]["total"]["median"])
        auto = r[r["auto"]]["total"]["median"]
        paper = PAPER_MS.get((r["queries"], r["iterations"]))
        lines.append(f"| {r['queries']} | {r['iterations']} | {paper or ''} | "
                     f"{ms(r['reference']['total'])} | {ms(r['cached']['total'])} | "
                     f"{ms(r['folded']['total'])} | {r['auto']} | {ref / auto:.2f}x | "
                     f"{ref / best:.2f}x | {ms(r['tf32']['total'])} |")
    lines += ["", "Stages (median ms):", "",
              "| queries | iterations | system | preprocess | backbone | per iteration | "
              "postprocess |", "|---:|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        if (r["queries"], r["iterations"]) in PAPER_MS:
            for system in SYSTEMS:
                s = r[system]
                lines.append(f"| {r['queries']} | {r['iterations']} | {system} | " + " | ".join(
                    f"{1e3 * s[k]['median']:.1f}" for k in ("preprocess", "backbone",
                                                            "per_iteration", "postprocess"))
                    + " |")
    lines += ["", "Runtime against the torch model on the GPU, max abs error over 8 "
              "iterations at 256 queries:", "",
              "| TF32 | form | " + " | ".join(OUTPUTS) + " |",
              "|---|---|" + "---:|" * len(OUTPUTS)]
    for mode, by_form in errors.items():
        for form, e in by_form.items():
            lines.append(f"| {mode} | {form} | " + " | ".join(f"{e[n]:.1e}" for n in OUTPUTS)
                         + " |")
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(
        {"gpu": gpu, "host": host, "rows": rows, "parity": errors, "paper_ms": {
            f"{q}x{i}": v for (q, i), v in PAPER_MS.items()}}, indent=1))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
