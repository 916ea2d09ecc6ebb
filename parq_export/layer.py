"""One recurrent PARQ layer: query position encoding, a DETR decoder layer and the box heads.

The same weights are applied at every iteration.  Shapes use B snippets, K queries, C channels,
S = N * h * w memory tokens ordered (view, row, column), H heads of d = C / H channels.

Two ways of computing the cross-attention are provided; both are exact:

* ``reference``: ``nn.MultiheadAttention`` on the memory, projecting keys and values again at
  every iteration, as the authors' code does;
* ``operands``: attention on per-snippet operands from :meth:`PARQLayer.attention_operands`,
  either the projected keys/values (the *cached* form: the projections run once per snippet)
  or the raw memory with the key/value weights folded onto the query side (the *folded* form:
  the memory is never projected).  In the folded form, for head h with W_k,h (d x C):
  q_h . (W_k,h m + b_k,h) = (q_h W_k,h) . m + q_h . b_k,h, and the last term is constant over
  the keys, so softmax removes it; and sum_j a_j (W_v,h m_j + b_v,h) = W_v,h (sum_j a_j m_j) +
  b_v,h because the weights a_j sum to one.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .ray_encoding import denormalize_points, inverse_sigmoid, normalize_points


def sine_encoding(points: torch.Tensor, dim_t: torch.Tensor) -> torch.Tensor:
    """PETR sine encoding of normalised points (..., 3) -> (..., 3 * F), axes in order (y, x, z).

    Each axis is scaled by 2 pi and divided by dim_t (F,); sin on even, cos on odd indices,
    interleaved.
    """
    e = (points * (2 * math.pi))[..., None] / dim_t                    # (..., 3, F)
    e = torch.stack([e[..., 0::2].sin(), e[..., 1::2].cos()], -1).flatten(-2)
    return torch.cat([e[..., 1, :], e[..., 0, :], e[..., 2, :]], -1)


def rotation_from_6d(a: torch.Tensor) -> torch.Tensor:
    """6D rotation (Zhou et al.) (..., 6) -> (..., 3, 3) with columns (x, y, z).

    x = normalise(a[0:3]); z = normalise(x cross a[3:6]); y = z cross x.
    """
    def normalise(v):
        return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp(min=1e-8)

    def cross(u, v):
        return torch.stack([u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1],
                            u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
                            u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]], -1)

    x = normalise(a[..., 0:3])
    z = normalise(cross(x, a[..., 3:6]))
    y = cross(z, x)
    return torch.stack([x, y, z], -1)


class MLPHead(nn.Module):
    """3DETR GenericMLP as Conv1d(kernel 1) on (B, C, K) with the authors' module indices:
    ``hidden`` x [conv without bias, GroupNorm(1, C), ReLU, Dropout(0)], then conv with bias.

    GroupNorm(1, C) normalises over all C x K values of a snippet, so a query's output depends
    on the other queries of the same snippet (as in the authors' model).
    """

    def __init__(self, dim: int, out: int, hidden: int):
        super().__init__()
        layers = []
        for _ in range(hidden):
            layers += [nn.Conv1d(dim, dim, 1, bias=False), nn.GroupNorm(1, dim), nn.ReLU(),
                       nn.Dropout(0.0)]
        layers.append(nn.Conv1d(dim, out, 1))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


class DecoderLayer(nn.Module):
    """DETR decoder layer, post-norm, with the parameter names of the authors' layer.

    ``dropout`` and ``attention_dropout`` (attributes, not weights: 0 unless
    :meth:`set_dropout` sets them) are the authors' training dropout, 0.1 both in their
    configuration: ``dropout`` on the three residual branches and inside the FFN,
    ``attention_dropout`` on the attention weights of both attentions, as DETR's layer, in
    every form.  They act only in training mode; at 0 nothing is drawn, so a run without them
    is bit for bit as before.  The attention weights are the large tensor, (B, H, K, S) per
    iteration: on the demo's configuration dropping them makes a training step about 1.5 times
    as long (0.30 s against 0.21), the others cost 3%.

    ``key_dropout`` (also an attribute, 0 unless set) is DropKey (Li et al., CVPR 2023) on the
    cross-attention, beyond the authors' recipe: each (query, cell) score is dropped before the
    softmax, which renormalises over the cells kept, instead of dropping weights after it.  Its
    mask is drawn 16 bits a draw from one 64-bit draw per four scores and given to the fused
    kernel as its mask, so it costs little: forward and backward of one cross-attention at the
    demo's size (batch 4, 64 queries, 3,600 cells) took 19 ms with it against 14 without and 39
    with ``attention_dropout`` through the same kernel (medians of 15, a 2-core EPYC); a
    whole training step of the demo, 0.229 s against 0.189 without (docs/demo-experiments.md)."""

    def __init__(self, dim: int, heads: int, ffn_dim: int):
        super().__init__()
        self.heads = heads
        self.dropout = 0.0
        self.attention_dropout = 0.0
        self.key_dropout = 0.0
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=0.0)
        self.multihead_attn = nn.MultiheadAttention(dim, heads, dropout=0.0)
        self.linear1 = nn.Linear(dim, ffn_dim)
        self.linear2 = nn.Linear(ffn_dim, dim)
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.norm3 = nn.LayerNorm(dim)

    def self_attention(self, x: torch.Tensor, pos: torch.Tensor,
                       mask: torch.Tensor | None = None) -> torch.Tensor:
        """(B, K, C) -> (B, K, C); q = k = x + pos, v = x.  ``mask`` (K, K) bool, True where
        query i may not attend to query j (training's denoising queries, see
        ``parq_train.denoise``); None: all attend to all, as at run time."""
        B, K, C = x.shape
        H, d = self.heads, C // self.heads
        W, b = self.self_attn.in_proj_weight, self.self_attn.in_proj_bias
        qk = x + pos
        q = F.linear(qk, W[:C], b[:C]).view(B, K, H, d).transpose(1, 2) * d ** -0.5
        k = F.linear(qk, W[C:2 * C], b[C:2 * C]).view(B, K, H, d).transpose(1, 2)
        v = F.linear(x, W[2 * C:], b[2 * C:]).view(B, K, H, d).transpose(1, 2)
        scores = q @ k.transpose(-1, -2)
        if mask is not None:
            scores = scores.masked_fill(mask, float("-inf"))
        ctx = self.drop(torch.softmax(scores, -1), self.attention_dropout) @ v
        return self.self_attn.out_proj(ctx.transpose(1, 2).reshape(B, K, C))

    def attention_operands(self, memory: torch.Tensor, cached: bool, fused: bool = False,
                           token_bias: bool = True):
        """Per-snippet operands of the cross-attention, memory (B, S, C) ->
        keys (B, Hk, S, Dk), values (B, Hk, S, Dv), key_map (H, d, Dk), value_map (H, Dv, d),
        value_bias (H, 1, d).  Cached: Hk = H, Dk = Dv = d, identity maps (None when
        ``fused``: the fused kernel needs none).  Folded: Hk = 1,
        Dk = Dv = C, the memory itself with W_k,h and W_v,h^T as maps.

        ``token_bias`` False (the exported cached form) leaves the biases off the S tokens:
        the key bias b_k adds q_h . b_k,h to every score of a query, which softmax removes, and
        the value bias is added once to the weighted sum, whose weights sum to 1.  Both are
        exact up to rounding and save two passes over (S, C) per snippet.  Training keeps the
        authors' arithmetic (True), so that a seeded run gives the same model as before."""
        C = memory.shape[-1]
        H, d = self.heads, C // self.heads
        W, b = self.multihead_attn.in_proj_weight, self.multihead_attn.in_proj_bias
        value_bias = b[2 * C:].reshape(H, 1, d)
        if cached:
            B, S, _ = memory.shape
            b_k, b_v = (b[C:2 * C], b[2 * C:]) if token_bias else (None, None)
            keys = F.linear(memory, W[C:2 * C], b_k).view(B, S, H, d).transpose(1, 2)
            values = F.linear(memory, W[2 * C:], b_v).view(B, S, H, d).transpose(1, 2)
            if token_bias:
                value_bias = memory.new_zeros(H, 1, d)
            if fused:
                return keys, values, None, None, value_bias
            eye = torch.eye(d, dtype=memory.dtype, device=memory.device).expand(H, d, d)
            return keys, values, eye, eye, value_bias
        keys = memory[:, None]
        return (keys, keys, W[C:2 * C].reshape(H, d, C),
                W[2 * C:].reshape(H, d, C).transpose(1, 2), value_bias)

    def cross_queries(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, K, C) -> the cross-attention's queries per head, scaled: (B, H, K, d)."""
        B, K, C = x.shape
        H, d = self.heads, C // self.heads
        W, b = self.multihead_attn.in_proj_weight, self.multihead_attn.in_proj_bias
        return F.linear(x, W[:C], b[:C]).view(B, K, H, d).transpose(1, 2) * d ** -0.5

    def cross_attention(self, x, keys, values, key_map, value_map, value_bias):
        """x (B, K, C) attends to the operands of :meth:`attention_operands` -> (B, K, C).

        With ``key_map`` None (the ``fused`` form, for training: the cached operands without
        maps) torch's fused scaled-dot-product kernel computes the attention; it is the same
        arithmetic in another rounding order.  At the demo's size on this CPU the attention's
        forward and backward take 19-20 ms instead of 28-35 per iteration of a batch of 4 (one
        thread), a whole training step 0.185 s instead of 0.205 (two threads, parq-train).

        The queries are grouped like the keys, (B, Hk, H / Hk * K, Dk), so one batched product
        serves both forms without broadcasting over heads.
        """
        B, K, C = x.shape
        H = self.heads
        q = self.cross_queries(x)
        dropped = self.dropped_keys((B, H, K, keys.shape[2]), q.device)
        if key_map is None:  # the fused form: one kernel, no (K, S) softmax kept for backward
            p = self.attention_dropout if self.training else 0.0
            ctx = F.scaled_dot_product_attention(
                q, keys, values, scale=1.0, dropout_p=p,
                attn_mask=None if dropped is None else ~dropped) + value_bias
            return self.multihead_attn.out_proj(ctx.transpose(1, 2).reshape(B, K, C))
        q = (q @ key_map).reshape(B, keys.shape[1], -1, keys.shape[-1])
        scores = q @ keys.transpose(-1, -2)                             # (B, Hk, H/Hk*K, S)
        if dropped is not None:
            scores = scores.masked_fill(dropped.view(scores.shape), float("-inf"))
        attn = torch.softmax(scores, -1)
        attn = self.drop(attn, self.attention_dropout)
        ctx = (attn @ values).reshape(B, H, K, -1) @ value_map + value_bias
        return self.multihead_attn.out_proj(ctx.transpose(1, 2).reshape(B, K, C))

    def forward(self, x, pos, operands=None, memory=None, attend=None, self_mask=None):
        """x, pos (B, K, C).  Give ``operands`` (fast form), ``attend`` (a function computing
        the cross-attention of x + pos, (B, K, C) -> (B, K, C)) or ``memory`` (B, S, C), in
        which case nn.MultiheadAttention runs exactly as in the authors' code.  ``self_mask``:
        see :meth:`self_attention`."""
        if memory is None:
            if attend is None:
                def attend(y):
                    return self.cross_attention(y, *operands)
            x = self.norm1(x + self.drop(self.self_attention(x, pos, self_mask)))
            x = self.norm2(x + self.drop(attend(x + pos)))
        else:
            tgt, p, mem = x.transpose(0, 1), pos.transpose(0, 1), memory.transpose(0, 1)
            q = tgt + p
            tgt = self.norm1(tgt + self.drop(self.self_attn(q, q, value=tgt,
                                                            attn_mask=self_mask)[0]))
            B, K, S = x.shape[0], x.shape[1], memory.shape[1]
            dropped = self.dropped_keys((B, self.heads, K, S), x.device)
            tgt = self.norm2(tgt + self.drop(self.multihead_attn(
                tgt + p, mem, value=mem,
                attn_mask=None if dropped is None else dropped.view(-1, K, S))[0]))
            x = tgt.transpose(0, 1)
        return self.norm3(x + self.drop(self.linear2(self.drop(F.relu(self.linear1(x))))))

    def set_dropout(self, rate: float, attention: float = 0.0, key: float = 0.0) -> None:
        """Training dropout: ``rate`` on the residual branches and the FFN, ``attention`` on
        the attention weights (also nn.MultiheadAttention's, which the ``memory`` form runs),
        ``key`` DropKey on the cross-attention's scores (see the class)."""
        self.dropout, self.attention_dropout, self.key_dropout = rate, attention, key
        self.self_attn.dropout = self.multihead_attn.dropout = attention

    def dropped_keys(self, shape: tuple, device) -> torch.Tensor | None:
        """DropKey's mask for cross-attention scores of ``shape`` (B, H, K, S): bool, True
        where query k of head h does not read cell s in this step, each with probability
        ``key_dropout`` rounded to 1/65536; None in evaluation mode or at rate 0 (nothing is
        drawn then).  Every form draws the same mask from the same generator state, in this
        (B, H, K, S) order, so the forms agree under one seed."""
        if not (self.key_dropout and self.training):
            return None
        count = math.prod(shape)
        bits = torch.randint(-2 ** 63, 2 ** 63 - 1, (-(-count // 4),), dtype=torch.int64,
                             device=device).view(torch.int16)[:count]
        return (bits < -2 ** 15 + round(self.key_dropout * 2 ** 16)).view(shape)

    def drop(self, x: torch.Tensor, rate: float | None = None) -> torch.Tensor:
        """Training dropout at ``rate`` (default ``self.dropout``; see the class); the identity
        at 0 or in evaluation mode."""
        rate = self.dropout if rate is None else rate
        if rate and self.training:
            return F.dropout(x, rate)
        return x


class PARQLayer(nn.Module):
    """One PARQ iteration: query content (B, K, C) + reference points (B, K, 3), normalised to
    [0, 1]^3 with the decoder scale -> box parameters in the local frame:

    center (B, K, 3) metres, size (B, K, 3) metres (full extents), ortho6d (B, K, 6),
    rotation (B, K, 3, 3) = R_local_object, logits (B, K, classes + 1; the last is no-object),
    next_reference_points (B, K, 3) normalised.
    """

    def __init__(self, dim, heads, ffn_dim, num_classes, mean_sizes, decoder_scale,
                 pos_features=128, temperature=10000.0):
        super().__init__()
        self.scale = tuple(float(s) for s in decoder_scale)
        self.position_encoder = nn.Sequential(nn.Linear(3 * pos_features, dim), nn.ReLU(),
                                              nn.Linear(dim, dim))
        self.decoder = DecoderLayer(dim, heads, ffn_dim)
        self.heads = nn.ModuleDict({
            "sem_cls_head": MLPHead(dim, num_classes + 1, 0),
            "center_head": MLPHead(dim, 3, 2),
            "size_head": MLPHead(dim, 3, 0),
            "rotation_head": MLPHead(dim, 6, 2),
        })
        i = torch.arange(pos_features, dtype=torch.float32)
        self.register_buffer("dim_t", temperature ** (2 * (i // 2) / pos_features),
                             persistent=False)
        self.register_buffer("mean_sizes", torch.tensor(mean_sizes, dtype=torch.float32),
                             persistent=False)

    def attention_operands(self, memory: torch.Tensor, cached: bool, fused: bool = False,
                           token_bias: bool = True):
        return self.decoder.attention_operands(memory, cached, fused, token_bias)

    def forward(self, query_content, reference_points, operands=None, memory=None,
                attend=None, self_mask=None, split=None) -> dict:
        """``self_mask``: see DecoderLayer.self_attention.  ``split`` K: the heads decode
        queries [:K] and [K:] apart, so that the heads' GroupNorm statistics of the first K
        are those of the K alone (training's denoising queries come after them)."""
        pos = self.position_encoder(sine_encoding(reference_points, self.dim_t))
        tokens = self.decoder(query_content, pos, operands=operands, memory=memory,
                              attend=attend, self_mask=self_mask)
        if split is None:
            return self.decode(tokens, reference_points)
        parts = [self.decode(tokens[:, :split], reference_points[:, :split]),
                 self.decode(tokens[:, split:], reference_points[:, split:])]
        return {k: torch.cat([p[k] for p in parts], 1) for k in parts[0]}

    def decode(self, tokens: torch.Tensor, reference_points: torch.Tensor) -> dict:
        x = tokens.transpose(1, 2)                                      # (B, C, K)
        logits = self.heads["sem_cls_head"](x).transpose(1, 2)
        offset = self.heads["center_head"](x).transpose(1, 2)
        center = denormalize_points(torch.sigmoid(offset + inverse_sigmoid(reference_points)),
                                    self.scale)
        label = torch.argmax(torch.softmax(logits, -1), -1)
        size = torch.exp(self.heads["size_head"](x).transpose(1, 2)) * self.mean_sizes[label]
        ortho6d = self.heads["rotation_head"](x).transpose(1, 2)
        return {"center": center, "size": size, "ortho6d": ortho6d,
                "rotation": rotation_from_6d(ortho6d), "logits": logits,
                "next_reference_points": normalize_points(center, self.scale)}
