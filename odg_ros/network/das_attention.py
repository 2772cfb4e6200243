"""DaS (Dynamic-and-Static) attention, paper Sec. 3.4 (Eq. 15-16).

Self-attention over concat(Q_d, Q_s), then split back, so dynamic and static queries
exchange information both ways. As in OPUS, the logits of head h are biased by
``-distance(centroid_i, centroid_j) * tau_h(query_i)`` (tau from a zero-initialised linear
layer with bias U(0, 2)) so attention starts local. With ``mix_sets=False`` (ablation) the
two sets attend only within themselves.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.attention.flex_attention import flex_attention


def use_flex_attention(query: torch.Tensor, training: bool) -> bool:
    """FlexAttention adds the distance bias inside its kernel, never writing [B, H, Q, Q];
    it is fast only compiled (the node's compiled / graphs step on CUDA). Eagerly, on the
    CPU, or in training the SDPA path with a materialised bias runs. Both compute the bias
    and the softmax in float32 (at least), so bf16 gives one answer in every mode."""
    return query.is_cuda and not training and torch.compiler.is_compiling()


def flex_das_attention(q, k, v, centroids, tau, num_dynamic: int | None):
    """softmax(q k^T / sqrt(d) - tau_h(i) * |c_i - c_j|) v with the bias computed per score.
    q, k, v [B, H, Q, d]; centroids [B, Q, 3]; tau [B, H, Q]; num_dynamic: queries below
    it attend only among themselves, the others likewise (None: all attend to all)."""
    dtype = torch.promote_types(q.dtype, torch.float32)    # the bias in at least float32
    centroids, tau = centroids.to(dtype), tau.to(dtype)

    def distance_bias(score, b, h, i, j):
        dx = centroids[b, i, 0] - centroids[b, j, 0]
        dy = centroids[b, i, 1] - centroids[b, j, 1]
        dz = centroids[b, i, 2] - centroids[b, j, 2]
        score = score - tau[b, h, i] * torch.sqrt(dx * dx + dy * dy + dz * dz)
        if num_dynamic is None:
            return score
        return torch.where((i < num_dynamic) != (j < num_dynamic), -float("inf"), score)

    return flex_attention(q, k, v, score_mod=distance_bias)


def sdpa_das_attention(q, k, v, centroids, tau, num_dynamic: int | None,
                       dropout: float = 0.0):
    """flex_das_attention's attention by scaled_dot_product_attention on a materialised
    [B, H, Q, Q] bias. The bias and the attention in float32 (at least), as FlexAttention's
    kernel scores: in bf16 the distance would step by 0.25 m at 40 m. Half-precision q, k, v
    are widened exactly. Returns q's dtype."""
    dtype = torch.promote_types(q.dtype, torch.float32)
    # norms of coordinate differences, as the flex kernel computes them (cdist's
    # |a|^2 + |b|^2 - 2ab loses millimetres to cancellation at 40 m; its direct mode has
    # no ONNX export)
    centroids = centroids.to(dtype)
    dist = torch.linalg.vector_norm(centroids[:, :, None] - centroids[:, None], dim=-1)
    bias = dist.unsqueeze(1) * -tau.to(dtype).unsqueeze(-1)            # [B, H, Q, Q]
    if num_dynamic is not None:
        is_dyn = torch.arange(q.shape[2], device=q.device) < num_dynamic
        cross = is_dyn[:, None] != is_dyn[None, :]
        bias = bias.masked_fill(cross, float("-inf"))
    if q.dtype == dtype:
        return F.scaled_dot_product_attention(q, k, v, attn_mask=bias, dropout_p=dropout)
    with torch.autocast(q.device.type, enabled=False):   # it would go back to half precision
        return F.scaled_dot_product_attention(q.to(dtype), k.to(dtype), v.to(dtype),
                                              attn_mask=bias, dropout_p=dropout).to(q.dtype)


class DaSAttention(nn.Module):
    def __init__(self, embed_dims: int, num_heads: int, dropout: float = 0.1,
                 mix_sets: bool = True):
        super().__init__()
        self.num_heads = num_heads
        self.mix_sets = mix_sets
        self.qkv = nn.Linear(embed_dims, 3 * embed_dims)
        self.proj = nn.Linear(embed_dims, embed_dims)
        self.dropout = dropout
        self.gen_tau = nn.Linear(embed_dims, num_heads)
        nn.init.zeros_(self.gen_tau.weight)
        nn.init.uniform_(self.gen_tau.bias, 0.0, 2.0)

    def forward(self, query: torch.Tensor, centroids: torch.Tensor, num_dynamic: int):
        """query [B, Q, E] (dynamic first), centroids [B, Q, 3] metres -> [B, Q, E]."""
        B, Q, E = query.shape
        H = self.num_heads
        q, k, v = self.qkv(query).view(B, Q, 3, H, E // H).permute(2, 0, 3, 1, 4)
        split = not self.mix_sets and 0 < num_dynamic < Q
        tau = self.gen_tau(query).permute(0, 2, 1)                      # [B, H, Q]
        if use_flex_attention(query, self.training):
            out = flex_das_attention(q, k, v, centroids, tau, num_dynamic if split else None)
        else:
            out = sdpa_das_attention(q, k, v, centroids, tau, num_dynamic if split else None,
                                     self.dropout if self.training else 0.0)
        return self.proj(out.transpose(1, 2).reshape(B, Q, E))
