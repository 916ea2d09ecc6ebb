"""Shared fixtures: a tiny exported model (seconds), the authors' full-size checkpoint layouts
and its export (about half a minute, once per session), and ScanNet-layout folders."""
from __future__ import annotations

import pathlib
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from parq_runtime.geometry import camera_pose

ROOT = pathlib.Path(__file__).resolve().parents[1]
# A copy of ../shared/golden (the authors' outputs and the seeded checkpoint writer), so that a
# clean clone tests itself.
GOLDEN = ROOT / "tests" / "golden"


def tiny_config(**overrides):
    from parq_export.config import PARQConfig

    base = dict(resnet_depth=18, resnet_width=8, fpn_channels=16, heads=2, ffn_dim=32,
                num_queries=20, ray_samples=8, image_size=(64, 48))
    base.update(overrides)
    return PARQConfig(**base)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory):
    import torch

    from parq_export import checkpoint
    from parq_export.model import PARQ

    torch.manual_seed(0)
    model = PARQ(tiny_config())
    # A larger query spread than nn.Embedding's N(0, 1) init: points all over the box.
    with torch.no_grad():
        model.refpoint.weight.uniform_(-2.5, 2.5)
    path = tmp_path_factory.mktemp("tiny") / "tiny.pt"
    checkpoint.save(path, model)
    return path


@pytest.fixture(scope="session")
def tiny_model(tiny_checkpoint, tmp_path_factory):
    from parq_export.export import export

    out = tmp_path_factory.mktemp("tiny_export") / "tiny_model"
    export(tiny_checkpoint, out, log=lambda *_: None)
    return out


def make_official(path: pathlib.Path, *flags) -> pathlib.Path:
    subprocess.run([sys.executable, str(GOLDEN / "make_official_ckpt.py"), str(path),
                    "--seed", "0", *flags], check=True)
    return path


@pytest.fixture(scope="session")
def official_checkpoint(tmp_path_factory):
    return make_official(tmp_path_factory.mktemp("official") / "official.ckpt")


@pytest.fixture(scope="session")
def official_model(official_checkpoint, tmp_path_factory):
    from parq_export.export import export

    out = tmp_path_factory.mktemp("official_export") / "official_model"
    export(official_checkpoint, out, log=lambda *_: None)
    return out


def write_scannet(folder: pathlib.Path, frames: int = 12, size=(96, 72), seed: int = 0,
                  authors_names: bool = False, step=0.15) -> pathlib.Path:
    """A ScanNet-layout capture of noise images along a short walk (z-up world)."""
    rng = np.random.default_rng(seed)
    for sub in ("color", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    w, h = size
    K = np.eye(4)
    K[0, 0] = K[1, 1] = 0.9 * w
    K[0, 2], K[1, 2] = w / 2 - 0.5, h / 2 - 0.5
    np.savetxt(folder / "intrinsic" / "intrinsic_color.txt", K)
    for i in range(frames):
        color = f"frame-{i:06d}.color.png" if authors_names else f"{i}.png"
        pose = f"frame-{i:06d}.pose.txt" if authors_names else f"{i}.txt"
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(
            folder / "color" / color)
        np.savetxt(folder / "pose" / pose,
                   camera_pose([step * i, 0.02 * i, 1.5], 0.05 * i, np.radians(15)))
    return folder


def model_with_card(source: pathlib.Path, folder: pathlib.Path, card: dict) -> pathlib.Path:
    """``folder`` (new): model folder ``source``'s two graphs with ``card`` as its model.json,
    written as given (unchecked, so that a test can hand the runtime a broken card)."""
    import json

    folder.mkdir()
    for name in ("backbone.onnx", "layer.onnx"):
        (folder / name).write_bytes((source / name).read_bytes())
    (folder / "model.json").write_text(json.dumps(card))
    return folder


@pytest.fixture
def scannet_folder(tmp_path):
    return write_scannet(tmp_path / "scene")
