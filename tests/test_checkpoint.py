"""Every checkpoint layout loads to the same weights; broken ones fail with a useful message;
pickled code never runs."""
import os
import pathlib
import pickle

import pytest
import torch

from parq_export import checkpoint
from parq_export.model import PARQ
from parq_runtime.errors import ParqError

from conftest import make_official, tiny_config


@pytest.fixture(scope="module")
def layouts(official_checkpoint, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("layouts")
    return {"official": official_checkpoint,
            "official-old-fpn": make_official(tmp / "old.ckpt", "--fpn-style", "old"),
            "lightning": make_official(tmp / "lightning.ckpt", "--lightning")}


def test_all_official_layouts_give_the_same_model(layouts, tmp_path):
    loaded = {name: checkpoint.load(path) for name, path in layouts.items()}
    assert loaded["official"].layout == "official"
    assert loaded["lightning"].layout == "lightning"
    reference = loaded["official"].state_dict
    assert len(reference) == 350 - 20 - 2  # minus the duplicated heads and the unused norm
    for name, ck in loaded.items():
        assert ck.config.resnet_depth == 50 and ck.config.num_queries == 256
        assert ck.config.feature_dim == 1024 and ck.config.ray_samples == 64
        assert set(ck.state_dict) == set(reference), name
        for key, value in reference.items():
            assert torch.equal(ck.state_dict[key], value), (name, key)
    # the Lightning checkpoint's yacs config was read (yacs is not installed here)
    with pytest.raises(ImportError):
        __import__("yacs")
    assert "heads" in loaded["official"].defaulted
    model = loaded["lightning"].model()
    checkpoint.save(tmp_path / "ours.pt", model)
    ours = checkpoint.load(tmp_path / "ours.pt")
    assert ours.layout == "parq-onnx" and ours.config == loaded["official"].config
    assert all(torch.equal(ours.state_dict[k], v) for k, v in reference.items())


def _official_state(tmp_path):
    model = PARQ(tiny_config(num_queries=4))
    sd = {}
    for k, v in model.state_dict().items():
        k = (k.replace("backbone.", "backbone2d.resnet_fpn.", 1)
             .replace("ray_encoder.mlp.", "add_ray_pe.encoder.")
             .replace("refpoint.", "box3d_decoder.refpoint.")
             .replace("layer.heads.", "box3d_decoder.mlp_heads.")
             .replace("layer.decoder.", "box3d_decoder.parq_module.decoder.layers.0.")
             .replace("layer.position_encoder.",
                      "box3d_decoder.parq_module.decoder.position_encoder."))
        sd[k] = v.clone()
        if k.startswith("box3d_decoder.mlp_heads."):
            sd["box3d_decoder.parq_module.decoder.mlp_heads." + k[24:]] = v.clone()
    return sd


def test_partial_checkpoint_names_missing_and_unexpected_keys(tmp_path):
    sd = _official_state(tmp_path)
    del sd["add_ray_pe.encoder.2.weight"]
    del sd["box3d_decoder.parq_module.decoder.layers.0.norm1.bias"]
    sd["box3d_decoder.something_new.weight"] = torch.zeros(3)
    torch.save({"state_dict": sd}, tmp_path / "partial.ckpt")
    with pytest.raises(ParqError) as e:
        checkpoint.load(tmp_path / "partial.ckpt")
    message = str(e.value)
    assert "2 missing keys" in message
    assert "ray_encoder.mlp.2.weight" in message and "layer.decoder.norm1.bias" in message
    assert "1 unexpected keys: box3d_decoder.something_new.weight" in message


def test_wrong_shape_and_differing_head_copies(tmp_path):
    sd = _official_state(tmp_path)
    sd["box3d_decoder.parq_module.decoder.linear1.weight"] = torch.zeros(1)
    sd = {k.replace("decoder.linear1", "decoder.layers.0.linear1"): v for k, v in sd.items()}
    sd["box3d_decoder.parq_module.decoder.layers.0.linear1.weight"] = torch.zeros(32, 7)
    torch.save({"state_dict": sd}, tmp_path / "shape.ckpt")
    with pytest.raises(ParqError, match=r"wrong shape: layer.decoder.linear1.weight \(32, 7\)"):
        checkpoint.load(tmp_path / "shape.ckpt")
    sd = _official_state(tmp_path)
    sd["box3d_decoder.parq_module.decoder.mlp_heads.size_head.layers.0.bias"] += 1
    torch.save({"state_dict": sd}, tmp_path / "heads.ckpt")
    with pytest.raises(ParqError, match="two copies of head tensor"):
        checkpoint.load(tmp_path / "heads.ckpt")


class Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_pickled_code_is_never_executed(tmp_path):
    marker = tmp_path / "pwned"
    sd = _official_state(tmp_path)
    torch.save({"state_dict": sd, "payload": Exploit(marker)}, tmp_path / "evil.ckpt")
    # torch's own weights-only loader refuses the file outright:
    with pytest.raises(Exception):
        torch.load(tmp_path / "evil.ckpt", weights_only=True)
    ck = checkpoint.load(tmp_path / "evil.ckpt")
    assert not marker.exists()
    assert ck.config.num_queries == 4
    torch.save({"state_dict": {"refpoint": Exploit(marker)}}, tmp_path / "evil2.ckpt")
    with pytest.raises(ParqError, match="not tensors"):
        checkpoint.load(tmp_path / "evil2.ckpt")
    assert not marker.exists()


def test_unreadable_files(tmp_path):
    with pytest.raises(ParqError, match="not found"):
        checkpoint.load(tmp_path / "nope.ckpt")
    (tmp_path / "text.ckpt").write_text("hello")
    with pytest.raises(ParqError, match="not a readable PyTorch checkpoint"):
        checkpoint.load(tmp_path / "text.ckpt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ParqError, match="not a PARQ checkpoint"):
        checkpoint.load(tmp_path / "other.pt")
    (tmp_path / "legacy.pkl").write_bytes(pickle.dumps({"state_dict": {}}))
    with pytest.raises(ParqError):
        checkpoint.load(tmp_path / "legacy.pkl")
    good = tmp_path / "good.pt"
    checkpoint.save(good, PARQ(tiny_config()))
    data = good.read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ParqError, match="not a readable PyTorch checkpoint"):
        checkpoint.load(tmp_path / "truncated.pt")


def test_torch_version_strings_read_back_as_str(tmp_path):
    """Training records hold torch.__version__ (a str subclass outside the allow-list): it
    reads back as its text, not as an inert stand-in that cannot be saved again."""
    import torch

    from parq_export.checkpoint import safe_load

    torch.save({"torch": torch.__version__}, tmp_path / "v.pt")
    value = safe_load(tmp_path / "v.pt")["torch"]
    assert type(value) is str and value == str(torch.__version__)
