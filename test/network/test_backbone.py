"""ResNet layout: torchvision-compatible state_dict keys, frozen stage 1, BN in eval (loading
pretrained weights: test_backbone_weights.py); the folded inference copy."""
import copy

import torch

from odg_ros.network.backbone import ResNet

# Parameter counts of torchvision's resnet18/34/50 minus their 1000-way fc layer.
TORCHVISION_PARAMS_WITHOUT_FC = {"resnet18": 11_689_512 - 513_000,
                                 "resnet34": 21_797_672 - 513_000,
                                 "resnet50": 25_557_032 - 2_049_000}


def test_parameter_counts_match_torchvision():
    for name, expected in TORCHVISION_PARAMS_WITHOUT_FC.items():
        assert sum(p.numel() for p in ResNet(name).parameters()) == expected, name


def test_stage_one_frozen_and_batchnorm_in_eval():
    model = ResNet("resnet18", frozen_stages=1).train()
    assert not any(p.requires_grad for p in model.conv1.parameters())
    assert not any(p.requires_grad for p in model.layer1.parameters())
    assert all(p.requires_grad for p in model.layer2.parameters())
    assert all(not m.training for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d))
    before = model.bn1.running_mean.clone()
    model(torch.randn(2, 3, 64, 64) * 5 + 3)
    assert torch.equal(before, model.bn1.running_mean)


def test_from_scratch_backbone_trains_every_stage_and_its_batchnorm():
    model = ResNet("resnet18", frozen_stages=-1, norm_eval=False).train()
    assert all(p.requires_grad for p in model.parameters())
    before = model.bn1.running_mean.clone()
    model(torch.randn(2, 3, 64, 64) * 5 + 3)
    assert not torch.equal(before, model.bn1.running_mean)
    model.eval()  # inference uses the running statistics: same input, same output, any batch
    x = torch.randn(3, 3, 64, 64)
    torch.testing.assert_close(model(x)[3][:1], model(x[:1])[3], rtol=1e-5, atol=1e-5)


def test_feature_strides():
    feats = ResNet("resnet18")(torch.randn(1, 3, 64, 128))
    assert [tuple(f.shape[-2:]) for f in feats] == [(16, 32), (8, 16), (4, 8), (2, 4)]


def test_folded_backbone_equals_the_backbone_with_batchnorm():
    """Non-trivial BN statistics and affine terms; float64 for the exact comparison, float32
    (the runtime) within rounding; the original keeps its BatchNorm layers."""
    from odg_ros.network.backbone import folded_for_inference
    torch.manual_seed(0)
    for name in ("resnet18", "resnet50"):
        backbone = ResNet(name, frozen_stages=-1, norm_eval=False).eval()
        for m in backbone.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.data.uniform_(0.5, 1.5)
                m.bias.data.uniform_(-0.2, 0.2)
        folded = folded_for_inference(backbone)
        assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
        assert any(isinstance(m, torch.nn.BatchNorm2d) for m in backbone.modules())
        assert folded.layer2[0].conv1.weight.is_contiguous(memory_format=torch.channels_last)
        x = torch.randn(1, 3, 32, 64)
        with torch.no_grad():
            backbone64 = copy.deepcopy(backbone).double()
            exact = backbone64(x.double())
            for a, b in zip(folded_for_inference(backbone64)(x.double()), exact):
                torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-9)
            for a, b in zip(folded(x), exact):
                scale = b.abs().max()
                assert ((a.double() - b).abs().max() / scale) < 1e-4
