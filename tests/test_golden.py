"""The authors' own outputs (../shared/golden/official-case) reproduced by the exported model
run with the numpy runtime, within the tolerances of ../shared/golden/README.md."""
import json

import numpy as np
import pytest
from PIL import Image

from parq_runtime.detector import Detector

from conftest import GOLDEN

CASE = GOLDEN / "official-case"


@pytest.fixture(scope="module")
def case():
    meta = json.loads((CASE / "case.json").read_text())
    expected = np.load(CASE / "expected.npz")
    images = [np.asarray(Image.open(CASE / f"{i}.png").convert("RGB"))
              for i in range(meta["views"])]
    return meta, expected, images


@pytest.mark.parametrize("form", ["cached", "folded"])
def test_golden_case(official_model, case, form):
    meta, expected, images = case
    det = Detector(official_model)
    result = det.detect(images, expected["intrinsics"], expected["cam_to_world"],
                        iters=meta["iterations"], queries=meta["queries"], form=form)
    np.testing.assert_allclose(result.T_world_local, expected["T_world_local_4x4"][0],
                               atol=1e-6)
    assert len(result.iterations) == meta["iterations"]
    for l, it in enumerate(result.iterations):
        e = {k: expected[f"iter{l}_{k}"] for k in ("reference", "center", "size", "ortho6d",
                                                    "rotation", "logits")}
        np.testing.assert_allclose(it.reference, e["reference"], atol=1e-4, rtol=0)
        np.testing.assert_allclose(it.center, e["center"], atol=1e-4, rtol=0)
        np.testing.assert_allclose(it.rotation, e["rotation"], atol=1e-3, rtol=0)
        np.testing.assert_allclose(it.logits, e["logits"], atol=1e-3, rtol=0)
        top2 = np.sort(e["logits"], -1)[:, -2:]
        clear = top2[:, 1] - top2[:, 0] > 1e-3
        np.testing.assert_allclose(it.size[clear], e["size"][clear], rtol=1e-3, atol=0)


def test_golden_probes(official_model, official_checkpoint, case):
    """The image features (before the ray encoding) and the ray encoding at the probes,
    formed from backbone.onnx's factors: the levels resized to P2's grid in numpy
    (loop.resize_taps) and the checkpoint's last ray-MLP layer applied to ray_hidden."""
    from parq_export.checkpoint import load
    from parq_runtime.detector import empty_cache
    from parq_runtime.loop import resize_taps

    meta, expected, images = case
    det = Detector(official_model)
    net, camera, _, T_local_camera = det.prepare(images, expected["intrinsics"],
                                                 expected["cam_to_world"])
    names = [o.name for o in det.backbone.get_outputs()]
    out = dict(zip(names, det.backbone.run(None, {
        "images": net, **empty_cache((80, 60), 1024), "camera": camera.astype(np.float32),
        "T_local_camera": T_local_camera.astype(np.float32), "key_value": np.array(False)})))
    v, c, y, x = expected["probe_index"].T
    F = 256
    features = np.zeros(len(v))
    for level in range(4):
        sel = c // F == level
        P = out[f"level_{level}"]
        lo_r, hi_r, fr = resize_taps(60, P.shape[1])
        lo_c, hi_c, fc = resize_taps(80, P.shape[2])
        vv, cc, yy, xx = v[sel], c[sel] % F, y[sel], x[sel]
        a, b = fr[yy], fc[xx]
        features[sel] = ((1 - a) * (1 - b) * P[vv, lo_r[yy], lo_c[xx], cc]
                         + (1 - a) * b * P[vv, lo_r[yy], hi_c[xx], cc]
                         + a * (1 - b) * P[vv, hi_r[yy], lo_c[xx], cc]
                         + a * b * P[vv, hi_r[yy], hi_c[xx], cc])
    ray_out = load(official_checkpoint).model().ray_encoder.mlp[2]
    W2 = ray_out.weight.detach().numpy().astype(np.float64)
    b2 = ray_out.bias.detach().numpy().astype(np.float64)
    ray = np.einsum("pk,pk->p", out["ray_hidden"][v, y, x].astype(np.float64), W2[c]) + b2[c]
    np.testing.assert_allclose(features, expected["probe_features"], atol=2e-4)
    np.testing.assert_allclose(ray, expected["probe_ray_encoding"], atol=2e-4)
