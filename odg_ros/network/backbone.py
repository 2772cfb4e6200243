"""ResNet-18/34/50 image encoder with torchvision-compatible state_dict keys.

A standard ImageNet checkpoint saved from torchvision (``conv1.weight``, ``layer1.0.bn1.*``,
``layer2.0.downsample.0.weight``, ...), timm or mmdetection loads with
``backbone_weights.load_backbone_weights``. As in OPUS/SparseBEV the stem and ``layer1`` are frozen
(``frozen_stages=1``) and every BatchNorm stays in eval mode, even while training; a backbone
trained from scratch (the CPU preset) uses ``frozen_stages=-1, norm_eval=False`` instead.
"""
from __future__ import annotations

import copy

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

ARCHITECTURES = {
    "resnet18": ("basic", (2, 2, 2, 2)),
    "resnet34": ("basic", (3, 4, 6, 3)),
    "resnet50": ("bottleneck", (3, 4, 6, 3)),
}


class _Residual(nn.Module):
    """A residual block: relu(branch(x) + shortcut(x)); the shortcut is a strided 1x1
    convolution where the branch changes the size or the channels (torchvision's
    ``downsample``), else the identity."""

    def _add_shortcut(self, in_ch: int, out_ch: int, stride: int) -> None:
        self.relu = nn.ReLU(inplace=True)
        self.downsample = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(nn.Conv2d(in_ch, out_ch, 1, stride, bias=False),
                                            nn.BatchNorm2d(out_ch))

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        return self.relu(self.branch(x) + identity)


class BasicBlock(_Residual):
    expansion = 1

    def __init__(self, in_ch: int, width: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, width, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self._add_shortcut(in_ch, width * self.expansion, stride)

    def branch(self, x):
        return self.bn2(self.conv2(self.relu(self.bn1(self.conv1(x)))))


class Bottleneck(_Residual):
    expansion = 4

    def __init__(self, in_ch: int, width: int, stride: int = 1):
        super().__init__()
        out_ch = width * self.expansion
        self.conv1 = nn.Conv2d(in_ch, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)  # stride on 3x3 (v1.5)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out_ch, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out_ch)
        self._add_shortcut(in_ch, out_ch, stride)

    def branch(self, x):
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        return self.bn3(self.conv3(out))


class ResNet(nn.Module):
    """Returns C2..C5 (outputs of layer1..layer4, strides 4, 8, 16, 32)."""

    def __init__(self, name: str = "resnet50", frozen_stages: int = 1, norm_eval: bool = True):
        super().__init__()
        kind, depths = ARCHITECTURES[name]
        block = BasicBlock if kind == "basic" else Bottleneck
        self.frozen_stages = frozen_stages
        self.norm_eval = norm_eval
        # True: layer1..4 keep only their inputs for the backward pass and run again in it
        # (gradient checkpointing; training memory of large images and many frames)
        self.checkpoint_stages = False
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        in_ch = 64
        self.out_channels = []
        for i, (width, depth) in enumerate(zip((64, 128, 256, 512), depths)):
            blocks = []
            for j in range(depth):
                blocks.append(block(in_ch, width, stride=2 if (j == 0 and i > 0) else 1))
                in_ch = width * block.expansion
            setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
            self.out_channels.append(in_ch)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        self._freeze()

    def _freeze(self) -> None:
        frozen = [self.conv1, self.bn1] if self.frozen_stages >= 0 else []
        frozen += [getattr(self, f"layer{i}") for i in range(1, self.frozen_stages + 1)]
        for module in frozen:
            for p in module.parameters():
                p.requires_grad_(False)

    def train(self, mode: bool = True):
        super().train(mode)
        # A pretrained backbone keeps its BN statistics (batches of 6 views are too small to
        # re-estimate them); a backbone trained from scratch has no statistics worth keeping.
        if self.norm_eval:
            for m in self.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        feats = []
        for i in range(1, 5):
            layer = getattr(self, f"layer{i}")
            if self.checkpoint_stages and torch.is_grad_enabled() and \
                    any(p.requires_grad for p in layer.parameters()):
                x = checkpoint(layer, x, use_reentrant=False)
            else:
                x = layer(x)
            feats.append(x)
        return feats


def folded_for_inference(backbone: ResNet) -> ResNet:
    """An inference copy of ``backbone``: every BatchNorm (with its running statistics)
    folded into the convolution before it, which gains a bias, and the weights in
    channels-last memory, the layout the features run in (cuDNN / oneDNN then need no
    weight re-layout per call). The original is left as it is (training keeps its BN)."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval
    folded = copy.deepcopy(backbone).eval()
    for module in list(folded.modules()):
        for i in (1, 2, 3):
            conv, bn = getattr(module, f"conv{i}", None), getattr(module, f"bn{i}", None)
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                setattr(module, f"conv{i}", fuse_conv_bn_eval(conv, bn))
                setattr(module, f"bn{i}", nn.Identity())
        if isinstance(module, nn.Sequential) and len(module) == 2 and \
                isinstance(module[0], nn.Conv2d) and isinstance(module[1], nn.BatchNorm2d):
            module[0] = fuse_conv_bn_eval(module[0], module[1])
            module[1] = nn.Identity()
    remaining = [m for m in folded.modules() if isinstance(m, nn.BatchNorm2d)]
    if remaining:
        raise RuntimeError(f"{len(remaining)} BatchNorm layers follow no convolution")
    return folded.to(memory_format=torch.channels_last)
