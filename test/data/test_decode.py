"""The loader's image decoder: simplejpeg where installed gives Pillow's pixels, at the same
reduced scale; Pillow decodes the rest; a wrong size is one clear error."""
import numpy as np
import pytest
from PIL import Image

from odg_ros import preprocess
from odg_ros.data import decode

INPUT_HW = (64, 176)


def textured(h=360, w=640, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 0.3 + 40 * np.sin(y / 9.0), y * 0.5, (x + y) * 0.2], -1)
    return np.clip(img + rng.normal(0, 20, img.shape), 0, 255).astype(np.uint8)


def pillow_path(path, dst_hw):
    with Image.open(path) as im:
        return decode.decode_resized(im, dst_hw)


@pytest.mark.parametrize("dst_hw", [(32, 88), INPUT_HW, (128, 352), (360, 640)])
def test_simplejpeg_gives_pillows_pixels_at_the_same_scale(tmp_path, dst_hw):
    pytest.importorskip("simplejpeg")
    path = tmp_path / "cam.jpg"
    Image.fromarray(textured()).save(path, quality=90)
    factor = preprocess.jpeg_reduction((360, 640), dst_hw)
    reduced = decode.decode_jpeg_reduced(path.read_bytes(), dst_hw, (360, 640))
    assert reduced.shape == (360 // factor, 640 // factor, 3)
    ours = decode.read_image(path, dst_hw, (360, 640))
    assert ours.shape == (*dst_hw, 3) and ours.dtype == np.uint8
    np.testing.assert_array_equal(ours, pillow_path(path, dst_hw))


def test_pillow_decodes_without_simplejpeg_and_for_png(tmp_path, monkeypatch):
    Image.fromarray(textured()).save(tmp_path / "cam.jpg", quality=90)
    Image.fromarray(textured(seed=1)).save(tmp_path / "cam.png")
    with_simplejpeg = decode.read_image(tmp_path / "cam.jpg", INPUT_HW)
    png = decode.read_image(tmp_path / "cam.png", INPUT_HW)
    np.testing.assert_array_equal(png, preprocess.resize_crop(textured(seed=1), INPUT_HW))
    monkeypatch.setattr(decode, "simplejpeg", None)
    np.testing.assert_array_equal(decode.read_image(tmp_path / "cam.jpg", INPUT_HW),
                                  with_simplejpeg)


def test_a_wrong_size_or_missing_file_is_one_clear_error(tmp_path):
    Image.fromarray(textured()).save(tmp_path / "cam.jpg", quality=90)
    with pytest.raises(ValueError, match=r"cam.jpg: image is 360x640, infos say \(900, 1600\)"):
        decode.read_image(tmp_path / "cam.jpg", INPUT_HW, (900, 1600))
    with pytest.raises(FileNotFoundError, match="image not found"):
        decode.read_image(tmp_path / "gone.jpg", INPUT_HW)
