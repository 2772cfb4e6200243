"""The training data path: the loader ships uint8 images, the upload normalises them on the
device, and a training step is the one it was when the loader shipped normalised floats."""
import pytest
import torch

from odg_ros import preprocess
from odg_ros.data.batch import collate, to_device
from odg_ros.train.trainer import Trainer, TrainOptions

from testing.helpers import tiny_config, write_tiny_split


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("split"), 2)


def trainer(split, out):
    return Trainer(tiny_config(num_frames=2), split, TrainOptions(
        out_dir=out, epochs=1, workers=0, warmup_steps=1, progress=False,
        render_pixels_per_camera=64, lr=1e-3))


def test_upload_normalises_uint8_images_and_passes_normalised_ones():
    images = torch.randint(0, 256, (1, 2, 6, 8, 12, 3), dtype=torch.uint8)
    batch = {"images": images, "token": ["a"], "render_targets": [[torch.zeros(0, 4)]]}
    uploaded = to_device(batch, "cpu")
    expected = preprocess.normalize(images)
    assert uploaded["images"].shape == (1, 2, 6, 3, 8, 12)
    torch.testing.assert_close(uploaded["images"], expected, rtol=0, atol=0)
    reference = (images.double() / 255 - torch.tensor(preprocess.IMAGENET_MEAN).double()) \
        / torch.tensor(preprocess.IMAGENET_STD).double()
    torch.testing.assert_close(uploaded["images"].double(), reference.movedim(-1, -3),
                               rtol=0, atol=1e-6)
    again = to_device(uploaded, "cpu")          # already normalised: left as it is
    assert again["images"] is uploaded["images"]


def test_a_step_on_uint8_images_is_the_step_on_normalised_floats(split, tmp_path):
    """Augmentation on (flip, zoom, photometric): the losses of the first step and the weights
    after it are those of the loader that normalised in its workers."""
    new, old = trainer(split, tmp_path / "new"), trainer(split, tmp_path / "old")
    batch = collate([new.dataset[1]])
    assert batch["images"].dtype == torch.uint8
    host_normalised = dict(batch, images=preprocess.normalize(batch["images"]))
    torch.manual_seed(5)
    terms_new, applied_new = new.train_step(batch).read()
    torch.manual_seed(5)
    terms_old, applied_old = old.train_step(host_normalised).read()
    assert applied_new and applied_old and set(terms_new) == set(terms_old)
    for name, value in terms_old.items():
        assert terms_new[name] == pytest.approx(value, rel=1e-5, abs=1e-7), name
    for a, b in zip(new.model.parameters(), old.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------- prefetch
class RecordedStreams:
    """Stands in for CudaStreams: logs the calls the prefetcher makes, in order."""

    def __init__(self, log):
        self.log, self.on_side_now, self.kept = log, False, set()

    def on_side(self):
        streams = self

        class Side:
            def __enter__(self):
                streams.on_side_now = True

            def __exit__(self, *exc):
                streams.on_side_now = False
        return Side()

    def mark_uploaded(self):
        assert self.on_side_now, "the upload's event must be recorded on the side stream"
        event = f"event{self.log[-1].split()[-1]}"
        self.log.append(f"record {event}")
        return event

    def wait(self, event):
        assert not self.on_side_now
        self.log.append(f"wait {event}")

    def keep_for_current(self, tensor):
        self.log.append("keep")
        self.kept.add(id(tensor))


def host_batches(log, count):
    for k in range(count):
        log.append(f"fetch {k}")
        yield {"images": torch.full((1, 1, 1, 2, 2, 3), k, dtype=torch.uint8),
               "time_delta": torch.full((1, 1), float(k)), "token": [f"s{k}"],
               "render_targets": [[torch.full((2, 4), float(k))]]}


def run_prefetcher(count, streams_for):
    from odg_ros.data.prefetch import DevicePrefetcher, batch_tensors
    log = []
    streams = streams_for(log)

    def upload(batch, device):
        assert streams is None or streams.on_side_now, "uploads run on the side stream"
        log.append(f"upload {int(batch['time_delta'][0, 0])}")
        return to_device(batch, device)
    for batch in DevicePrefetcher(host_batches(log, count), "cpu", upload, streams):
        log.append(f"step {int(batch['time_delta'][0, 0])}")
        assert batch["images"].dtype == torch.float32
        if streams is not None:     # every device tensor the step reads
            assert {id(t) for t in batch_tensors(batch)} <= streams.kept
            assert len(list(batch_tensors(batch))) == 2
            # the render targets stay on the host: no stream to keep them for
            assert id(batch["render_targets"][0][0]) not in streams.kept
    return log


def test_prefetcher_uploads_the_next_batch_before_the_current_step():
    """With streams: batch k+1 is fetched and its upload queued on the side stream before
    step k; step k waits for batch k's event only, and every device tensor of batch k is
    marked as used by the current stream before the step."""
    log = run_prefetcher(3, RecordedStreams)
    hand_over = lambda k: [f"wait event{k}", "keep", "keep", f"step {k}"]  # noqa: E731
    assert log == (["fetch 0", "upload 0", "record event0", "fetch 1", "upload 1",
                    "record event1"] + hand_over(0)
                   + ["fetch 2", "upload 2", "record event2"] + hand_over(1) + hand_over(2))


def test_prefetcher_without_streams_fetches_nothing_ahead():
    """On the CPU each batch is fetched and uploaded only when its step is next."""
    log = run_prefetcher(3, lambda log: None)
    assert log == [f"{what} {k}" for k in range(3) for what in ("fetch", "upload", "step")]
    assert run_prefetcher(0, RecordedStreams) == []


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="side streams and record_stream need a GPU; no GPU on this machine")
def test_prefetched_cuda_batches_equal_direct_uploads_while_steps_run():
    """Real streams: each batch arrives complete although the current stream is busy with a
    long computation when its upload is queued, and no later upload overwrites it."""
    from odg_ros.data.prefetch import DevicePrefetcher
    host = [{k: (v.pin_memory() if torch.is_tensor(v) else v) for k, v in b.items()}
            for b in host_batches([], 6)]
    work = torch.randn(2048, 2048, device="cuda")
    read = []
    for batch in DevicePrefetcher(host, "cuda"):
        for _ in range(20):                  # the "step": keeps the current stream busy
            work = torch.tanh(work @ work)
        # queued after the long work; the batch is dropped at once: without record_stream a
        # later upload could take its memory before this copy runs
        read.append((batch["images"].clone(), batch["render_targets"][0][0].clone()))
        del batch
    torch.cuda.synchronize()
    for (images, targets), original in zip(read, host, strict=True):
        expected = to_device(original, "cuda")
        torch.testing.assert_close(images, expected["images"], rtol=0, atol=0)
        torch.testing.assert_close(targets, expected["render_targets"][0][0], rtol=0, atol=0)
