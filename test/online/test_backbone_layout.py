"""The node step's backbone and FPN run channels-last end to end, BatchNorm folded: a census of
the step sees no layout conversion inside them (no ``contiguous`` / ``clone`` / ``_to_copy``
into another memory format), and every convolution gets a channels-last input and weight (a
convolution given mixed layouts converts inside its kernel, where no census can see it)."""
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from odg_ros.online.predictor import OnlinePredictor
from testing.online import make_model, make_sets

aten = torch.ops.aten
CONVERSIONS = {aten.clone.default, aten._to_copy.default, aten.contiguous.default,
               aten.copy_.default}


class LayoutCensus(TorchDispatchMode):
    """Inside the feature extractor (``inside`` set by module hooks): layout conversions and
    convolutions whose input or weight is not channels-last."""

    def __init__(self):
        super().__init__()
        self.inside, self.conversions, self.mixed, self.convolutions = False, [], [], 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if self.inside:
            if func in CONVERSIONS and (kwargs.get("memory_format") not in (
                    None, torch.preserve_format) or func is not aten._to_copy.default):
                self.conversions.append(str(func))
            if func in (aten.convolution.default, aten.conv2d.default):
                self.convolutions += 1
                if not all(t.is_contiguous(memory_format=torch.channels_last)
                           for t in args[:2]):
                    self.mixed.append(tuple(args[1].shape))
        return func(*args, **kwargs)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_node_steps_features_are_channels_last_end_to_end(precision):
    model, cfg = make_model()
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, precision=precision)
    step = predictor.online_step
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in step.backbone.modules())
    census = LayoutCensus()

    def enter(*_):
        census.inside = True

    def leave(*_):
        census.inside = False
    for module in (step.backbone, step.neck):
        module.register_forward_pre_hook(enter)
        module.register_forward_hook(leave)
    images, ego2img, pose, stamp = make_sets(cfg, 1)[0]
    predictor.step(images, ego2img, pose, stamp)             # fills the buffers
    with torch.inference_mode(), census:
        predictor.online_step(torch.from_numpy(images), predictor._packed)
    assert census.convolutions > 20                          # backbone and FPN ran
    assert census.conversions == [] and census.mixed == [], (census.conversions, census.mixed)
