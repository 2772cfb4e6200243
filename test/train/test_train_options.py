"""Training options for GPU memory and speed: channels-last convolution weights, gradient
checkpointing of the backbone, a compiled forward. Each leaves the losses and gradients as
they were (float32: the sampling kernels have no float64 path; the sum is taken in float64)."""
import time

import pytest
import torch

from odg_ros.data.batch import collate
from odg_ros.network import ODG
from odg_ros.train.trainer import (Trainer, TrainOptions, channels_last_convolutions,
                                  checkpoint_backbone)

from testing.helpers import model_inputs, tiny_config, write_tiny_split


def scalar(output):
    """Every output of every layer in one float64 number (so every gradient path counts)."""
    total = output.init_means.double().square().mean()
    for layer in output.layers:
        for t in (layer.means, layer.logits, layer.scales, layer.rotations, layer.opacities,
                  layer.boxes, layer.box_logits):
            if t is not None:
                total = total + t.double().square().mean()
    return total


def loss_and_gradients(model, inputs, seed=0):
    model.train()
    model.zero_grad(set_to_none=True)
    torch.manual_seed(seed)
    loss = scalar(model(*inputs))
    loss.backward()
    return loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()
                           if p.grad is not None}


def twin_models(**overrides):
    cfg = tiny_config(num_frames=2, **overrides)
    torch.manual_seed(0)
    model = ODG(cfg)
    twin = ODG(cfg)
    twin.load_state_dict(model.state_dict())
    inputs = model_inputs(cfg, seed=1)
    return model, twin, inputs


def assert_same(a, b, rtol, atol):
    (loss_a, grads_a), (loss_b, grads_b) = a, b
    torch.testing.assert_close(loss_a, loss_b, rtol=rtol, atol=atol)
    assert set(grads_a) == set(grads_b) and len(grads_a) > 50
    for name in grads_a:
        torch.testing.assert_close(grads_a[name], grads_b[name], rtol=rtol, atol=atol, msg=name)


def test_channels_last_weights_leave_loss_and_gradients_as_they_were():
    model, twin, inputs = twin_models()
    channels_last_convolutions(twin)
    convs = [m.weight for m in twin.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) > 20
    assert all(w.is_contiguous(memory_format=torch.channels_last) for w in convs)
    assert sum(not w.is_contiguous() for w in convs) > 20     # 1x1 kernels are both
    assert_same(loss_and_gradients(model, inputs), loss_and_gradients(twin, inputs),
                rtol=1e-10, atol=1e-12)


def test_backbone_checkpointing_gives_the_same_gradients_and_runs_stages_again():
    """A pretrained-style backbone (frozen stem and layer1, BatchNorm frozen): the stages that
    train run twice per step (forward, then again in the backward), layer1 once."""
    model, twin, inputs = twin_models(norm_eval=True, frozen_stages=1)
    checkpoint_backbone(twin)
    calls = {"layer1": 0, "layer4": 0}
    for name in calls:            # (the recomputation runs no module hooks: wrap forward)
        block = getattr(twin.backbone, name)[0]

        def counted(x, name=name, forward=block.forward):
            calls[name] += 1
            return forward(x)
        block.forward = counted
    expected = loss_and_gradients(model, inputs)
    assert_same(expected, loss_and_gradients(twin, inputs), rtol=1e-10, atol=1e-12)
    assert calls == {"layer1": 1, "layer4": 2}
    with torch.no_grad():            # nothing to recompute without autograd
        twin(*inputs)
    assert calls == {"layer1": 2, "layer4": 3}


def test_backbone_checkpointing_is_refused_where_batchnorm_trains():
    model = ODG(tiny_config(num_frames=2))          # odg_cpu: BatchNorm trains
    with pytest.raises(ValueError, match="--checkpoint-backbone needs a backbone with frozen "
                                         "BatchNorm"):
        checkpoint_backbone(model)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("split"), 2)


def first_step(split, out, **options):
    torch.manual_seed(0)
    trainer = Trainer(tiny_config(num_frames=2), split, TrainOptions(
        out_dir=out, epochs=1, workers=0, warmup_steps=1, progress=False,
        render_pixels_per_camera=64, lr=1e-3, augment=False, **options))
    torch.manual_seed(1)
    terms, applied = trainer.train_step(collate([trainer.dataset[1]])).read()
    assert applied
    return trainer, terms


def test_compile_wraps_the_forward_and_leaves_the_module_and_checkpoints_plain(
        split, tmp_path, monkeypatch):
    """--compile hands the forward (the DDP wrapper's where there is one) to torch.compile;
    the state dict the checkpoints hold keeps the plain module's keys."""
    compiled = []

    def recording_compile(module, **kwargs):
        compiled.append(module)
        return module                                   # runs eagerly: nothing is compiled
    monkeypatch.setattr(torch, "compile", recording_compile)
    trainer, _ = first_step(split, tmp_path, compile=True)
    assert compiled == [trainer.model] and trainer.forward_module is trainer.model
    trainer.save()
    saved = torch.load(tmp_path / "latest.pt", map_location="cpu", weights_only=False)["model"]
    assert not any("_orig_mod" in key for key in saved)
    assert set(saved) == set(trainer.model.state_dict())


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="Inductor takes ~15 min to compile the tiny model's training "
                           "forward on a 2-core CPU (measured: 927 s); no GPU on this machine")
def test_compiled_forward_gives_the_eager_losses(split, tmp_path):
    """Inductor with eager's random numbers (dropout): every loss term of the first step as
    in eager mode, to bf16 autocast's precision."""
    import torch._inductor.config as inductor_config
    inductor_config.fallback_random = True
    try:
        start = time.perf_counter()
        _, compiled = first_step(split, tmp_path / "compiled", compile=True, device="cuda")
        print(f"compile and first step: {time.perf_counter() - start:.0f} s")
    finally:
        inductor_config.fallback_random = False
    trainer, eager = first_step(split, tmp_path / "eager", device="cuda")
    assert trainer.model.backbone.layer2[0].conv2.weight.is_contiguous(
        memory_format=torch.channels_last)             # on CUDA the weights are NHWC
    assert set(compiled) == set(eager)
    for name, value in eager.items():
        assert compiled[name] == pytest.approx(value, rel=2e-2, abs=1e-4), name
