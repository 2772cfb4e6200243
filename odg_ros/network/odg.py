"""ODG: image encoder (ResNet + FPN) per frame, and the dual-Gaussian-query decoder.

Feature extraction is separate from decoding so the online path runs the backbone on the
newest frame only and reuses the cached features of the k-1 previous frames
(``extract_features`` once per frame, ``decode`` over the cached list, or ``decode_ring``
over a ``FeatureRing`` that keeps the cached frames in the sampling layout).
"""
from __future__ import annotations

import torch
from torch import nn

from ..model_config import ModelConfig
from .backbone import ResNet
from .decoder import Decoder
from .fpn import FPN
from .outputs import ODGOutput
from .feature_ring import FeatureRing
from .queries import DualGaussianQueries
from .sampling import camera_rows_layout


class ODG(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.num_dynamic = cfg.dynamic_queries
        self.backbone = ResNet(cfg.backbone, cfg.frozen_stages, cfg.norm_eval)
        self.neck = FPN(self.backbone.out_channels, cfg.fpn_channels)
        self.queries = DualGaussianQueries(cfg.dynamic_queries, cfg.static_queries,
                                           cfg.embed_dims, cfg.pc_range)
        self.decoder = Decoder(cfg, cfg.dynamic_queries)
        # True: sample the camera-rows layout (2-D grid_sample); False: the plain per-camera
        # 3-D layout, kept as the reference the fast path is tested and benchmarked against
        self.fast_sampling = True
        self._index_cache: dict[tuple, torch.Tensor] = {}   # see _index_tensor

    def extract_features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images [B, N, 3, H, W] (normalised) -> L levels [B, N, C, H_l, W_l].

        The levels are views of the FPN output (channels-last memory, no copy); ``decode``
        lays the frames out for sampling (``sampling.camera_rows_layout``), and a
        ``FeatureRing`` does it once per frame for ``decode_ring``.
        """
        B, N = images.shape[:2]
        x = images.flatten(0, 1).contiguous(memory_format=torch.channels_last)
        return [f.unflatten(0, (B, N)) for f in self.neck(self.backbone(x))]

    def decode(self, frame_feats: list[list[torch.Tensor]], ego2img: torch.Tensor,
               ego_warp: torch.Tensor, time_delta: torch.Tensor,
               gaussian_attributes: bool | None = None, budget=None) -> ODGOutput:
        """frame_feats: T frames (0 = current, then older) of L levels [B, N, C, H_l, W_l];
        ego2img [B, T, N, 4, 4]; ego_warp [B, T, 4, 4]; time_delta [B, T].
        gaussian_attributes: run Phi_s/r/sigma (default: while training; the grid does not
        need them). budget: a ``budget.QueryBudget`` (None: every query, no keep-scores).

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
        if self.fast_sampling:
            # the T given frames are laid out once; the missing ones read the oldest
            G, L = self.cfg.num_groups, len(frame_feats[0])
            mlvl = [camera_rows_layout([feats[level] for feats in frame_feats], G)
                    for level in range(L)]
            return self.decode_stored(mlvl, ego2img, ego_warp, time_delta,
                                      self._frame_index(list(range(T)), ego2img.device),
                                      gaussian_attributes, budget)
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
                per_frame.append(f.reshape(B, N, G, C // G, h, w).permute(0, 2, 3, 1, 4, 5))
            stacked = torch.stack(per_frame)                            # [T, B, G, c, N, h, w]
            mlvl.append(stacked.reshape(-1, *stacked.shape[3:]))
        return self.decode_stored(mlvl, ego2img, ego_warp, time_delta, None,
                                  gaussian_attributes, budget)

    def decode_ring(self, ring: FeatureRing, ego2img: torch.Tensor, ego_warp: torch.Tensor,
                    time_delta: torch.Tensor, gaussian_attributes: bool | None = None,
                    budget=None) -> ODGOutput:
        """``decode`` over the frames cached in ``ring`` (newest first, T = len(ring)), with
        the geometry of those T frames as for ``decode``: no per-step re-layout of history."""
        T = len(ring)
        if T == 0:
            raise ValueError("decode_ring: the feature ring is empty")
        if not (ego2img.shape[1] == ego_warp.shape[1] == time_delta.shape[1] == T):
            raise ValueError(f"{T} cached frames but geometry for {ego2img.shape[1]}, "
                             f"{ego_warp.shape[1]}, {time_delta.shape[1]} frames")
        if T > self.cfg.num_frames:
            raise ValueError(f"{T} frames cached, the model takes at most {self.cfg.num_frames}")
        slots = ring.slots()                       # slots[t]: storage slot of time step t
        order = sorted(range(T), key=lambda t: slots[t])   # time step of each stored slot
        index = self._index_tensor(order, ego2img.device)
        return self.decode_stored(ring.levels(), ego2img.index_select(1, index),
                                  ego_warp.index_select(1, index),
                                  time_delta.index_select(1, index),
                                  self._frame_index(slots, ego2img.device),
                                  gaussian_attributes, budget)

    def _frame_index(self, slots: list[int], device) -> torch.Tensor | None:
        """Stored frame read by each of the model's ``num_frames`` time steps: ``slots`` for
        the given ones, the oldest again for the rest; None when that is the identity."""
        index = slots + [slots[-1]] * (self.cfg.num_frames - len(slots))
        if index == list(range(self.cfg.num_frames)):
            return None
        return self._index_tensor(index, device)

    def _index_tensor(self, index: list[int], device) -> torch.Tensor:
        """A cached device copy of a small index list: no host-to-device copy (a host sync
        on CUDA) inside a step once the ring has cycled through its slot orders."""
        key = (tuple(index), str(device))
        if key not in self._index_cache:
            self._index_cache[key] = torch.tensor(index, device=device)
        return self._index_cache[key]

    def decode_stored(self, mlvl, ego2img, ego_warp, time_delta, frame_index,
                      gaussian_attributes=None, budget=None) -> ODGOutput:
        """``decode`` over frames already stored in a sampling layout (what ``decode`` and
        ``decode_ring`` lay out, or an online step's ``ring.all_levels()``): mlvl, L levels of
        F stored frames; geometry [B, F, ...] in the same storage order; frame_index
        [num_frames] (see ``SpatioTemporalSampling``; None: time step t reads frame t)."""
        B = ego2img.shape[0]
        geometry = {"ego2img": ego2img.float(), "ego_warp": ego_warp.float(),
                    "time_delta": time_delta.float(), "image_hw": self.cfg.image_size,
                    "frame_index": frame_index}
        query, means, boxes = self.queries(B)
        if gaussian_attributes is None:
            gaussian_attributes = self.training
        layers, keep_scores = self.decoder(query, means, boxes, mlvl, geometry,
                                           gaussian_attributes, budget)
        return ODGOutput(init_means=means, layers=layers, num_dynamic=self.num_dynamic,
                         keep_scores=keep_scores)

    def forward(self, images: torch.Tensor, ego2img: torch.Tensor, ego_warp: torch.Tensor,
                time_delta: torch.Tensor, history_grad: bool = True,
                **decode_options) -> ODGOutput:
        """images [B, T, N, 3, H, W]: the backbone runs over all frames (training / offline).

        history_grad=False runs the backbone on frames t > 0 without autograd (SparseBEV's
        ``stop_prev_grad``): the same outputs, a backbone backward over one frame instead of T.
        """
        B, T = images.shape[:2]
        if history_grad or T == 1:
            feats = self.extract_features(images.flatten(0, 1))        # batch = B*T
            frame_feats = [[f.unflatten(0, (B, T))[:, t] for f in feats] for t in range(T)]
        else:
            current = self.extract_features(images[:, 0])
            with torch.no_grad():
                past = self.extract_features(images[:, 1:].flatten(0, 1))
            frame_feats = [current] + [[f.unflatten(0, (B, T - 1))[:, t] for f in past]
                                       for t in range(T - 1)]
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
        heads += list(self.decoder.budget_heads.parameters())
        head_ids = {id(p) for p in heads}
        decoder = [p for p in list(self.decoder.parameters()) + list(self.queries.parameters())
                   if id(p) not in head_ids]
        return {"backbone": count(self.backbone.parameters()),
                "neck": count(self.neck.parameters()),
                "decoder": count(decoder), "heads": count(heads)}
