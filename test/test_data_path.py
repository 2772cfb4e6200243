"""The training data path: the loader ships uint8 images, the upload normalises them on the
device, and a training step is the one it was when the loader shipped normalised floats."""
import pytest
import torch

from odg_ros import preprocess
from odg_ros.data.batch import collate, to_device
from odg_ros.train.trainer import Trainer, TrainOptions

from helpers import tiny_config, write_tiny_split


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

