"""Pretrained ResNet weights for the image encoder, from a local checkpoint file.

Layouts read (all share torchvision's ResNet key names below a prefix):
- torchvision / timm: ``conv1.weight``, ``layer1.0.bn1.running_mean``, ... (``fc.*`` ignored);
- mmdetection: a detector's ``backbone.*`` keys, e.g. the nuImages-pretrained Cascade Mask
  R-CNN ResNet-50 that OPUS and SparseBEV start from (its neck and heads are ignored);
- mmdetection3d: ``img_backbone.*`` (a camera detector such as OPUS or SparseBEV itself);
each possibly under a ``state_dict`` / ``model`` / ``state_dict_ema`` wrapper and with DDP's
``module.`` prefix. A checkpoint lacking a backbone key or with another shape (another depth)
is refused; missing ``num_batches_tracked`` counters (not stored by every release) are not.

``backbone_start`` decides how a training run's backbone starts: a config that freezes stages
or keeps BatchNorm statistics fixed only makes sense from pretrained weights, so without any
it refuses, unless the user asks to train the whole backbone from scratch.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

log = logging.getLogger(__name__)

WRAPPERS = ("state_dict", "model", "state_dict_ema")
PREFIXES = {"img_backbone.": "mmdetection3d", "backbone.": "mmdetection",
            "": "torchvision/timm"}
OPTIONAL_SUFFIX = "num_batches_tracked"


class BackboneWeightsError(ValueError):
    """A backbone checkpoint that cannot start this model, or none where one is needed."""


@dataclass
class BackboneLoadReport:
    layout: str
    loaded: int
    missing: list[str] = field(default_factory=list)      # optional keys the file lacked
    unexpected: list[str] = field(default_factory=list)   # backbone-prefixed keys not ours
    other: int = 0                                         # keys outside the backbone

    def summary(self) -> str:
        parts = [f"{self.loaded} backbone tensors loaded ({self.layout} layout)"]
        if self.missing:
            parts.append(f"{len(self.missing)} missing, kept at initialisation: "
                         f"{_examples(self.missing)}")
        if self.unexpected:
            parts.append(f"{len(self.unexpected)} unexpected, ignored: "
                         f"{_examples(self.unexpected)}")
        if self.other:
            parts.append(f"{self.other} keys of other modules ignored")
        return "; ".join(parts)


def _examples(keys: list[str], count: int = 3) -> str:
    return ", ".join(keys[:count]) + (", ..." if len(keys) > count else "")


def read_state_dict(source) -> dict:
    """A state dict from a path (``torch.load``) or a dict; unwraps the usual wrappers."""
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise BackboneWeightsError(f"backbone weights {path}: no such file")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:   # pickle / zip errors: one line, the file's name
            raise BackboneWeightsError(f"backbone weights {path}: not a PyTorch checkpoint "
                                       f"({type(error).__name__}: {error})") from None
    else:
        state = source
    while isinstance(state, dict):
        wrapper = next((k for k in WRAPPERS if isinstance(state.get(k), dict)), None)
        if wrapper is None:
            break
        state = state[wrapper]
    if not isinstance(state, dict) or not state:
        raise BackboneWeightsError("backbone weights: the checkpoint holds no state dict")
    if all(k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    return state


def backbone_keys(state: dict) -> tuple[str, str]:
    """-> (prefix, layout name) of the backbone keys in ``state``."""
    for prefix, layout in PREFIXES.items():
        if f"{prefix}conv1.weight" in state and any(
                k.startswith(f"{prefix}layer1.") for k in state):
            return prefix, layout
    sample = _examples(sorted(state))
    raise BackboneWeightsError(
        "backbone weights: no ResNet found (expected conv1.weight and layer1.* at the top, "
        f"under backbone. or under img_backbone.); the file's keys start {sample}")


def load_backbone_weights(backbone: nn.Module, source) -> BackboneLoadReport:
    """Load ResNet weights in any layout of the module docstring into ``backbone``.

    Raises ``BackboneWeightsError`` (one line) on a missing or mis-shaped key."""
    state = read_state_dict(source)
    own = backbone.state_dict()
    prefix, layout = backbone_keys(state)
    ours = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    if prefix == "":   # the whole file is the backbone (fc, or a timm head, are extra)
        other = 0
    else:
        other = len(state) - len(ours)
    missing = [k for k in own if k not in ours]
    required = [k for k in missing if not k.endswith(OPTIONAL_SUFFIX)]
    if required:
        raise BackboneWeightsError(
            f"backbone weights ({layout} layout) lack {len(required)} of the model's keys, "
            f"e.g. {_examples(required)}: another architecture than {type(backbone).__name__}?")
    for k in own:
        if k in ours and ours[k].shape != own[k].shape:
            raise BackboneWeightsError(
                f"backbone weights: {prefix}{k} has shape {tuple(ours[k].shape)}, the model's "
                f"is {tuple(own[k].shape)} (a checkpoint of another ResNet depth?)")
    unexpected = sorted(k for k in ours if k not in own)
    extra_blocks = [k for k in unexpected if k.startswith("layer")]
    if extra_blocks:
        raise BackboneWeightsError(
            f"backbone weights ({layout} layout) hold {len(extra_blocks)} keys of blocks the "
            f"model lacks, e.g. {_examples(extra_blocks)}: a deeper ResNet's checkpoint?")
    backbone.load_state_dict({k: ours[k] for k in own if k in ours}, strict=False)
    return BackboneLoadReport(layout, sum(k in ours for k in own), missing,
                              [prefix + k for k in unexpected], other)


FROM_SCRATCH_FLAG = "--backbone-from-scratch"


def backbone_start(cfg, backbone_weights=None, weights_elsewhere: bool = False,
                   from_scratch: bool = False):
    """-> the config to train (``cfg``, or with the backbone unfrozen when ``from_scratch``).

    A config with frozen stages or fixed BatchNorm statistics (``frozen_stages >= 0`` or
    ``norm_eval``) keeps those at their random initialisation unless pretrained weights come
    from ``backbone_weights`` or elsewhere (``weights_elsewhere``: an initial checkpoint, a
    resume); without any it refuses, or with ``from_scratch`` trains every stage and the BN
    statistics, saying so."""
    frozen = cfg.frozen_stages >= 0 or cfg.norm_eval
    if backbone_weights or weights_elsewhere or not frozen:
        if from_scratch and frozen:
            log.warning("%s ignored: the backbone starts from given weights", FROM_SCRATCH_FLAG)
        return cfg
    if from_scratch:
        log.warning("training the %s backbone of %s FROM SCRATCH: every stage and its "
                    "BatchNorm statistics train (frozen_stages=-1, norm_eval=false), not "
                    "the preset's frozen stem + layer1 with fixed statistics; expect a far "
                    "longer training than from pretrained weights", cfg.backbone, cfg.name)
        return cfg.replace(frozen_stages=-1, norm_eval=False)
    raise BackboneWeightsError(
        f"{cfg.name} freezes the backbone's first stages (frozen_stages={cfg.frozen_stages}) "
        f"and keeps its BatchNorm statistics fixed (norm_eval={cfg.norm_eval}), which is only "
        f"right from pretrained weights; pass --backbone-weights FILE (a {cfg.backbone} "
        f"checkpoint in torchvision, timm or mmdetection layout, e.g. nuImages Cascade Mask "
        f"R-CNN), or {FROM_SCRATCH_FLAG} to unfreeze and train it all")
