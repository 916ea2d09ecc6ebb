"""The paper's efficiency table (Table 6) for this package on this machine.

The authors' configuration (ResNet50, 1024 channels, 3 views; ScanNet-size 1296x968 frames
resized to 320x240), weights from tests/golden/make_official_ckpt.py (only the arithmetic
matters).  In one process and interleaved, run after run:

* reference: this package's torch model run the authors' way (eager; every iteration
  recomputes the cross-attention keys and values, as their code does), with their
  preprocessing (PIL);
* runtime: parq_runtime.Detector on the exported graphs (the cheaper exact attention form
  chosen per snippet).

Grid: iterations 1, 2, 4, 6, 8 at 256 queries; queries 16, 32, 64, 128, 256 at 8 iterations;
32 queries with 2 iterations.  Medians and quartiles over --runs runs after --warmup; per stage
and end to end; peak resident memory of each system measured alone in a subprocess; this
machine's fp32 matrix-multiply peak measured in the same run, and each stage's achieved GFLOP/s
against it.  Writes results/latency.{md,csv,json,png}.

    python benchmarks/latency.py [--runs 5] [--threads N]
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time

import numpy as np

import common
import flops

GRID = ([(256, i) for i in (1, 2, 4, 6, 8)] + [(q, 8) for q in (16, 32, 64, 128)]
        + [(32, 2)])


def reference_run(model, images, K, T_world_camera, iters, reference_points, device="cpu"):
    """The authors' pipeline with this package's torch model (on ``device``, where ``model``
    is); returns stage timings, each taken after the device has finished its work."""
    import torch

    def sync():
        if device != "cpu":
            torch.cuda.synchronize()

    from parq_export.model import pixel_aligned_features
    from parq_export.ray_encoding import denormalize_points
    from parq_runtime import boxes, geometry, preprocess

    config = model.config
    timings = {}
    t = time.perf_counter()
    prepared = [preprocess.prepare(im, K, config.image_size) for im in images]
    x = torch.from_numpy(np.stack([p[0] for p in prepared])).permute(0, 3, 1, 2)[None]
    x = x.float().to(device) / 255.0
    camera = geometry.scale_camera(geometry.pinhole(np.stack([p[1] for p in prepared])),
                                   1.0 / config.feature_stride)
    T_world_local = geometry.snippet_frame(T_world_camera)
    T_local_camera = geometry.invert(T_world_local) @ T_world_camera
    camera_t = torch.from_numpy(camera).float()[None].to(device)
    T_lc = torch.from_numpy(T_local_camera).float()[None].to(device)
    T_cl = torch.from_numpy(geometry.invert(T_local_camera)).float()[None].to(device)
    sync()
    timings["preprocess"] = time.perf_counter() - t
    with torch.no_grad():
        t = time.perf_counter()
        memory = model.memory(model.image_features(x), camera_t, T_lc)
        tokens = memory.flatten(1, 3)
        sync()
        timings["backbone"] = time.perf_counter() - t
        ref = torch.from_numpy(reference_points).float()[None].to(device)
        per_iteration = []
        for _ in range(iters):
            t = time.perf_counter()
            points = denormalize_points(ref, config.decoder_scale)
            content = pixel_aligned_features(memory, points, camera_t, T_cl)
            out = model.layer(content, ref, memory=tokens)
            ref = out["next_reference_points"]
            sync()
            per_iteration.append(time.perf_counter() - t)
    timings["iterations"] = per_iteration
    t = time.perf_counter()
    last = type("Last", (), {k: out[k][0].cpu().numpy() for k in ("center", "size",
                                                                 "ortho6d", "logits")})
    boxes.detections(last, T_world_local, list(config.classes), config.score_threshold,
                     config.nms_iou, config.eval_region)
    timings["postprocess"] = time.perf_counter() - t
    return timings


def summarise(timings: dict) -> dict:
    loop = sum(timings["iterations"])
    return {"preprocess": timings["preprocess"], "backbone": timings["backbone"],
            "loop": loop, "per_iteration": loop / len(timings["iterations"]),
            "postprocess": timings["postprocess"],
            "total": timings["preprocess"] + timings["backbone"] + loop
            + timings["postprocess"]}


def rss_only(system: str, threads) -> None:
    """Child process: one run at 256 queries and 8 iterations, then print peak RSS (MB).
    The runtime's child never imports torch (as in deployment)."""
    images, K, T = common.golden_snippet()
    if system == "runtime":
        from parq_runtime import Detector
        Detector(common.official_model(), threads=threads).detect(images, K, T, iters=8,
                                                                  queries=256)
    else:
        import torch

        from parq_export import checkpoint
        if threads:
            torch.set_num_threads(threads)
        model = checkpoint.load(common.official_checkpoint()).model()
        reference_run(model, images, K, T, 8, model.initial_reference_points()
                      .detach().numpy())
    print(common.peak_rss_mb())


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5,
                   help="timed runs per setting after warm-up (default 5)")
    p.add_argument("--warmup", type=int, default=1,
                   help="untimed warm-up runs per setting (default 1)")
    p.add_argument("--threads", type=int, default=None,
                   help="threads for both systems (default: onnxruntime's and torch's own)")
    p.add_argument("--rss-only", choices=("runtime", "reference"), help=argparse.SUPPRESS)
    p.add_argument("--out", default=str(common.RESULTS / "latency"),
                   help="output stem: .md, .csv, .json, .png (default results/latency)")
    args = p.parse_args()
    if args.rss_only:
        return rss_only(args.rss_only, args.threads)

    import torch

    from parq_export import checkpoint
    from parq_runtime import Detector

    if args.threads:
        torch.set_num_threads(args.threads)
    threads = args.threads or torch.get_num_threads()
    model_dir = common.official_model()
    det = Detector(model_dir, threads=args.threads)
    model = checkpoint.load(common.official_checkpoint()).model()
    config = model.config
    images, K, T = common.golden_snippet()
    peak = common.matmul_peak(threads)
    print(f"fp32 matmul peak {peak:.0f} GFLOP/s ({threads} threads)", file=sys.stderr)
    rows = []
    for queries, iters in GRID:
        points = det.reference_points(queries)
        samples = {"reference": [], "runtime": []}
        forms = []
        for run in range(args.warmup + args.runs):
            order = ("reference", "runtime") if run % 2 == 0 else ("runtime", "reference")
            for system in order:
                if system == "reference":
                    timings = reference_run(model, images, K, T, iters, points)
                else:
                    result = det.detect(images, K, T, iters=iters, queries=queries)
                    timings = result.timings
                    forms.append(result.form)
                if run >= args.warmup:
                    samples[system].append(summarise(timings))
        for system, runs in samples.items():
            form = forms[-1] if system == "runtime" else "reference"
            stage_flops = {
                "backbone": 3 * flops.resnet_fpn(config)
                + flops.ray_encoding(config, 3, hidden_only=(form == "folded"))
                + (flops.key_value_projection(config, 3) if form == "cached" else 0.0),
                "per_iteration": flops.layer(config, 3, queries, form)}
            for stage in runs[0]:
                s = common.stats([r[stage] for r in runs])
                gflops = stage_flops.get(stage)
                rows.append({"queries": queries, "iterations": iters, "system": system,
                             "form": form, "stage": stage, **{k: round(v, 5) if
                                                                isinstance(v, float) else v
                                                                for k, v in s.items()},
                             "gflop_per_s": round(gflops / s["median"] / 1e9, 1)
                             if gflops else None,
                             "of_peak": round(gflops / s["median"] / 1e9 / peak, 3)
                             if gflops else None})
        ref = next(r for r in rows[::-1] if r["system"] == "reference" and r["stage"] == "total"
                   and r["queries"] == queries and r["iterations"] == iters)
        ours = next(r for r in rows[::-1] if r["system"] == "runtime" and r["stage"] == "total"
                    and r["queries"] == queries and r["iterations"] == iters)
        print(f"{queries:4d} queries {iters} iterations: reference {ref['median']:.3f} s, "
              f"runtime {ours['median']:.3f} s ({forms[-1]}), {ref['median'] / ours['median']:.2f}x",
              file=sys.stderr)
    # Both exact attention forms, forced, at the two settings the issue names: what each
    # costs up front (backbone, with or without the key/value projections) and per iteration.
    form_rows = []
    for queries, iters in ((32, 2), (256, 8)):
        for form in ("cached", "folded"):
            runs = [summarise(det.detect(images, K, T, iters=iters, queries=queries,
                                         form=form).timings)
                    for _ in range(args.warmup + args.runs)][args.warmup:]
            row = {"queries": queries, "iterations": iters, "form": form}
            for stage in ("backbone", "per_iteration", "loop", "total"):
                row[stage] = round(common.stats([r[stage] for r in runs])["median"], 5)
            form_rows.append(row)
            print(json.dumps(row), file=sys.stderr)
    rss = {}
    for system in ("reference", "runtime"):
        cmd = [sys.executable, __file__, "--rss-only", system]
        if args.threads:
            cmd += ["--threads", str(args.threads)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        rss[system] = float(out.strip().splitlines()[-1])
    write(args.out, rows, rss, peak, threads, form_rows)


def write(out, rows, rss, peak, threads, form_rows):
    import pathlib

    out = pathlib.Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    machine = common.machine()
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    out.with_suffix(".json").write_text(json.dumps(
        {"machine": machine, "threads": threads, "matmul_peak_gflops": peak,
         "peak_rss_mb": rss, "rows": rows, "forms": form_rows}, indent=1))

    def get(system, q, i, stage):
        return next(r for r in rows if r["system"] == system and r["queries"] == q
                    and r["iterations"] == i and r["stage"] == stage)

    lines = [f"Machine: {machine['cpu']}, {machine['cores']} cores ({', '.join(machine['isa'])}), "
             f"{threads} threads; onnxruntime {machine['onnxruntime']}, torch "
             f"{machine['torch']}. fp32 matmul peak {peak:.0f} GFLOP/s. Medians of the runs, "
             "seconds; [quartiles].", "",
             "| queries | iterations | reference total | runtime total | speed-up | runtime form "
             "| runtime backbone | runtime per iteration |",
             "|---:|---:|---:|---:|---:|---|---:|---:|"]
    for q, i in GRID:
        r, o = get("reference", q, i, "total"), get("runtime", q, i, "total")
        b, it = get("runtime", q, i, "backbone"), get("runtime", q, i, "per_iteration")
        lines.append(f"| {q} | {i} | {r['median']:.3f} [{r['p25']:.3f}, {r['p75']:.3f}] | "
                     f"{o['median']:.3f} [{o['p25']:.3f}, {o['p75']:.3f}] | "
                     f"{r['median'] / o['median']:.2f}x | {o['form']} | {b['median']:.3f} | "
                     f"{it['median'] * 1000:.1f} ms |")
    lines += ["", "Stages at 256 queries, 8 iterations (median s; GFLOP/s; share of the matmul "
              "peak):", "", "| system | preprocess | backbone | per iteration | postprocess |",
              "|---|---:|---:|---:|---:|"]
    for system in ("reference", "runtime"):
        cells = []
        for stage in ("preprocess", "backbone", "per_iteration", "postprocess"):
            r = get(system, 256, 8, stage)
            cell = f"{r['median']:.3f}"
            if r["gflop_per_s"]:
                cell += f" ({r['gflop_per_s']:.0f} GFLOP/s, {100 * r['of_peak']:.0f}%)"
            cells.append(cell)
        lines.append(f"| {system} | " + " | ".join(cells) + " |")
    lines += ["", "Both exact attention forms, forced (median s). \"one more iteration\" is the "
              "per-iteration time as a share of the same run's backbone:", "",
              "| queries | iterations | form | backbone | per iteration | backbone + loop | "
              "one more iteration |", "|---:|---:|---|---:|---:|---:|---:|"]
    for r in form_rows:
        lines.append(f"| {r['queries']} | {r['iterations']} | {r['form']} | "
                     f"{r['backbone']:.3f} | {1000 * r['per_iteration']:.1f} ms | "
                     f"{r['backbone'] + r['loop']:.3f} | "
                     f"{100 * r['per_iteration'] / r['backbone']:.1f}% |")
    lines += ["", f"Peak resident memory at 256 queries, 8 iterations: reference "
              f"{rss['reference']:.0f} MB, runtime {rss['runtime']:.0f} MB."]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot(out, rows)
    print("\n".join(lines))


def plot(out, rows):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot", file=sys.stderr)
        return
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (vary, fixed, xs, label) in zip(axes, (
            ("iterations", ("queries", 256), (1, 2, 4, 6, 8), "iterations (256 queries)"),
            ("queries", ("iterations", 8), (16, 32, 64, 128, 256), "queries (8 iterations)"))):
        for system, style in (("reference", "o-"), ("runtime", "s-")):
            ys = [next(r["median"] for r in rows if r["system"] == system and
                       r["stage"] == "total" and r[vary] == x and r[fixed[0]] == fixed[1])
                  for x in xs]
            ax.plot(xs, ys, style, label=system)
        ax.set_xlabel(label)
        ax.set_ylabel("seconds per snippet (median)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("PARQ, 3 views of 320x240: torch eager (authors' way) vs parq_runtime")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)


if __name__ == "__main__":
    main()
