"""Loading PARQ checkpoints without executing pickled code.

Three layouts are read:

* the authors' release file ``{'state_dict': OrderedDict}`` (``parq_release.ckpt``);
* their PyTorch-Lightning training checkpoints, whose ``hyper_parameters`` pickle a
  ``yacs.config.CfgNode`` (read here with yacs absent);
* this package's own format ``{'format': 'parq-onnx', 'format_version': 1, 'config': {...},
  'state_dict': {...}}``.

Every file is unpickled by :class:`_RestrictedUnpickler`, which resolves only the names on
torch's weights-only allow-list (tensor rebuilders, plain containers).  Classes a checkpoint
names beyond those (yacs' CfgNode, Lightning's AttributeDict, ...) are replaced by
:class:`Inert` stand-ins that only record their pickled state, so no code from the file runs.

The authors' key names are mapped to this package's (``backbone2d.resnet_fpn.body.*`` ->
``backbone.body.*`` ...).  Their heads are stored twice (``box3d_decoder.mlp_heads.*`` and
``box3d_decoder.parq_module.decoder.mlp_heads.*``, one module in their model): the copies must be
equal.  ``box3d_decoder.parq_module.decoder.norm.*`` exists but their forward never uses it, so it
is dropped.  FPN keys are accepted in torchvision's new (``inner_blocks.0.0.weight``) and old
(``inner_blocks.0.weight``) styles.
"""
from __future__ import annotations

import hashlib
import io
import pathlib
import pickle
import re
from dataclasses import dataclass, field

import torch

from parq_runtime import files
from parq_runtime.errors import ParqError

from .config import PARQConfig, SCANNET_CLASSES, SCANNET_MEAN_SIZES
from .model import PARQ

FORMAT = "parq-onnx"
FORMAT_VERSION = 1

OFFICIAL_PREFIXES = (
    ("backbone2d.resnet_fpn.body.", "backbone.body."),
    ("backbone2d.resnet_fpn.fpn.", "backbone.fpn."),
    ("add_ray_pe.encoder.", "ray_encoder.mlp."),
    ("box3d_decoder.refpoint.", "refpoint."),
    ("box3d_decoder.mlp_heads.", "layer.heads."),
    ("box3d_decoder.parq_module.decoder.layers.0.", "layer.decoder."),
    ("box3d_decoder.parq_module.decoder.position_encoder.", "layer.position_encoder."),
)
OFFICIAL_UNUSED = ("box3d_decoder.parq_module.decoder.norm.",)
OFFICIAL_HEAD_COPY = ("box3d_decoder.parq_module.decoder.mlp_heads.", "box3d_decoder.mlp_heads.")


class Inert(dict):
    """Stand-in for a class or function named in a checkpoint outside torch's allow-list: it
    keeps constructor arguments, items and pickled state as plain data and has no behaviour."""

    def __init__(self, *args, **kwargs):
        super().__init__()
        self.args = args
        self.items_ = []

    def __setstate__(self, state):
        self.state = state

    def append(self, item):
        self.items_.append(item)

    def extend(self, items):
        self.items_.extend(items)


def _stand_in(qualified: str) -> type:
    module, _, name = qualified.rpartition(".")
    return type(name, (Inert,), {"__module__": module, "__qualname__": name})


class _RestrictedUnpickler(pickle.Unpickler):
    """Python's documented way to unpickle untrusted data: ``find_class`` is the only door to
    code, and it opens only on torch's weights-only allow-list (tensor and storage rebuilders,
    plain containers, dtypes); every other name becomes an :class:`Inert` stand-in.  torch's
    own ``weights_only`` unpickler is not used as is because it refuses the dict subclasses
    (yacs' CfgNode, Lightning's AttributeDict) that training checkpoints hold."""

    # str subclasses that checkpoints record versions with: read back as plain str.
    AS_STR = {"torch.torch_version.TorchVersion"}

    def find_class(self, module, name):
        allowed = torch._weights_only_unpickler._get_allowed_globals()
        qualified = f"{module}.{name}"
        if qualified in allowed:
            return allowed[qualified]
        if qualified in self.AS_STR:
            return str
        return _stand_in(qualified)


class _RestrictedPickle:
    """The ``pickle_module`` handed to torch.load."""

    Unpickler = _RestrictedUnpickler
    __name__ = "parq_restricted_pickle"

    @staticmethod
    def load(file, **kwargs):
        return _RestrictedUnpickler(file, **kwargs).load()


def safe_load(path) -> object:
    """torch.load through :class:`_RestrictedUnpickler`; ParqError for unreadable files."""
    path = pathlib.Path(path)
    if path.is_dir():
        raise ParqError(f"{path}: is a folder, expected a checkpoint file")
    if not path.is_file():
        raise ParqError(f"{path}: checkpoint not found")
    try:
        return torch.load(str(path), map_location="cpu", weights_only=False,
                          pickle_module=_RestrictedPickle)
    except Exception as e:  # any failure to parse is the file's fault, never code from it
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ParqError(f"{path}: not a readable PyTorch checkpoint ({first})") from None


@dataclass
class Checkpoint:
    """A loaded checkpoint: this package's config and state dict (its key names), the layout it
    came in, and the config fields that were not recorded in it and took the release's values."""

    config: PARQConfig
    state_dict: dict
    layout: str
    sha256: str
    defaulted: list = field(default_factory=list)

    def model(self) -> PARQ:
        model = PARQ(self.config)
        model.load_state_dict(self.state_dict, strict=True)
        return model.eval()


def sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load(path) -> Checkpoint:
    """Read any supported layout; raises ParqError naming missing and unexpected keys."""
    obj = safe_load(path)
    digest = sha256(path)
    if isinstance(obj, dict) and obj.get("format") == FORMAT:
        if obj.get("format_version") != FORMAT_VERSION:
            raise ParqError(f"{path}: {FORMAT} checkpoint version {obj.get('format_version')}, "
                            f"this package reads version {FORMAT_VERSION}")
        try:
            config = PARQConfig.from_dict(obj["config"])
        except (ValueError, TypeError, KeyError) as e:
            raise ParqError(f"{path}: bad config: {e}") from None
        state = dict(obj["state_dict"])
        layout = FORMAT
        defaulted = []
    elif isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        hyper = obj.get("hyper_parameters")
        layout = "lightning" if hyper is not None else "official"
        state = official_to_package(obj["state_dict"], path)
        config, defaulted = infer_config(state, hyper if isinstance(hyper, dict) else {}, path)
    else:
        raise ParqError(f"{path}: not a PARQ checkpoint (no 'state_dict' found)")
    check_keys(state, config, path)
    return Checkpoint(config, state, layout, digest, defaulted)


def official_to_package(sd: dict, path) -> dict:
    """Rename the authors' keys to this package's; checks the duplicated heads."""
    out, unknown = {}, []
    copies = {}
    for key, value in sd.items():
        if not isinstance(value, torch.Tensor):
            unknown.append(key)
            continue
        if key.startswith(OFFICIAL_UNUSED):
            continue
        if key.startswith(OFFICIAL_HEAD_COPY[0]):
            copies[OFFICIAL_HEAD_COPY[1] + key[len(OFFICIAL_HEAD_COPY[0]):]] = value
            continue
        for old, new in OFFICIAL_PREFIXES:
            if key.startswith(old):
                name = new + key[len(old):]
                name = re.sub(r"^(backbone\.fpn\.(?:inner|layer)_blocks\.\d+)\.(weight|bias)$",
                              r"\1.0.\2", name)
                out[name] = value
                break
        else:
            out[key] = value  # reported as unexpected by check_keys
    for key, value in copies.items():
        if key not in sd:
            continue  # reported through the missing primary key
        if value.shape != sd[key].shape or not torch.equal(value, sd[key]):
            raise ParqError(f"{path}: the two copies of head tensor {key} differ; the official "
                            "model holds one module under both names")
    if unknown:
        raise ParqError(f"{path}: state_dict entries that are not tensors: {_few(unknown)}")
    return out


def _get(node, dotted: str):
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def infer_config(state: dict, hyper: dict, path) -> tuple:
    """PARQConfig of an official or Lightning checkpoint: shapes from the tensors, the rest
    from the yacs config when there is one, else the release's eval.yaml values."""
    release = PARQConfig()

    def shape(key, dim, default):
        # A missing tensor takes the release's value here; check_keys then lists every
        # missing key at once.
        return state[key].shape[dim] if key in state else default

    layer_counts = []
    for i in range(1, 5):
        blocks = {int(m.group(1)) for k in state
                  for m in [re.match(rf"backbone\.body\.layer{i}\.(\d+)\.", k)] if m}
        layer_counts.append(max(blocks) + 1 if blocks else 0)
    bottleneck = "backbone.body.layer1.0.conv3.weight" in state
    depths = {(False, (2, 2, 2, 2)): 18, (False, (3, 4, 6, 3)): 34,
              (True, (3, 4, 6, 3)): 50, (True, (3, 4, 23, 3)): 101}
    depth = depths.get((bottleneck, tuple(layer_counts)))
    if not any(layer_counts):
        depth = release.resnet_depth
    if depth is None:
        raise ParqError(f"{path}: ResNet with blocks {layer_counts} "
                        f"({'bottleneck' if bottleneck else 'basic'}) is not ResNet18/34/50/101")
    num_classes = shape("layer.heads.sem_cls_head.layers.0.weight", 0,
                        len(release.classes) + 1) - 1
    if num_classes != len(SCANNET_CLASSES):
        raise ParqError(f"{path}: {num_classes} classes; only the authors' 9 ScanNet classes "
                        "have known names and mean sizes (convert to this package's format "
                        "with a config to export other label sets)")
    defaulted = set()

    def pick(field_name, *dotted):
        """Values of the yacs keys, or the release's value of the field if one is absent."""
        values = [_get(hyper, d) for d in dotted]
        if any(v is None for v in values):
            defaulted.add(field_name)
            return getattr(release, field_name)
        return values[0] if len(values) == 1 else tuple(values)

    track = pick("eval_region", "MODEL.DECODER.TRACK_SCALE")
    if len(track) == 6:  # their TRACK_SCALE: x range, y range (unused), z range
        track = (track[0], track[1], track[4], track[5])
    try:
        config = PARQConfig(
            resnet_depth=depth,
            resnet_width=shape("backbone.body.conv1.weight", 0, release.resnet_width),
            fpn_channels=shape("backbone.fpn.inner_blocks.0.0.weight", 0, release.fpn_channels),
            heads=int(pick("heads", "MODEL.DECODER.TRANSFORMER.DEC_HEADS")),
            ffn_dim=shape("layer.decoder.linear1.weight", 0, release.ffn_dim),
            num_queries=shape("refpoint.weight", 0, release.num_queries),
            ray_samples=shape("ray_encoder.mlp.0.weight", 1, 3 * release.ray_samples) // 3,
            ray_depth=tuple(float(v) for v in pick(
                "ray_depth", "MODEL.TOKENIZER.MIN_DEPTH", "MODEL.TOKENIZER.MAX_DEPTH")),
            ray_scale=tuple(float(v) for v in pick(
                "ray_scale", "MODEL.TOKENIZER.RAY_POINTS_SCALE")),
            decoder_scale=tuple(float(v) for v in pick(
                "decoder_scale", "MODEL.DECODER.TRANSFORMER.SCALE")),
            classes=SCANNET_CLASSES,
            mean_sizes=SCANNET_MEAN_SIZES,
            iterations=int(pick("iterations", "MODEL.DECODER.TRANSFORMER.DEC_LAYERS")),
            score_threshold=float(pick("score_threshold", "MODEL.DECODER.CONF_THRESH")),
            eval_region=tuple(float(v) for v in track),
        )
    except (ValueError, TypeError) as e:
        raise ParqError(f"{path}: {e}") from None
    shared = _get(hyper, "MODEL.DECODER.TRANSFORMER.SHARE_WEIGHTS")
    if shared is False or any(".decoder.layers.1." in k for k in state):
        raise ParqError(f"{path}: decoder layers without shared weights are not supported")
    return config, sorted(defaulted)


def check_keys(state: dict, config: PARQConfig, path) -> None:
    """Raise ParqError naming missing, unexpected and mis-shaped tensors."""
    with torch.device("meta"):
        expected = PARQ(config).state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    wrong = [f"{k} {tuple(state[k].shape)} (expected {tuple(v.shape)})"
             for k, v in expected.items() if k in state and state[k].shape != v.shape]
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing keys: {_few(missing)}")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected keys: {_few(unexpected)}")
    if wrong:
        parts.append(f"{len(wrong)} tensors of the wrong shape: {_few(wrong)}")
    if parts:
        raise ParqError(f"{path}: does not match the PARQ architecture it describes; "
                        + "; ".join(parts))


def _few(items, n=6) -> str:
    items = list(items)
    return ", ".join(items[:n]) + (f" and {len(items) - n} more" if len(items) > n else "")


def save(path, model: PARQ, metadata: dict | None = None) -> None:
    """Write this package's checkpoint format (loadable with weights_only=True), whole or not
    at all: serialised in memory, then written to a temporary file renamed into place, so a
    run stopped while it writes leaves no partial checkpoint and an earlier one whole
    (ParqError naming the path when it cannot be written)."""
    buffer = io.BytesIO()
    torch.save({"format": FORMAT, "format_version": FORMAT_VERSION,
                "config": model.config.to_dict(),
                "state_dict": {k: v.detach().cpu().contiguous()
                               for k, v in model.state_dict().items()},
                "metadata": dict(metadata or {})}, buffer)
    files.atomic_write(path, buffer.getvalue())
