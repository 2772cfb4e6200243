"""The census sees every way the host can wait for the device: each spelling, planted alone in
a tiny step with the CUDA paths forced, is counted exactly once and as its kind; what does
not wait (pinned non-blocking uploads, scalars, host-only work, constants already made) is
counted as no wait."""
import numpy as np
import pytest
import torch

from odg_ros.transfer import device_constant, upload
from odg_ros.bench.census import Census, CensusMode


def waits_of(step):
    """(waits by kind, total waits, ops) of ``step(x, h, i)`` with x a device tensor, h host
    data of the same shape (as the batch's targets are), i a device long tensor."""
    x = torch.tensor([1.0, -2.0, 3.0])
    h = torch.tensor([4.0, 5.0, 6.0])
    i = torch.tensor([0, 2, 2])
    census = Census()
    with CensusMode(census, None, host_tensors=[h]):
        step(x, h, i)
    kinds = {kind: n for kind, n in census.kinds.items() if n}
    return kinds, sum(census.syncs.values()), sum(census.ops.values())


def masked_write(x, h, i):
    x[x > 0] = 0.0


PLANTED = {
    # values read by the host
    ".item()": ("read", lambda x, h, i: x.sum().item()),
    "bool()": ("read", lambda x, h, i: bool(x.sum() > 0)),
    "float()": ("read", lambda x, h, i: float(x.sum())),
    "int()": ("read", lambda x, h, i: int(i.sum())),
    "if tensor": ("read", lambda x, h, i: 1 if (x > 0).any() else 0),
    ".tolist()": ("read", lambda x, h, i: x.tolist()),
    ".numpy()": ("read", lambda x, h, i: x.numpy()),
    "np.asarray()": ("read", lambda x, h, i: np.asarray(x)),
    "allclose": ("read", lambda x, h, i: torch.allclose(x, x * 1.0)),
    "equal": ("read", lambda x, h, i: torch.equal(x, x * 1.0)),
    "histc": ("read", lambda x, h, i: torch.histc(x, bins=4)),
    # copies to host memory
    ".cpu()": ("download", lambda x, h, i: x.cpu()),
    '.to("cpu")': ("download", lambda x, h, i: x.to("cpu")),
    '.to(device="cpu")': ("download", lambda x, h, i: x.to(device="cpu")),
    "copy_ into host": ("download", lambda x, h, i: h.copy_(x)),
    # sizes that depend on the data
    "nonzero": ("shape", lambda x, h, i: x.nonzero()),
    "argwhere": ("shape", lambda x, h, i: torch.argwhere(x)),
    "where(condition)": ("shape", lambda x, h, i: torch.where(x > 0)),
    "masked_select": ("shape", lambda x, h, i: x.masked_select(x > 0)),
    "boolean index": ("shape", lambda x, h, i: x[x > 0]),
    "boolean index_put": ("shape", masked_write),
    "boolean index of an empty device tensor, beside empty host data": (
        "shape", lambda x, h, i: (h[:0].clone(), x[:0].clone()[x[:0] > 0])),
    "unique": ("shape", lambda x, h, i: torch.unique(x)),
    "unique(return_counts)": ("shape", lambda x, h, i: torch.unique(i, return_counts=True)),
    "unique_consecutive": ("shape", lambda x, h, i: torch.unique_consecutive(i)),
    "bincount": ("shape", lambda x, h, i: torch.bincount(i)),
    "repeat_interleave": ("shape", lambda x, h, i: torch.repeat_interleave(x, i)),
    # copies from pageable host memory
    "torch.tensor(device=)": ("upload",
                              lambda x, h, i: x * torch.tensor([1.0, 2.0, 3.0], device=x.device)),
    "new_tensor": ("upload", lambda x, h, i: x * x.new_tensor([1.0, 2.0, 3.0])),
    "as_tensor(list)": ("upload",
                        lambda x, h, i: x * torch.as_tensor([1.0, 2.0, 3.0], device=x.device)),
    "as_tensor(array)": ("upload", lambda x, h, i: x * torch.as_tensor(np.ones(3, np.float32),
                                                                       device=x.device)),
    "from_numpy().to()": ("upload",
                          lambda x, h, i: x * torch.from_numpy(np.ones(3, np.float32)).to(x)),
    "fresh tensor, then a host op": ("upload", lambda x, h, i: x + torch.tensor([1.0, 2, 3]) * 2),
    "fresh sizes with a device factory": ("upload", lambda x, h, i: torch.repeat_interleave(
        torch.arange(3), torch.tensor([1, 2, 0]), output_size=3)),
    "host .to(device)": ("upload", lambda x, h, i: x * h.to(x.device)),
    "host .to(device, non_blocking) unpinned": (
        "upload", lambda x, h, i: x * h.to(x.device, non_blocking=True)),
    "pinned .to(device) blocking": ("upload", lambda x, h, i: h.pin_memory().to(x.device)),
    "copy_ from host": ("upload", lambda x, h, i: x.copy_(h)),
    "host tensor in a device op": ("upload", lambda x, h, i: x * h),
    "host index into a device tensor": ("upload", lambda x, h, i: x[h.long() % 3]),
}

NO_WAIT = {
    "a pinned non-blocking upload": lambda x, h, i: x * upload(h, x.device),
    "upload of a fresh host tensor": lambda x, h, i: x * upload(torch.tensor([1.0, 2, 3]),
                                                                x.device),
    "a 0-dim host tensor in a device op": lambda x, h, i: x * h.sum(),
    "host work": lambda x, h, i: (h * 2).sort().values.tolist(),
    "a fresh tensor on the host": lambda x, h, i: (torch.tensor([1.0, 2, 3]) + h).tolist(),
    "a factory on the host": lambda x, h, i: (torch.zeros(3) + h).numpy(),
    "a factory on the device": lambda x, h, i: x + torch.zeros(3) * 2,
    "repeat_interleave with output_size": lambda x, h, i: torch.repeat_interleave(
        x, i, output_size=4),
    "a device constant made before": lambda x, h, i: x * device_constant((1.0, 2.0, 3.0),
                                                                         x.device),
    ".cpu() of host data": lambda x, h, i: h.cpu().numpy(),
    ".to(device) of a device tensor": lambda x, h, i: x.to(x.device) * 2,
    "an integer index": lambda x, h, i: x[i],
    "empty tensors (all at address 0)": lambda x, h, i: (h.new_zeros(0),
                                                         torch.cat([x, x.new_zeros(0)])),
}


@pytest.mark.parametrize("name", list(PLANTED))
def test_each_spelling_is_one_wait_of_its_kind(name):
    kind, step = PLANTED[name]
    kinds, total, ops = waits_of(step)
    assert kinds == {kind: 1} and total == 1, (name, kinds)
    assert ops >= 1


@pytest.mark.parametrize("name", list(NO_WAIT))
def test_what_does_not_wait_counts_no_wait(name):
    device_constant((1.0, 2.0, 3.0), "cpu")            # made before, as in a warm-up step
    kinds, total, _ = waits_of(NO_WAIT[name])
    assert total == 0, (name, kinds)


def test_a_constant_made_in_the_step_is_one_upload_the_first_time():
    values = (7.0, 8.0, 9.0)      # a key no other test makes
    assert waits_of(lambda x, h, i: x * device_constant(values, x.device))[:2] == \
        ({"upload": 1}, 1)
    assert waits_of(lambda x, h, i: x * device_constant(values, x.device))[1] == 0


def test_every_kind_is_planted():
    from odg_ros.bench.census import WAIT_KINDS
    assert {kind for kind, _ in PLANTED.values()} == set(WAIT_KINDS)
