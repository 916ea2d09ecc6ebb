"""Training loop for a small PARQ on generated scenes (CPU).

There are no pretrained weights here, so the ResNet trains from scratch with ordinary
BatchNorm; at the end each BatchNorm's statistics and affine terms are moved into the
FrozenBatchNorm2d the exported architecture uses (same four tensors, same eps).

The schedule is a fixed number of steps (AdamW, linear warm-up then cosine decay, gradient
clipping at 1.0 as the authors), so the same seed gives the same model whatever the machine's
speed; the command records how long it took.  ``parq-train --minutes`` sets that number from
the machine's pace instead, once, inside the warm-up (:mod:`parq_train.budget`), and records it.
"""
from __future__ import annotations

import copy
import math
import time

import numpy as np
import torch
from torch import nn

from parq_export.backbone import FrozenBatchNorm2d
from parq_export.layer import DecoderLayer
from parq_export.model import PARQ

from . import dense, denoise, mirror as mirror_augment, resume
from .average import WeightMean
from .budget import PLAN_AT
from .loss import WEIGHTS, total_loss
from .progress import minutes


def swap_norms(module: nn.Module, to_trainable: bool) -> nn.Module:
    """FrozenBatchNorm2d <-> BatchNorm2d, carrying weight, bias and running statistics."""
    for name, child in list(module.named_children()):
        if to_trainable and isinstance(child, FrozenBatchNorm2d):
            new = nn.BatchNorm2d(child.weight.numel(), eps=child.eps)
        elif not to_trainable and isinstance(child, nn.BatchNorm2d):
            new = FrozenBatchNorm2d(child.num_features, eps=child.eps)
        else:
            swap_norms(child, to_trainable)
            continue
        with torch.no_grad():
            for key in ("weight", "bias", "running_mean", "running_var"):
                getattr(new, key).copy_(getattr(child, key))
        setattr(module, name, new)
    return module


def set_dropout(model: nn.Module, rate: float, attention: float = 0.0,
                key: float = 0.0) -> None:
    """The training dropout of the model's decoder layer(s): ``rate`` on the residual branches
    and the FFN, ``attention`` on the attention weights, ``key`` DropKey on the
    cross-attention's scores (DecoderLayer)."""
    for module in model.modules():
        if isinstance(module, DecoderLayer):
            module.set_dropout(rate, attention, key)


def init_reference_points(model: PARQ, generator: torch.Generator, snippets=None) -> None:
    """Learned reference points start at k-means centres of the training targets' centers in
    the local frame (anchors where objects are), or uniform in the decoder box without data."""
    from scipy.cluster.vq import kmeans2

    from parq_runtime.loop import normalize

    K = model.refpoint.weight.shape[0]
    u = torch.rand(model.refpoint.weight.shape, generator=generator) * 0.9 + 0.05
    if snippets:
        centers = normalize(np.concatenate([s.centers for s in snippets]),
                            model.config.decoder_scale)
        centers = centers[np.all((centers > 0.02) & (centers < 0.98), -1)]
        if len(centers) >= K:
            seed = int(torch.randint(0, 2 ** 31 - 1, (1,), generator=generator))
            anchors, _ = kmeans2(centers, K, minit="++", seed=seed)
            u = torch.from_numpy(np.clip(anchors, 0.02, 0.98)).float()
    with torch.no_grad():
        model.refpoint.weight.copy_(torch.log(u / (1 - u)))


def to_batch(snippets: list, augment: np.random.Generator | None = None) -> tuple:
    images = np.stack([s.images for s in snippets]).astype(np.float32) / 255.0
    if augment is not None:  # brightness / contrast / colour jitter per image
        B, N = images.shape[:2]
        gain = augment.uniform(0.75, 1.25, (B, N, 1, 1, 1))
        tint = augment.uniform(0.9, 1.1, (B, N, 1, 1, 3))
        offset = augment.uniform(-0.08, 0.08, (B, N, 1, 1, 1))
        images = np.clip(images * gain * tint + offset, 0.0, 1.0).astype(np.float32)
    images = torch.from_numpy(images).permute(0, 1, 4, 2, 3).contiguous()
    camera = torch.from_numpy(np.stack([s.camera for s in snippets]))
    T_local_camera = torch.from_numpy(np.stack([s.T_local_camera for s in snippets]))
    targets = [{"labels": torch.from_numpy(s.labels), "centers": torch.from_numpy(s.centers),
                "sizes": torch.from_numpy(s.sizes), "rotations": torch.from_numpy(s.rotations)}
               for s in snippets]
    return images, camera, T_local_camera, targets


def learning_rate(step: int, steps: int, peak: float, warmup: int) -> float:
    if step < warmup:
        return peak * (step + 1) / warmup
    progress = (step - warmup) / max(1, steps - warmup)
    return peak * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress)))


def new_model(config, seed: int, snippets=None) -> PARQ:
    """A PARQ with trainable batch norms and reference points at the targets' k-means
    centres (see init_reference_points)."""
    torch.manual_seed(seed)
    model = swap_norms(PARQ(config), to_trainable=True)
    init_reference_points(model, torch.Generator().manual_seed(seed), snippets)
    return model


def train(config, snippets: list, steps: int, seed: int, folds_of_class, batch_size: int = 4,
          lr: float = 4e-4, iterations: int = 4, log=print, log_every: int = 50,
          model: PARQ | None = None, snapshot=None, snapshot_every: int = 0,
          backbone_lr: float = 1.0, form: str = "cached", bf16: bool = False,
          denoise_scale: float = 0.0, denoise_class_weight: float = 1.0,
          mirror: bool = False, dense_weight: float = 0.0, average_from: int = 0,
          average_every: int = 2000, dropout: float = 0.0, attention_dropout: float = 0.0,
          key_dropout: float = 0.0, center_weight: float = WEIGHTS["center"],
          state: dict | None = None, save_state=None, plan=None,
          plan_at: int = PLAN_AT) -> tuple:
    """Train a PARQ (``model`` from :func:`new_model`, possibly with a pretrained backbone,
    or a fresh one) on the snippets; returns (model with frozen norms, history).

    ``snapshot(model, step)``, if given, is called every ``snapshot_every`` steps with a
    copy of the model in evaluation form (frozen norms), so a long run leaves usable
    checkpoints behind it.  ``backbone_lr`` scales the learning rate of the ResNet-FPN (the
    pretrained part) against the rest.  ``form`` is the attention form of PARQ.forward: the
    default ``cached`` is what trained the shipped demo; ``fused`` computes the same in another
    rounding order, faster.  ``bf16`` runs the forward pass under CPU autocast to bfloat16
    (products and convolutions in bfloat16, weights, optimiser and loss in float32): on CPUs
    with AMX it is faster (see ``parq-train --bf16``); elsewhere it is emulated and slower.
    ``denoise_scale`` above 0 adds a denoising query per target, its center moved by up to
    that many half extents (:mod:`parq_train.denoise`; beyond the paper's objective); 0 trains
    exactly as before.  ``denoise_class_weight`` scales their class loss.  ``mirror`` replaces
    each snippet of a batch by its mirror image with probability 1/2
    (:mod:`parq_train.mirror`); off, nothing is drawn for it, so training is as before.
    ``dense_weight`` above 0 adds :mod:`parq_train.dense`'s auxiliary loss on the backbone's
    features times that weight (the snippets need their dense targets: ``load_scenes(...,
    dense=True)``); its probe trains with the model and is dropped at the end; 0 trains
    exactly as before.  ``average_from`` above 0 returns the mean of the weights after
    ``average_from``, ``average_from + average_every``, ... steps, the last of them the run's
    last step (:mod:`parq_train.average`); the steps taken are the same either way.
    ``dropout`` and ``attention_dropout`` above 0 train the decoder layer with the authors'
    dropout at those rates, on its residual branches and FFN and on its attention weights
    (:class:`parq_export.layer.DecoderLayer`; 0.1 both in their configuration); 0 trains
    exactly as before.  ``key_dropout`` above 0 adds DropKey on the cross-attention (beyond
    the authors' recipe; see DecoderLayer).  All are set back to 0 on the returned model.
    ``center_weight`` weights the L1 center loss (the paper's 5 by default; the matching does
    not change with it).

    ``save_state(state)``, if given, is called at the snapshots' steps with the whole state of
    the run (:func:`parq_train.resume.capture`); ``state`` is such a state to continue from,
    in place of the first ``state["step"]`` steps (same arguments otherwise): the weights then
    come out as without the interruption, bit for bit.

    ``plan(done, seconds)``, if given, is called once after ``plan_at`` steps (``seconds`` of
    training) and returns the run's length from then on, at most ``steps``
    (:mod:`parq_train.budget`).  The warm-up's length is set from ``steps`` before the first
    step, so a run planned inside its warm-up to N steps takes the steps of a run of N steps
    whenever both give the same warm-up (at least 5,000 steps: 500)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    if model is None:
        model = new_model(config, seed, snippets)
    model.train()
    set_dropout(model, dropout, attention_dropout, key_dropout)
    probe, captured, hook = None, {}, None
    if dense_weight > 0:
        probe = dense.DenseProbe(config.feature_dim, len(config.classes))
        hook = model.backbone.register_forward_hook(
            lambda module, inputs, output: captured.__setitem__("features", output))
    # what the optimiser, the gradient clipping and a saved state cover: the model, and the
    # dense probe when there is one
    trained = model if probe is None else nn.ModuleDict({"model": model, "probe": probe})
    groups = {}
    for name, p in trained.named_parameters():
        name = name.removeprefix("model.")
        scale = backbone_lr if name.startswith("backbone.") else 1.0
        decay = 0.0 if p.dim() < 2 or name.startswith("refpoint") else 1e-4
        groups.setdefault((scale, decay), []).append(p)
    optimizer = torch.optim.AdamW([{"params": params, "weight_decay": decay, "scale": scale}
                                   for (scale, decay), params in groups.items()], lr=lr)
    folds = torch.as_tensor(folds_of_class)
    history, order, running, first, seconds = [], [], {}, 0, 0.0
    weight_mean = None
    if average_from:
        if average_from > steps or (steps - average_from) % average_every:
            raise ValueError(f"steps {steps} is not on the weight mean's grid "
                             f"({average_from} + k * {average_every})")
        weight_mean = WeightMean(average_from, average_every)
    if state is not None:
        first, seconds, order, running, history = resume.restore(state, trained, optimizer,
                                                                 rng)
        if weight_mean is not None:
            weight_mean.load_state_dict(state["average"])
    start = time.perf_counter() - seconds
    warmup = min(500, steps // 10)
    step = first
    while step < steps:
        if len(order) < batch_size:
            order += list(rng.permutation(len(snippets)))
        batch = [snippets[i] for i in order[:batch_size]]
        del order[:batch_size]
        if mirror:
            batch = mirror_augment.mirror_some(batch, rng, config.feature_stride)
        for group in optimizer.param_groups:
            group["lr"] = group["scale"] * learning_rate(step, steps, lr, warmup)
        images, camera, T_local_camera, targets = to_batch(batch, rng)
        extra = None
        if denoise_scale > 0:
            extra, index = denoise.noised_queries(targets, config.decoder_scale, rng,
                                                  denoise_scale)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            outputs = model(images, camera, T_local_camera, iterations=iterations, form=form,
                            extra_points=extra)
        if bf16:
            outputs = [{k: v.float() if v.is_floating_point() else v for k, v in out.items()}
                       for out in outputs]
        if extra is not None:
            outputs, noised = denoise.split(outputs, config.num_queries)
        loss, parts = total_loss(outputs, targets, folds, len(config.classes),
                                 {"center": center_weight})
        if extra is not None:
            dn_loss, dn_parts = denoise.denoise_loss(noised, index, targets, folds,
                                                     denoise_class_weight)
            loss = loss + dn_loss
            parts.update({f"denoise {k}": v for k, v in dn_parts.items()})
        if probe is not None:
            features = captured.pop("features").float()
            dense_depth = torch.from_numpy(np.stack([s.dense_depth for s in batch]))
            dense_labels = torch.from_numpy(np.stack([s.dense_labels for s in batch]))
            aux, aux_parts = dense.dense_loss(probe, features, dense_depth.flatten(0, 1),
                                              dense_labels.flatten(0, 1).long())
            loss = loss + dense_weight * aux
            parts.update(aux_parts)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(trained.parameters(), 1.0)
        optimizer.step()
        if weight_mean is not None and weight_mean.due(step + 1):
            weight_mean.add(model.state_dict())
        for k, v in dict(parts, total=float(loss.detach())).items():
            running[k] = running.get(k, 0.0) + v
        if (step + 1) % log_every == 0 or step + 1 == steps:
            window = step + 1 - (history[-1]["step"] if history else 0)  # the last: shorter
            mean = {k: v / window for k, v in running.items()}
            elapsed = time.perf_counter() - start
            history.append({"step": step + 1, "seconds": round(elapsed, 1), **mean})
            log(f"step {step + 1}/{steps}  {minutes(elapsed, step + 1, steps)}  "
                f"loss {mean['total']:.3f}  "
                + "  ".join(f"{k} {mean[k]:.3f}" for k in ("center", "size", "rotation",
                                                           "class", "denoise center",
                                                           "dense depth", "dense class")
                            if k in mean))
            running = {}
        if snapshot_every and (step + 1) % snapshot_every == 0 and step + 1 < steps:
            if save_state is not None:
                save_state(resume.capture(trained, optimizer, rng, order, running, history,
                                          step + 1, time.perf_counter() - start,
                                          average=weight_mean))
            if snapshot is not None:
                snapshot(swap_norms(copy.deepcopy(model), to_trainable=False).eval(), step + 1)
        step += 1
        if plan is not None and step == plan_at and step < steps:
            planned = plan(step, time.perf_counter() - start)
            if not step <= planned <= steps:
                raise ValueError(f"a plan of {planned} steps after {step} of {steps}")
            steps = planned
    if hook is not None:
        hook.remove()
    if weight_mean is not None:
        weight_mean.load_into(model)
    set_dropout(model, 0.0)
    model = swap_norms(model, to_trainable=False).eval()
    return model, history
