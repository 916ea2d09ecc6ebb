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


def test_golden_probes(official_model, case):
    """The image features (before the ray encoding) and the ray encoding at the probes."""
    meta, expected, images = case
    det = Detector(official_model)
    net, camera, _, T_local_camera = det.prepare(images, expected["intrinsics"],
                                                 expected["cam_to_world"])
    names = [o.name for o in det.backbone.get_outputs()]
    out = dict(zip(names, det.backbone.run(None, {
        "images": net, "cached_features": np.zeros((0, 1024, 60, 80), np.float32),
        "camera": camera.astype(np.float32),
        "T_local_camera": T_local_camera.astype(np.float32), "key_value": np.array(False)})))
    v, c, y, x = expected["probe_index"].T
    features = out["features"][v, c, y, x]
    ray = out["memory"][v, y, x, c] - features
    np.testing.assert_allclose(features, expected["probe_features"], atol=2e-4)
    np.testing.assert_allclose(ray, expected["probe_ray_encoding"], atol=2e-4)
