"""parq-train --dense-weight: the auxiliary dense loss (parq_train.dense)."""
import numpy as np
import torch

from parq_train import dense, mirror, pretrain, resume, train
from parq_train.data import scene_snippets, training_scenes

from conftest import tiny_config
from test_train import tiny_snippets


def with_dense_targets(snippets, config, seed=0, mark=True):
    """The tiny snippets with dense targets: the left half of each view shows class 4 at 2 m,
    the right half the room at 4 m; ``mark`` darkens the images' left halves to match (a
    pattern the probe can learn), else the images are left as they were."""
    rng = np.random.default_rng(seed)
    w, h = config.feature_size
    out = []
    for s in snippets:
        labels = np.full((3, h, w), len(config.classes), np.uint8)
        labels[:, :, : w // 2] = 4
        depth = np.where(labels == 4, np.log(2.0), np.log(4.0)).astype(np.float32)
        depth[:, 0, 0] = np.nan                           # a cell without depth is skipped
        images = s.images.copy()
        if mark:
            left = images[:, :, : images.shape[2] // 2]
            left[:] = rng.integers(0, 60, left.shape)
        s = mirror.replace(s, images=images, dense_depth=depth, dense_labels=labels)
        out.append(s)
    return out


def test_a_snippets_dense_targets_are_the_pretrainings_for_its_views(tmp_path):
    """scene_snippets(dense=True) gives each view the targets pretraining gives its keyframe."""
    config = tiny_config()
    folder = training_scenes(tmp_path / "train", 1, seed=3, frames=12, size=config.image_size,
                             log=lambda *_: None)[0]
    images, depths, labels = pretrain.frame_targets(folder, config)
    snippets = scene_snippets(folder, config, views=3, stride=1, dense=True)
    plain = scene_snippets(folder, config, views=3, stride=1)
    assert plain[0].dense_depth is None and plain[0].dense_labels is None
    by_image = {images[i].tobytes(): i for i in range(len(images))}
    for s in snippets:
        assert s.dense_depth.shape == s.dense_labels.shape == (3,) + config.feature_size[::-1]
        for v in range(3):
            i = by_image[s.images[v].tobytes()]
            np.testing.assert_array_equal(s.dense_labels[v], labels[i])
            np.testing.assert_array_equal(s.dense_depth[v], depths[i])
    # objects are seen: some cells hold a class other than the room
    assert any((s.dense_labels < len(config.classes)).any() for s in snippets)


def test_the_dense_loss_trains_the_probe_and_the_backbone_and_the_objective_still_falls():
    config = tiny_config(num_queries=16)
    snippets = with_dense_targets(tiny_snippets(config), config)
    model, history = train.train(config, snippets, steps=60, seed=0, folds_of_class=[1] * 9,
                                 batch_size=2, iterations=2, lr=2e-3, log=lambda *_: None,
                                 log_every=10, dense_weight=1.0)
    first, last = history[0], history[-1]
    assert last["dense class"] < 0.5 * first["dense class"], history
    assert last["dense depth"] < 0.5 * first["dense depth"], history
    assert last["center"] < first["center"], history
    # the probe is not part of the model: the exported architecture is unchanged
    plain, _ = train.train(config, snippets, steps=1, seed=0, folds_of_class=[1] * 9,
                           batch_size=2, iterations=2, log=lambda *_: None)
    assert model.state_dict().keys() == plain.state_dict().keys()
    assert not model.backbone._forward_hooks


def test_weight_zero_trains_exactly_as_without_the_targets():
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    kwargs = dict(steps=3, seed=0, folds_of_class=[1] * 9, batch_size=2, iterations=2,
                  log=lambda *_: None)
    a, _ = train.train(config, snippets, **kwargs)
    marked = with_dense_targets(snippets, config, mark=False)
    b, _ = train.train(config, marked, dense_weight=0.0, **kwargs)
    c, _ = train.train(config, marked, dense_weight=1.0, **kwargs)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)


def test_mirroring_flips_the_dense_targets_with_the_images():
    config = tiny_config()
    s = with_dense_targets(tiny_snippets(config), config)[0]
    m = mirror.mirrored(s, config.feature_stride)
    np.testing.assert_array_equal(m.dense_labels, s.dense_labels[:, :, ::-1])
    np.testing.assert_array_equal(m.dense_depth, s.dense_depth[:, :, ::-1])
    assert (m.dense_labels[:, :, -1] == 4).all() and (s.dense_labels[:, :, 0] == 4).all()


def test_a_dense_run_resumed_from_its_state_gives_the_same_weights(tmp_path):
    """The probe's weights and moments are part of the saved state."""
    config = tiny_config(num_queries=16)
    snippets = with_dense_targets(tiny_snippets(config), config)
    kwargs = dict(steps=5, seed=0, folds_of_class=[1] * 9, batch_size=1, iterations=2,
                  lr=2e-3, log=lambda *_: None, log_every=2, snapshot_every=2,
                  dense_weight=1.0)
    states = []
    whole, history = train.train(config, snippets, save_state=states.append, **kwargs)
    assert any(k.startswith("probe.") for k in states[0]["model"])
    path = tmp_path / "state.pt"
    resume.save(path, states[0], {"seed": 0}, {})
    state, _ = resume.read(path, {"seed": 0})
    resumed, resumed_history = train.train(config, snippets, model=train.new_model(config, 5),
                                           state=state, **kwargs)
    a, b = whole.state_dict(), resumed.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    strip = lambda h: [{k: v for k, v in e.items() if k != "seconds"} for e in h]  # noqa: E731
    assert strip(resumed_history) == strip(history)
