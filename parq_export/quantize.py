"""int8 image encoder: static QDQ quantization of backbone.onnx's convolutions.

onnxruntime.quantization rewrites every Conv of the ResNet-FPN (and nothing else: the ray
encoding, the memory and the attention operands stay fp32) with per-channel int8 weights and
uint8 activations whose ranges are calibrated on frames of generated scenes.  ``reduce_range``
(7-bit weights) avoids the saturation of the u8 x s8 multiply-add on CPUs without VNNI.

Whether it pays is measured, not assumed: ``benchmarks/int8.py`` reports speed and the F1
change on the demo model's held-out scenes.
"""
from __future__ import annotations

import pathlib
import tempfile

import numpy as np

from parq_runtime import keyframes, preprocess
from parq_runtime.detector import empty_cache, snippet_inputs
from parq_runtime.errors import ParqError
from parq_runtime.readers import open_capture

# The default calibration set: parq-synth scenes no training, tuning or benchmark uses.
CALIBRATION = {"scenes": 8, "seed": 5000, "frames": 30}


def generate_calibration(folder, size) -> pathlib.Path:
    """Write the default calibration scenes (CALIBRATION) at ``size`` = (w, h) into
    ``folder``, keeping those already there (a cache: the same arguments write the same
    scenes)."""
    from parq_synth import generate

    generate(folder, CALIBRATION["scenes"], CALIBRATION["seed"], frames=CALIBRATION["frames"],
             size=tuple(size), skip_existing=True)
    return pathlib.Path(folder)


def calibration_feeds(scenes_dir, card_config, views: int = 3, limit: int = 48) -> list:
    """Backbone inputs for ``limit`` snippets of the generated scenes under ``scenes_dir``."""
    folders = sorted(p.parent for p in pathlib.Path(scenes_dir).glob("*/boxes.json"))
    if not folders:
        raise ParqError(f"{scenes_dir}: no generated scenes to calibrate with (parq-synth)")
    feeds = []
    for folder in folders:
        capture = open_capture(folder)
        keys = keyframes.select([f.cam_to_world for f in capture.frames])
        for window in keyframes.windows(keys, views)[:2]:
            frames = [capture.frames[i] for i in window]
            prepared = [preprocess.prepare(f.load_image(), f.intrinsics,
                                           card_config.image_size, card_config.image_filter)
                        for f in frames]
            images, camera, _, T_local_camera = snippet_inputs(
                prepared, np.stack([f.cam_to_world for f in frames]), card_config.feature_stride,
                capture.up)
            feeds.append({
                "images": images,
                **empty_cache(card_config.feature_size, card_config.feature_dim),
                "camera": camera.astype(np.float32),
                "T_local_camera": T_local_camera.astype(np.float32),
                "key_value": np.array(False)})
            if len(feeds) >= limit:
                return feeds
    return feeds


def quantize_backbone(backbone_path, out_path, feeds: list, reduce_range: bool = True) -> None:
    from onnxruntime.quantization import (CalibrationDataReader, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.items = iter(feeds)

        def get_next(self):
            return next(self.items, None)

    with tempfile.TemporaryDirectory() as tmp:
        prepared = pathlib.Path(tmp) / "pre.onnx"
        quant_pre_process(str(backbone_path), str(prepared), skip_symbolic_shape=True)
        quantize_static(str(prepared), str(out_path), Reader(),
                        quant_format=QuantFormat.QDQ, op_types_to_quantize=["Conv"],
                        per_channel=True, reduce_range=reduce_range,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
