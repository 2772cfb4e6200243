"""ODG: image encoder (ResNet + FPN) per frame, and the dual-Gaussian-query decoder.

Feature extraction is separate from decoding so the online path runs the backbone on the
newest frame only and reuses the cached features of the k-1 previous frames
(``extract_features`` once per frame, ``decode`` over the cached list).
"""
from __future__ import annotations

import torch
from torch import nn

from ..config import ModelConfig
from .backbone import ResNet
from .decoder import Decoder
from .fpn import FPN
from .outputs import ODGOutput
from .queries import DualGaussianQueries


class ODG(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        num_dynamic = cfg.num_dynamic if cfg.dual_queries else 0
        num_static = cfg.num_static + (0 if cfg.dual_queries else cfg.num_dynamic)
        self.num_dynamic = num_dynamic
        self.backbone = ResNet(cfg.backbone, cfg.frozen_stages)
        self.neck = FPN(self.backbone.out_channels, cfg.fpn_channels)
        self.queries = DualGaussianQueries(num_dynamic, num_static, cfg.embed_dims, cfg.pc_range)
        self.decoder = Decoder(cfg, num_dynamic)

    def extract_features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images [B, N, 3, H, W] (normalised) -> L levels [B, N, C, H_l, W_l].

        The levels are stored in the sampling layout [B, G, C/G, N, H_l, W_l] and returned as
        views, so decoding needs no re-layout of cached frames.
        """
        B, N = images.shape[:2]
        x = images.flatten(0, 1).contiguous(memory_format=torch.channels_last)
        levels = self.neck(self.backbone(x))
        G = self.cfg.num_groups
        out = []
        for f in levels:
            _, C, h, w = f.shape
            f = f.reshape(B, N, G, C // G, h, w).permute(0, 2, 3, 1, 4, 5).contiguous()
            out.append(f.permute(0, 3, 1, 2, 4, 5).reshape(B, N, C, h, w))
        return out

    def decode(self, frame_feats: list[list[torch.Tensor]], ego2img: torch.Tensor,
               ego_warp: torch.Tensor, time_delta: torch.Tensor,
               gaussian_attributes: bool | None = None, prune=None) -> ODGOutput:
        """frame_feats: T frames (0 = current, then older) of L levels [B, N, C, H_l, W_l];
        ego2img [B, T, N, 4, 4]; ego_warp [B, T, 4, 4]; time_delta [B, T].
        gaussian_attributes: run Phi_s/r/sigma (default: while training; the grid does not
        need them). prune: a ``decoder.PruneRule`` for adaptive inference (None: full model).

        With fewer frames than ``cfg.num_frames`` (a history still filling up) the oldest
        frame is repeated, as the dataset does at the start of a scene.
        """
        T = len(frame_feats)
        if not (ego2img.shape[1] == ego_warp.shape[1] == time_delta.shape[1] == T):
            raise ValueError(f"{T} feature frames but geometry for {ego2img.shape[1]}, "
                             f"{ego_warp.shape[1]}, {time_delta.shape[1]} frames")
        missing = self.cfg.num_frames - T
        if missing < 0:
            raise ValueError(f"{T} frames given, the model takes at most {self.cfg.num_frames}")
        if missing:
            frame_feats = list(frame_feats) + [frame_feats[-1]] * missing
            ego2img = torch.cat([ego2img, ego2img[:, -1:].expand(-1, missing, -1, -1, -1)], 1)
            ego_warp = torch.cat([ego_warp, ego_warp[:, -1:].expand(-1, missing, -1, -1)], 1)
            time_delta = torch.cat([time_delta, time_delta[:, -1:].expand(-1, missing)], 1)
        B = ego2img.shape[0]
        G = self.cfg.num_groups
        mlvl = []
        for level in range(len(frame_feats[0])):
            per_frame = []
            for feats in frame_feats:
                f = feats[level]
                _, N, C, h, w = f.shape
                per_frame.append(f.view(B, N, G, C // G, h, w).permute(0, 2, 3, 1, 4, 5))
            stacked = torch.stack(per_frame)                            # [T, B, G, c, N, h, w]
            mlvl.append(stacked.reshape(-1, *stacked.shape[3:]))
        geometry = {"ego2img": ego2img.float(), "ego_warp": ego_warp.float(),
                    "time_delta": time_delta.float(), "image_hw": self.cfg.image_size}
        query, means, boxes = self.queries(B)
        if gaussian_attributes is None:
            gaussian_attributes = self.training
        layers = self.decoder(query, means, boxes, mlvl, geometry, gaussian_attributes, prune)
        return ODGOutput(init_means=means, layers=layers, num_dynamic=self.num_dynamic)

    def forward(self, images: torch.Tensor, ego2img: torch.Tensor, ego_warp: torch.Tensor,
                time_delta: torch.Tensor, **decode_options) -> ODGOutput:
        """images [B, T, N, 3, H, W]: the backbone runs over all frames (training / offline)."""
        B, T = images.shape[:2]
        feats = self.extract_features(images.flatten(0, 1))            # batch = B*T
        frame_feats = [[f.unflatten(0, (B, T))[:, t] for f in feats] for t in range(T)]
        return self.decode(frame_feats, ego2img, ego_warp, time_delta, **decode_options)

    def parameter_groups(self) -> dict[str, int]:
        """Parameter counts per part (backbone, neck, decoder, heads)."""
        def count(params):
            return sum(p.numel() for p in params)
        heads = []
        for layer in self.decoder.layers:
            heads += list(layer.points.parameters())
            if layer.boxes is not None:
                heads += list(layer.boxes.parameters())
        heads += list(self.decoder.attributes.parameters())
        head_ids = {id(p) for p in heads}
        decoder = [p for p in list(self.decoder.parameters()) + list(self.queries.parameters())
                   if id(p) not in head_ids]
        return {"backbone": count(self.backbone.parameters()),
                "neck": count(self.neck.parameters()),
                "decoder": count(decoder), "heads": count(heads)}
