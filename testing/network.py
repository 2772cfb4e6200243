"""A ResNet state dict in torchvision's layout, for the backbone-weight tests."""
from __future__ import annotations


def torchvision_layout(name):
    """The state_dict key -> shape of torchvision's ResNet, enumerated from its structure."""
    bottleneck = name == "resnet50"
    depths = {"resnet18": (2, 2, 2, 2), "resnet34": (3, 4, 6, 3), "resnet50": (3, 4, 6, 3)}[name]
    keys = {}

    def bn(prefix, ch):
        for k in ("weight", "bias", "running_mean", "running_var"):
            keys[f"{prefix}.{k}"] = (ch,)
        keys[f"{prefix}.num_batches_tracked"] = ()

    keys["conv1.weight"] = (64, 3, 7, 7)
    bn("bn1", 64)
    in_ch = 64
    for i, (width, depth) in enumerate(zip((64, 128, 256, 512), depths)):
        out_ch = width * (4 if bottleneck else 1)
        for j in range(depth):
            p = f"layer{i + 1}.{j}"
            if bottleneck:
                keys[f"{p}.conv1.weight"] = (width, in_ch, 1, 1)
                keys[f"{p}.conv2.weight"] = (width, width, 3, 3)
                keys[f"{p}.conv3.weight"] = (out_ch, width, 1, 1)
                bn(f"{p}.bn1", width), bn(f"{p}.bn2", width), bn(f"{p}.bn3", out_ch)
            else:
                keys[f"{p}.conv1.weight"] = (width, in_ch, 3, 3)
                keys[f"{p}.conv2.weight"] = (width, width, 3, 3)
                bn(f"{p}.bn1", width), bn(f"{p}.bn2", width)
            if j == 0 and in_ch != out_ch:
                keys[f"{p}.downsample.0.weight"] = (out_ch, in_ch, 1, 1)
                bn(f"{p}.downsample.1", out_ch)
            in_ch = out_ch
    keys["fc.weight"] = (1000, in_ch)
    keys["fc.bias"] = (1000,)
    return keys
