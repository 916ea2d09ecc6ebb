"""parq_export.rebuild: a checkpoint read back out of a model folder's graphs."""
import numpy as np
import pytest
import torch

from parq_runtime.errors import ParqError


def test_rebuild_gives_back_the_exported_weights(tiny_checkpoint, tiny_model):
    from parq_export import checkpoint, rebuild

    original = checkpoint.load(tiny_checkpoint).model().state_dict()
    model = rebuild.rebuild(tiny_model, log=lambda *_: None)   # raises unless it reproduces
    state = model.state_dict()
    key_bias = "layer.decoder.multihead_attn.in_proj_bias"
    C = model.config.feature_dim
    compared = 0
    for name, value in original.items():
        if name.endswith(("running_mean", "running_var")) or "bn" in name \
                or "downsample.1" in name or name == key_bias:
            continue
        assert torch.allclose(state[name], value, rtol=1e-5, atol=1e-6), name
        compared += 1
    assert compared > 50
    # the key bias is dropped by the export (softmax removes it): 0; query and value kept
    assert torch.equal(state[key_bias][C:2 * C], torch.zeros(C))
    assert torch.allclose(state[key_bias][2 * C:], original[key_bias][2 * C:], atol=1e-6)
    # batch norms come back as the same function: scale and shift
    for prefix in ("backbone.body.bn1", "backbone.body.layer2.0.downsample.1"):
        def scale_shift(s):
            scale = s[f"{prefix}.weight"] / torch.sqrt(s[f"{prefix}.running_var"] + 1e-5)
            return scale, s[f"{prefix}.bias"] - s[f"{prefix}.running_mean"] * scale
        for a, b in zip(scale_shift(state), scale_shift(original)):
            assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)


def test_rebuild_keeps_what_a_tuning_wrote_into_the_card(tiny_model, tmp_path):
    """A tuning rewrites the card, not the card's ``config``: the rebuilt checkpoint takes the
    post-processing and run setting from the card, so that exported again it gives the same
    card."""
    from parq_export import card_rewrite, checkpoint, rebuild
    from parq_export.export import export

    def update(card):
        card["postprocess"].update(score_threshold=0.6, fusion="ray", min_support=3,
                                   ray_ratio=30.0, scene_nms=0.1, floor_classes=["chair"],
                                   floor_weight=10.0, labels="vote", phase_support=5)
        card["run"] = {"iters": 3, "queries": 8, "mirror": True, "phases": 2}

    tuned = card_rewrite.rewrite(tiny_model, tmp_path / "tuned", update)
    model = rebuild.rebuild(tmp_path / "tuned", log=lambda *_: None)
    checkpoint.save(tmp_path / "rebuilt.pt", model)
    again = export(tmp_path / "rebuilt.pt", tmp_path / "again", log=lambda *_: None).card
    for key in ("postprocess", "run", "query_order"):
        assert again[key] == tuned[key], key


def test_a_probe_value_is_found_and_other_values_are_not():
    from parq_export import rebuild

    values = 1.0 + rebuild.SPACING * (np.arange(6) + 1) * rebuild.ULP
    k, scaled = rebuild.locate(np.float32(values), total=6)
    assert k.tolist() == list(range(6)) and not scaled.any()
    k, scaled = rebuild.locate(np.float32(values / 2), total=6)      # a batch norm's scale
    assert k.tolist() == list(range(6)) and scaled.all()
    # sums of weights (a folded bias), values between probe values, config constants
    k, _ = rebuild.locate(np.float32(np.r_[values[:3] + values[3:], values[:2] + rebuild.ULP * 2,
                                           0.25, 1.0]), total=6)
    assert (k < 0).all()


def test_rebuild_refuses_what_is_not_a_model_folder(tmp_path, capsys):
    from parq_export import rebuild

    with pytest.raises(ParqError, match="model.json"):
        rebuild.rebuild(tmp_path, log=lambda *_: None)
    out = tmp_path / "x.pt"
    out.write_bytes(b"")
    assert rebuild.main([str(tmp_path), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already exists" in err[0]
    assert rebuild.main([str(tmp_path), "-o", str(tmp_path / "y.pt")]) == 2
    assert not (tmp_path / "y.pt").exists()
