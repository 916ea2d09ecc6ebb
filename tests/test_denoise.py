"""Denoising queries (parq_train.denoise): training-only extra queries that must leave the
learned queries' outputs as they are and carry the losses of their own targets."""
import numpy as np
import pytest
import torch

from parq_export import verify
from parq_export.model import PARQ
from parq_export.ray_encoding import denormalize_points
from parq_train import denoise, train

from conftest import tiny_config
from test_train import tiny_snippets


def snippet_tensors(config, seed=1):
    rng = np.random.default_rng(seed)
    camera, T_local_camera = verify.random_snippet(rng, 3, config)
    w, h = config.image_size
    torch.manual_seed(seed)
    return (torch.rand(2, 3, 3, h, w), torch.from_numpy(camera)[None].expand(2, -1, -1),
            torch.from_numpy(T_local_camera)[None].expand(2, -1, -1, -1))


@pytest.mark.parametrize("form", ["reference", "cached", "fused"])
def test_learned_queries_do_not_see_the_denoising_queries(form):
    """With extra points appended, the K learned queries' outputs at every iteration are
    those of a run without them (self-attention mask, heads decoded apart); the extra
    queries' own outputs do depend on the learned ones."""
    config = tiny_config(num_queries=16)
    model = PARQ(config).eval()
    images, camera, T_local_camera = snippet_tensors(config)
    extra = torch.rand(2, 5, 3) * 0.8 + 0.1
    with torch.no_grad():
        alone = model(images, camera, T_local_camera, iterations=3, form=form)
        joint = model(images, camera, T_local_camera, iterations=3, form=form,
                      extra_points=extra)
    for a, j in zip(alone, joint):
        assert j["center"].shape == (2, 21, 3)
        for key in ("center", "size", "rotation", "logits", "reference"):
            torch.testing.assert_close(j[key][:, :16], a[key], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(joint[0]["reference"][:, 16:],
                               denormalize_points(extra, config.decoder_scale))
    with torch.no_grad():
        model.refpoint.weight.add_(0.5)
        moved = model(images, camera, T_local_camera, iterations=1, form=form,
                      extra_points=extra)
    assert not torch.allclose(moved[0]["center"][:, 16:], joint[0]["center"][:, 16:])


def test_noised_queries_lie_within_the_scale_of_their_targets():
    """Offsets reach, and do not pass, scale x the half extent: horizontally the larger of
    width and depth (the box turns about the up axis), vertically the height."""
    config = tiny_config()
    box = torch.tensor([[0.4, 0.8, 1.0]])
    targets = [{"centers": torch.tensor([[0.3, -1.0, 2.0]]).repeat(300, 1),
                "sizes": box.repeat(300, 1)},
               {"centers": torch.zeros(0, 3), "sizes": torch.zeros(0, 3)}]
    half = torch.tensor([0.5, 0.4, 0.5], dtype=torch.float64)
    rng = np.random.default_rng(0)
    for scale in (0.5, 1.0):
        points, index = denoise.noised_queries(targets, config.decoder_scale, rng, scale)
        assert points.shape == (2, 300, 3)
        assert index[0].tolist() == list(range(300)) and index[1].tolist() == [-1] * 300
        metres = denormalize_points(points[0].double(), config.decoder_scale)
        offset = metres - targets[0]["centers"].double()
        assert torch.all(offset.abs() <= scale * half + 1e-6)
        assert torch.all(offset.amax(0) > 0.9 * scale * half)
        assert torch.all(offset.amin(0) < -0.9 * scale * half)


def test_denoising_loss_is_zero_for_a_perfect_prediction_and_counts_only_real_rows():
    targets = [{"labels": torch.tensor([2, 0]), "centers": torch.tensor([[0.0, 0, 2], [1, 0, 3]]),
                "sizes": torch.ones(2, 3), "rotations": torch.eye(3).expand(2, 3, 3)}]
    index = torch.tensor([[1, 0, -1]])
    logits = torch.full((1, 3, 10), -30.0)
    logits[0, 0, 0] = logits[0, 1, 2] = 30.0
    out = {"logits": logits, "center": torch.tensor([[[1.0, 0, 3], [0, 0, 2], [9, 9, 9]]]),
           "size": torch.ones(1, 3, 3), "rotation": torch.eye(3).expand(1, 3, 3, 3)}
    total, parts = denoise.denoise_loss([out], index, targets, torch.ones(10, dtype=torch.long))
    assert float(total) == pytest.approx(0.0, abs=1e-6)
    out["center"] = out["center"] + torch.tensor([0.3, 0.0, 0.0])
    total, parts = denoise.denoise_loss([out], index, targets, torch.ones(10, dtype=torch.long))
    assert parts["center"] == pytest.approx(0.1, abs=1e-6)   # mean over 2 rows x 3 axes
    assert float(total) == pytest.approx(0.5, abs=1e-5)      # weight 5


def test_denoising_class_weight_scales_only_the_class_term():
    targets = [{"labels": torch.tensor([2]), "centers": torch.tensor([[0.0, 0, 2]]),
                "sizes": torch.ones(1, 3), "rotations": torch.eye(3)[None]}]
    out = {"logits": torch.zeros(1, 1, 10), "center": torch.tensor([[[0.3, 0.0, 2.0]]]),
           "size": torch.ones(1, 1, 3), "rotation": torch.eye(3)[None, None]}
    folds = torch.ones(10, dtype=torch.long)
    full, parts = denoise.denoise_loss([out], torch.tensor([[0]]), targets, folds)
    boxes, parts0 = denoise.denoise_loss([out], torch.tensor([[0]]), targets, folds, 0.0)
    assert parts0 == parts and parts["class"] == pytest.approx(np.log(10), abs=1e-5)
    assert float(full) - float(boxes) == pytest.approx(np.log(10), abs=1e-5)
    assert float(boxes) == pytest.approx(5 * 0.1, abs=1e-5)


def test_training_with_denoising_queries_learns_them():
    """The denoising loss falls, the model that comes out has no trace of them, and scale 0
    trains exactly as without the option."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    kwargs = dict(seed=0, folds_of_class=[1] * 9, batch_size=2, iterations=2, lr=2e-3,
                  log=lambda *_: None, log_every=10)
    model, history = train.train(config, snippets, steps=60, denoise_scale=1.0, **kwargs)
    assert history[-1]["denoise center"] < 0.75 * history[0]["denoise center"], history
    assert history[-1]["total"] < 0.6 * history[0]["total"], history
    assert set(model.state_dict()) == set(PARQ(config).state_dict())
    plain, _ = train.train(config, snippets, steps=2, **kwargs)
    zero, _ = train.train(config, snippets, steps=2, denoise_scale=0.0, **kwargs)
    with_dn, _ = train.train(config, snippets, steps=2, denoise_scale=1.0, **kwargs)
    a, b, c = plain.state_dict(), zero.state_dict(), with_dn.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
