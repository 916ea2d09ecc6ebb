"""Floating-point operations of each PARQ stage, counted from the architecture (2 per
multiply-add; convolutions and matrix products only, elementwise work is not counted).

Check: ResNet50's body at 224x224 counts 4.09 GMAC, the usual figure.
"""
from __future__ import annotations

from parq_export.backbone import RESNET_LAYOUT, Bottleneck


def _conv(h, w, cin, cout, k, stride=1):
    ho, wo = -(-h // stride), -(-w // stride)
    return 2 * ho * wo * cin * cout * k * k, ho, wo


def resnet_fpn(config, width=None, height=None) -> float:
    """One image through ResNet + FPN (the four output levels)."""
    w = width or config.image_size[0]
    h = height or config.image_size[1]
    block, counts = RESNET_LAYOUT[config.resnet_depth]
    c = config.resnet_width
    flops, h, w = _conv(h, w, 3, c, 7, 2)
    h, w = -(-h // 2), -(-w // 2)  # max pool
    cin = c
    sizes, channels = [], []
    for i, n in enumerate(counts):
        width_i = c * 2 ** i
        for j in range(n):
            stride = 2 if (i > 0 and j == 0) else 1
            cout = width_i * block.expansion
            if block is Bottleneck:
                f1, _, _ = _conv(h, w, cin, width_i, 1)
                f2, ho, wo = _conv(h, w, width_i, width_i, 3, stride)
                f3, _, _ = _conv(ho, wo, width_i, cout, 1)
                f = f1 + f2 + f3
            else:
                f1, ho, wo = _conv(h, w, cin, width_i, 3, stride)
                f2, _, _ = _conv(ho, wo, width_i, cout, 3)
                f = f1 + f2
            if j == 0 and (stride != 1 or cin != cout):
                f += _conv(h, w, cin, cout, 1, stride)[0]
            flops += f
            cin, h, w = cout, ho, wo
        sizes.append((h, w))
        channels.append(cin)
    fpn = config.fpn_channels
    for (hh, ww), ch in zip(sizes, channels):
        flops += _conv(hh, ww, ch, fpn, 1)[0] + _conv(hh, ww, fpn, fpn, 3)[0]
    return float(flops)


def ray_encoding(config, views, hidden_only: bool = False) -> float:
    """The ray MLP over every token; ``hidden_only``: its first layer, all that backbone.onnx
    computes in the folded form (the second is applied to the factors, see
    parq_export.factored)."""
    fw, fh = config.feature_size
    C = config.feature_dim
    return float(2 * views * fw * fh * (3 * config.ray_samples * C + (0 if hidden_only
                                                                      else C * C)))


def key_value_projection(config, views) -> float:
    fw, fh = config.feature_size
    C = config.feature_dim
    return float(2 * 2 * views * fw * fh * C * C)


def layer(config, views, queries, form) -> float:
    """One iteration: everything in the layer graph.  ``reference`` = the authors' way, with the
    key/value projection inside."""
    fw, fh = config.feature_size
    S = views * fw * fh
    C, H, K, F = config.feature_dim, config.heads, queries, config.ffn_dim
    d = C // H
    dense = 2 * K * (3 * 128 * C + C * C       # position MLP
                     + 3 * C * C + C * C       # self-attention projections
                     + 2 * C * C               # cross-attention q and out projections
                     + 2 * C * F               # FFN
                     + 2 * 2 * C * C           # center and rotation hidden layers
                     + C * (len(config.classes) + 1 + 3 + 3 + 6))
    dense += 2 * 2 * H * K * K * d             # self-attention scores and sum
    if form == "folded":
        # factored (detector.folded_width), then the W2-folded maps; the resizes of the
        # score and weight maps are not counted (elementwise-sized).
        from parq_runtime.detector import folded_width

        attention = 2 * 2 * H * K * folded_width(views, config.feature_size, C) \
            + 2 * 2 * H * K * d * 2 * C + 2 * K * C * C     # maps; W2 on the query content
    else:
        attention = 2 * 2 * K * S * C + 2 * 2 * H * K * d * d
    if form == "reference":
        attention += key_value_projection(config, views)
    return float(dense + attention)
