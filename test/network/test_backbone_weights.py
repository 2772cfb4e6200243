"""Pretrained backbone weights: torchvision, timm, mmdetection and mmdetection3d layouts from
a file, missing / unexpected keys reported, wrong checkpoints refused in one line; a preset
with a frozen backbone refuses to train without weights (or unfreezes when asked)."""
import logging

import pytest
import torch

from odg_ros.commands import train as train_command
from odg_ros.network.backbone import ResNet
from odg_ros.network.backbone_weights import (BackboneWeightsError, backbone_start,
                                              load_backbone_weights)
from odg_ros.train.trainer import Trainer, TrainOptions

from testing.helpers import tiny_config, write_tiny_split
from testing.network import torchvision_layout


def generated(name, seed=1, counters=True):
    """A torchvision-layout ResNet state dict (fc included) of random values on the scale of
    trained ones (He-scaled convolutions, positive BN variances): a network that runs."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for k, shape in torchvision_layout(name).items():
        if k.endswith("num_batches_tracked"):
            if counters:
                state[k] = torch.tensor(7)
            continue
        value = torch.randn(shape, generator=g)
        if k.endswith("running_var"):
            value = 1.0 + value.abs()
        elif len(shape) > 1:   # convolution / fc weight
            value = value * (2.0 / torch.tensor(shape[1:]).prod()) ** 0.5
        elif k.endswith(".weight"):   # BN scale
            value = 1.0 + 0.1 * value
        else:
            value = 0.1 * value
        state[k] = value
    return state


def in_layout(state, layout):
    """``state`` (torchvision keys) saved as each library writes its checkpoints."""
    if layout == "torchvision":
        return state
    if layout == "timm":   # same names; timm's released files drop the BN counters
        return {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    if layout == "ddp":
        return {"model": {f"module.{k}": v for k, v in state.items() if not k.startswith("fc.")}}
    neck = {"neck.fpn_convs.0.conv.weight": torch.zeros(256, 256, 3, 3),
            "roi_head.bbox_head.0.fc_cls.weight": torch.zeros(11, 1024)}
    if layout == "mmdetection":   # nuImages Cascade Mask R-CNN: backbone.* + neck + heads
        body = {f"backbone.{k}": v for k, v in state.items() if not k.startswith("fc.")}
        return {"meta": {"mmdet_version": "2.x"}, "state_dict": {**body, **neck}}
    if layout == "mmdetection3d":   # a camera detector: img_backbone.* + img_neck + head
        body = {f"img_backbone.{k}": v for k, v in state.items() if not k.startswith("fc.")}
        return {"state_dict": {**body, "img_neck.lateral_convs.0.conv.weight":
                               torch.zeros(256, 512, 1, 1)}}
    raise ValueError(layout)


LAYOUT_NAMES = {"torchvision": "torchvision/timm", "timm": "torchvision/timm",
                "ddp": "torchvision/timm", "mmdetection": "mmdetection",
                "mmdetection3d": "mmdetection3d"}


@pytest.mark.parametrize("layout", sorted(LAYOUT_NAMES))
def test_resnet50_loads_from_a_file_in_each_layout(tmp_path, layout):
    state = generated("resnet50")
    path = tmp_path / "weights.pth"
    torch.save(in_layout(state, layout), path)
    model = ResNet("resnet50")
    report = load_backbone_weights(model, path)
    assert report.layout == LAYOUT_NAMES[layout]
    own = model.state_dict()
    for k, v in own.items():
        if layout == "timm" and k.endswith("num_batches_tracked"):
            continue
        assert torch.equal(v, state[k]), k
    counters = [k for k in own if k.endswith("num_batches_tracked")]
    assert report.missing == (counters if layout == "timm" else [])
    assert report.loaded == len(own) - len(report.missing)
    if layout in ("torchvision", "timm"):
        assert report.unexpected == ["fc.bias", "fc.weight"]
    else:
        assert report.unexpected == []
    assert report.other == {"mmdetection": 2, "mmdetection3d": 1}.get(layout, 0)
    assert "loaded" in report.summary()


def test_wrong_or_unusable_checkpoints_are_refused_in_one_line(tmp_path):
    wide = generated("resnet18")
    wide["layer2.0.conv1.weight"] = torch.zeros(256, 64, 3, 3)
    with pytest.raises(BackboneWeightsError, match="layer2.0.conv1.weight has shape"):
        load_backbone_weights(ResNet("resnet18"), wide)
    with pytest.raises(BackboneWeightsError, match="lack .* keys"):
        load_backbone_weights(ResNet("resnet50"), generated("resnet18"))   # no conv3
    with pytest.raises(BackboneWeightsError, match="blocks the model lacks"):
        load_backbone_weights(ResNet("resnet18"), generated("resnet34"))   # deeper
    with pytest.raises(BackboneWeightsError, match="no ResNet found.*neck"):
        load_backbone_weights(ResNet("resnet18"), {"neck.conv.weight": torch.zeros(1)})
    with pytest.raises(BackboneWeightsError, match="no such file"):
        load_backbone_weights(ResNet("resnet18"), tmp_path / "absent.pth")
    (tmp_path / "text.pth").write_text("not a checkpoint")
    with pytest.raises(BackboneWeightsError, match="not a PyTorch checkpoint"):
        load_backbone_weights(ResNet("resnet18"), tmp_path / "text.pth")
    with pytest.raises(BackboneWeightsError) as error:
        load_backbone_weights(ResNet("resnet50"), generated("resnet18"))
    assert "\n" not in str(error.value)


def test_frozen_backbone_needs_weights_or_an_explicit_from_scratch(caplog):
    frozen = tiny_config(frozen_stages=1, norm_eval=True)
    with pytest.raises(BackboneWeightsError, match="--backbone-weights.*--backbone-from-scratch"):
        backbone_start(frozen)
    with pytest.raises(BackboneWeightsError, match="norm_eval=True"):
        backbone_start(tiny_config(frozen_stages=-1, norm_eval=True))
    assert backbone_start(frozen, "w.pth") is frozen
    assert backbone_start(frozen, weights_elsewhere=True) is frozen
    scratch = tiny_config()   # the CPU preset trains every stage: nothing to refuse
    assert backbone_start(scratch) is scratch
    with caplog.at_level(logging.WARNING):
        unfrozen = backbone_start(frozen, from_scratch=True)
    assert (unfrozen.frozen_stages, unfrozen.norm_eval) == (-1, False)
    assert "FROM SCRATCH" in caplog.text


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("split"), 2)


def odg_t_tiny():
    """ODG-T's backbone (ResNet-50, stem + layer1 frozen, BN statistics fixed) and decoder
    widths on tiny images, two frames, few queries: two steps in a few seconds."""
    return ["--preset", "odg_t", "--set", "image_size=[32, 88]", "--set", "num_frames=2",
            "--set", "num_static=8", "--set", "num_dynamic=4",
            "--set", "points_per_layer=[1, 2, 2, 2, 2, 2]"]


def train_args(split, out, *extra):
    return odg_t_tiny() + ["--data", str(split), "--out", str(out), "--steps", "2",
                           "--epochs", "1", "--workers", "0", "--warmup", "1", "--no-render",
                           *extra]


def parse(args):
    import argparse
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    return parser.parse_args(args)


def test_odg_t_training_refuses_without_backbone_weights(split, tmp_path, capsys):
    from odg_ros.commands import main as cli_main
    assert cli_main(["train", *train_args(split, tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--backbone-weights" in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("layout", ["torchvision", "mmdetection", "mmdetection3d"])
def test_odg_t_trains_two_steps_from_generated_weights(split, tmp_path, layout, caplog,
                                                        monkeypatch):
    state = generated("resnet50", seed=3)
    path = tmp_path / f"{layout}.pth"
    torch.save(in_layout(state, layout), path)
    monkeypatch.setattr(Trainer, "save", lambda *args, **kwargs: None)  # no 100 MB writes
    args = parse(train_args(split, tmp_path / "run", "--backbone-weights", str(path)))
    cfg = train_command.load_preset(args.preset, **train_command.parse_overrides(args.set))
    options = TrainOptions(out_dir=tmp_path / "run", max_steps=2, epochs=1, workers=0,
                           warmup_steps=1, render=False, progress=False, backbone_weights=path)
    with caplog.at_level(logging.INFO):
        trainer = Trainer(cfg, split, options)
        if layout == "mmdetection":   # the steps do not depend on the layout: run them once
            assert trainer.fit() and trainer.step == 2 and trainer.skipped_steps == 0
    assert f"({LAYOUT_NAMES[layout]} layout)" in caplog.text
    model = trainer.model
    assert (model.cfg.frozen_stages, model.cfg.norm_eval) == (1, True)
    # the frozen stem and its fixed BN statistics kept the given weights through two steps;
    # a trained stage moved away from them
    assert torch.equal(model.backbone.conv1.weight, state["conv1.weight"])
    assert torch.equal(model.backbone.bn1.running_mean, state["bn1.running_mean"])
    assert torch.equal(model.backbone.layer2[0].bn1.running_var, state["layer2.0.bn1.running_var"])
    unchanged = torch.equal(model.backbone.layer4[0].conv1.weight, state["layer4.0.conv1.weight"])
    assert unchanged == (layout != "mmdetection")
