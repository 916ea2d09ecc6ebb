"""Hyperparameters of a PARQ model.

The defaults are the authors' ScanNet release (``config/eval.yaml`` of ymingxie/PARQ, which
overrides several values of their ``default.py``).  Every field here ends up in the model card
(``model.json``) so that the numpy runtime needs nothing else to drive the exported graphs.

Frames used below (see ``parq_runtime.geometry``):
  * camera: OpenCV axes, x right, y down, z forward;
  * local (snippet) frame: the gravity-aligned pseudo camera of the middle view, x left, y up,
    z forward on the horizontal plane.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from parq_runtime import fusion as scene_fusion  # not `fusion`: a field below has that name
from parq_runtime import preprocess
from parq_runtime.model_card import DEFAULT_RUN, PHASE_COUNTS

# Class names of the authors' ScanNet (Scan2CAD) release, in label order; label 9 is no-object.
SCANNET_CLASSES = ("chair", "table", "cabinet", "trash bin", "bookshelf", "display", "sofa",
                   "bathtub", "other")

# Mean full extents (x, y, z) in metres per class, from the authors' data/average_scan2cad.txt;
# "other" and no-object use (1, 1, 1) as in their BoxProcessor.  Object y is up.
SCANNET_MEAN_SIZES = (
    (0.55067552, 0.84943989, 0.5786128),   # chair
    (1.24506049, 0.66165523, 0.72455878),  # table
    (0.95658434, 0.99974904, 0.56246602),  # cabinet
    (0.36641966, 0.45580824, 0.27876528),  # trash bin
    (1.05132399, 1.3471979, 0.33744382),   # bookshelf
    (0.60740744, 0.4752175, 0.16435075),   # display
    (1.68820774, 0.76637348, 0.89351734),  # sofa
    (0.85305378, 0.43925023, 0.51612006),  # bathtub
    (1.0, 1.0, 1.0),                       # other
    (1.0, 1.0, 1.0),                       # no-object
)

RESNET_DEPTHS = (18, 34, 50, 101)


# The network input: P2 (stride 4) must be exactly (w/4, h/4) for the camera scaling to hold.
IMAGE_MULTIPLE, MIN_IMAGE_SIDE = 4, 32


def image_size_fits(width: int, height: int) -> bool:
    """Whether (width, height) can be a PARQ input: both multiples of IMAGE_MULTIPLE, at least
    MIN_IMAGE_SIDE."""
    return all(v % IMAGE_MULTIPLE == 0 and v >= MIN_IMAGE_SIDE for v in (width, height))


@dataclass(frozen=True)
class PARQConfig:
    """Architecture and pre/post-processing constants of one PARQ model.

    Scales are ``[xmin, xmax, ymin, ymax, zmin, zmax]`` in metres in the local frame.
    ``image_size`` is ``(width, height)`` of the network input.
    """

    resnet_depth: int = 50
    resnet_width: int = 64            # channels after the stem (torchvision: 64)
    fpn_channels: int = 256           # per FPN level; four levels are concatenated
    heads: int = 4
    ffn_dim: int = 768
    num_queries: int = 256
    ray_samples: int = 64
    ray_depth: tuple = (0.25, 5.25)   # metres along the optical axis, log-spaced
    ray_scale: tuple = (-3.0, 3.0, -2.0, 0.5, 0.25, 5.25)
    decoder_scale: tuple = (-3.0, 3.0, -2.0, 0.5, 0.25, 5.25)
    classes: tuple = SCANNET_CLASSES
    mean_sizes: tuple = SCANNET_MEAN_SIZES  # len(classes) + 1 rows, the last for no-object
    image_size: tuple = (320, 240)
    # how frames of another size are brought to image_size (parq_runtime.preprocess):
    # "pillow-bilinear", the authors' antialiasing filter, or "point", pixel centres as a
    # renderer samples them (parq-train's models, trained on frames rendered at image_size)
    image_filter: str = preprocess.AUTHORS_FILTER
    pixel_mean: tuple = (0.485, 0.456, 0.406)
    pixel_std: tuple = (0.229, 0.224, 0.225)
    iterations: int = 8               # recurrent iterations used in training
    score_threshold: float = 0.8      # the authors' evaluation threshold
    nms_iou: float = 0.1              # class-agnostic NMS on axis-aligned bounds
    eval_region: tuple = (-1.5, 1.5, 0.0, 2.0)  # kept centers: local x in (a, b), z in (c, d)
    fusion: str = scene_fusion.AUTHORS_MODE     # scene fusion (parq_runtime.fusion)
    min_support: int = scene_fusion.AUTHORS_MIN_SUPPORT  # snippets that must see a box
    ray_ratio: float = scene_fusion.RAY_RATIO   # along / across the ray, "ray" fusion only
    scene_nms: float | None = None    # IoU of one object's scene boxes; None: off
    # classes pulled to stand on the floor found in the images (parq_runtime.floor); (): none
    floor_classes: tuple = ()
    floor_weight: float = scene_fusion.FLOOR_WEIGHT
    # which class a scene box reports: "best" (the authors') or "vote" (parq_runtime.fusion)
    labels: str = scene_fusion.AUTHORS_LABELS
    # IoU at which a snippet's detection joins a scene box (parq_runtime.fusion; the authors' 0.1)
    match_iou: float = scene_fusion.MATCH_IOU
    # learned queries, most useful first (parq_train.tune): a run with fewer queries starts
    # from the first ones; () = farthest-point sampling (parq_runtime.queries)
    query_order: tuple = ()
    # keyframes between a snippet's views: 1 = consecutive (the authors'); a model trained on
    # wider snippets (parq-train --gap) records its gap here and parq-run uses it
    snippet_gap: int = 1
    # what parq-run runs without --iters / --queries: the setting the post-processing was
    # chosen for (parq_train.tune); the runtime's default for cards without one (2 x 32) unless
    # a tuning chose otherwise
    run_iters: int = DEFAULT_RUN["iters"]
    run_queries: int = DEFAULT_RUN["queries"]
    # and whether it adds each snippet's mirror-image run (parq-run --mirror); min_support then
    # counts runs, two a snippet
    run_mirror: bool = DEFAULT_RUN["mirror"]
    # and at how many point-sampling grids (parq-run --phases; 2 only helps frames at least
    # twice the network size), with the minimum support at two grids (None: twice min_support)
    run_phases: int = DEFAULT_RUN["phases"]
    phase_support: int | None = None
    extra: dict = field(default_factory=dict, compare=False)  # free-form provenance

    feature_stride = 4  # FPN level P2; every level is resized to it

    def __post_init__(self):
        problems = []
        if self.resnet_depth not in RESNET_DEPTHS:
            problems.append(f"resnet_depth {self.resnet_depth} not in {RESNET_DEPTHS}")
        if self.resnet_width < 8 or self.resnet_width % 8:
            problems.append(f"resnet_width {self.resnet_width} must be a multiple of 8")
        if self.feature_dim % self.heads:
            problems.append(f"feature dim {self.feature_dim} not divisible by {self.heads} heads")
        if len(self.mean_sizes) != len(self.classes) + 1:
            problems.append(f"{len(self.mean_sizes)} mean sizes for {len(self.classes)} classes "
                            "(need one more, for no-object)")
        if len(self.ray_scale) != 6 or len(self.decoder_scale) != 6:
            problems.append("ray_scale and decoder_scale need 6 values")
        w, h = self.image_size
        if not image_size_fits(w, h):
            problems.append(f"image_size {self.image_size}: width and height must be "
                            f"multiples of {IMAGE_MULTIPLE}, at least {MIN_IMAGE_SIDE}")
        problems += scene_fusion.problems(self.fusion, self.min_support, self.ray_ratio,
                                          self.scene_nms, tuple(self.floor_classes),
                                          self.floor_weight, self.classes, self.labels,
                                          self.match_iou)
        if self.query_order and sorted(self.query_order) != list(range(self.num_queries)):
            problems.append(f"query_order must be a permutation of the {self.num_queries} "
                            "learned queries")
        if self.image_filter not in preprocess.FILTERS:
            problems.append(f"image_filter {self.image_filter!r} not in {preprocess.FILTERS}")
        if isinstance(self.snippet_gap, bool) or not isinstance(self.snippet_gap, int) \
                or self.snippet_gap < 1:
            problems.append(f"snippet_gap {self.snippet_gap!r} must be an integer >= 1")
        for name in ("run_iters", "run_queries"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                problems.append(f"{name} {value!r} must be an integer >= 1")
        if not isinstance(self.run_mirror, bool):
            problems.append(f"run_mirror {self.run_mirror!r} must be True or False")
        if isinstance(self.run_phases, bool) or self.run_phases not in PHASE_COUNTS:
            problems.append(f"run_phases {self.run_phases!r} must be 1 or 2")
        if self.phase_support is not None and (
                isinstance(self.phase_support, bool) or not isinstance(self.phase_support, int)
                or self.phase_support < 1):
            problems.append(f"phase_support {self.phase_support!r} must be an integer >= 1")
        if not 0 < self.ray_depth[0] < self.ray_depth[1]:
            problems.append(f"ray_depth {self.ray_depth} must be 0 < near < far")
        if problems:
            raise ValueError("invalid PARQ config: " + "; ".join(problems))

    @property
    def feature_dim(self) -> int:
        """Channels of the concatenated FPN levels = decoder width."""
        return 4 * self.fpn_channels

    @property
    def feature_size(self) -> tuple:
        """(width, height) of the feature map (stride 4)."""
        return (self.image_size[0] // self.feature_stride,
                self.image_size[1] // self.feature_stride)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {k: (list(map(list, v)) if k == "mean_sizes" else list(v) if isinstance(v, tuple)
                    else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "PARQConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown config fields: {sorted(unknown)}")
        kw = {}
        for k, v in d.items():
            if k == "mean_sizes":
                v = tuple(tuple(float(x) for x in row) for row in v)
            elif isinstance(v, list):
                v = tuple(v)
            kw[k] = v
        return cls(**kw)

    def replace(self, **kw) -> "PARQConfig":
        return dataclasses.replace(self, **kw)
