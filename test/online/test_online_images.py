"""Image decoding and validation (every bad input -> a specific BadInput), rig calibration."""
import io

import numpy as np
import pytest
from PIL import Image

from odg_ros.geometry import ego_to_image, invert_transform, make_transform
from odg_ros.online.errors import BadInput
from odg_ros.online.images import EncodedImage, decode, decode_compressed, decode_for_input, \
    decode_raw, to_network_input
from odg_ros.online.camera_calibration import check_intrinsics, load_rig, set_ego2img
from odg_ros.preprocess import adjust_intrinsics, resize_crop
from odg_ros.resources import resource_path


def rgb_image(h=90, w=160, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def encode(array, fmt):
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format=fmt)
    return buffer.getvalue()


def bad_kind(fn, *args):
    with pytest.raises(BadInput) as error:
        fn(*args)
    return error.value.kind


def test_png_round_trip_is_exact_and_jpeg_is_close():
    image = rgb_image()
    assert np.array_equal(decode_compressed(encode(image, "PNG"), "png"), image)
    smooth = np.repeat(np.linspace(0, 255, 160, dtype=np.uint8)[None, :, None], 90, 0)
    smooth = np.repeat(smooth, 3, 2)
    decoded = decode_compressed(encode(smooth, "JPEG"), "bgr8; jpeg compressed bgr8")
    assert decoded.shape == (90, 160, 3)
    assert np.abs(decoded.astype(int) - smooth).mean() < 2


def test_grey_and_rgba_pngs_become_rgb():
    grey = rgb_image()[:, :, 0]
    out = decode_compressed(encode(grey, "PNG"), "png")
    assert out.shape == (90, 160, 3) and np.array_equal(out[:, :, 1], grey)
    rgba = np.concatenate([rgb_image(), np.full((90, 160, 1), 7, np.uint8)], axis=2)
    assert np.array_equal(decode_compressed(encode(rgba, "PNG"), "png"), rgba[:, :, :3])


def test_corrupt_truncated_and_unsupported_compressed_images():
    jpeg = encode(rgb_image(), "JPEG")
    assert bad_kind(decode_compressed, jpeg[: len(jpeg) // 2], "jpeg") == "corrupt_image"
    assert bad_kind(decode_compressed, b"", "jpeg") == "corrupt_image"
    assert bad_kind(decode_compressed, b"\xff\xd8\xff" + b"\x00" * 100, "jpeg") == "corrupt_image"
    assert bad_kind(decode_compressed, b"hello world", "jpeg") == "corrupt_image"
    assert bad_kind(decode_compressed, encode(rgb_image(), "BMP"), "bmp") == "corrupt_image"
    assert bad_kind(decode_compressed, jpeg, "16UC1; compressedDepth") == "unsupported_encoding"
    sixteen = encode(np.zeros((8, 8), np.uint16) + 1000, "PNG")
    assert bad_kind(decode_compressed, sixteen, "png") == "unsupported_encoding"


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"])
def test_raw_encodings(encoding):
    image = rgb_image(6, 5)
    channels = {"rgb8": image, "bgr8": image[:, :, ::-1],
                "rgba8": np.concatenate([image, np.zeros((6, 5, 1), np.uint8)], 2),
                "bgra8": np.concatenate([image[:, :, ::-1], np.zeros((6, 5, 1), np.uint8)], 2),
                "mono8": image[:, :, :1]}[encoding]
    c = channels.shape[2]
    step = 5 * c + 3                                       # padded rows
    rows = np.zeros((6, step), np.uint8)
    rows[:, :5 * c] = channels.reshape(6, -1)
    out = decode(EncodedImage(False, encoding, rows.tobytes(), 6, 5, step))
    expected = np.repeat(image[:, :, :1], 3, 2) if encoding == "mono8" else image
    assert np.array_equal(out, expected)


def test_raw_bad_inputs():
    data = rgb_image(6, 5).tobytes()
    assert bad_kind(decode_raw, data, "16UC1", 6, 5, 10) == "unsupported_encoding"
    assert bad_kind(decode_raw, data, "yuv422", 6, 5, 10) == "unsupported_encoding"
    assert bad_kind(decode_raw, data[:-1], "rgb8", 6, 5, 15) == "corrupt_image"
    assert bad_kind(decode_raw, data, "rgb8", 6, 5, 14) == "corrupt_image"
    assert bad_kind(decode_raw, data, "rgb8", 0, 5, 15) == "corrupt_image"


def test_network_input_checks_size_and_adjusts_intrinsics():
    image = rgb_image(90, 160)
    K = np.array([[100.0, 0, 80], [0, 100, 45], [0, 0, 1]])
    out, K2 = to_network_input(image, (90, 160), K, (32, 88))
    assert np.array_equal(out, resize_crop(image, (32, 88)))
    assert np.allclose(K2, adjust_intrinsics(K, (90, 160), (32, 88)))
    assert bad_kind(to_network_input, image, (900, 1600), K, (32, 88)) == "wrong_image_size"


def test_camera_info_checks():
    K = [[100.0, 0, 80], [0, 100, 45], [0, 0, 1]]
    assert check_intrinsics(K, 90, 160, "cam").image_hw == (90, 160)
    assert bad_kind(check_intrinsics, np.zeros(9), 90, 160) == "bad_camera_info"
    assert bad_kind(check_intrinsics, [[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]], 90, 160) \
        == "bad_camera_info"
    assert bad_kind(check_intrinsics, K, 0, 160) == "bad_camera_info"


def test_shipped_nuscenes_rig():
    rig = load_rig(resource_path("config/rig_nuscenes.yaml"))
    assert list(rig.cameras) == ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK",
                                 "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
    headings = {}
    for name, cam in rig.cameras.items():
        assert cam.image_hw == (900, 1600)
        optical_axis = cam.sensor2ego[:3, 2]               # camera z in base_link
        headings[name] = np.degrees(np.arctan2(optical_axis[1], optical_axis[0]))
        assert abs(optical_axis[2]) < 0.1                   # looking roughly horizontally
        assert 1.4 < cam.sensor2ego[2, 3] < 1.7             # mounted on the roof
    assert abs(headings["CAM_FRONT"]) < 2 and abs(abs(headings["CAM_BACK"]) - 180) < 2
    assert 40 < headings["CAM_FRONT_LEFT"] < 70 and -70 < headings["CAM_FRONT_RIGHT"] < -40
    assert 100 < headings["CAM_BACK_LEFT"] < 130 and -130 < headings["CAM_BACK_RIGHT"] < -100
    # a point 10 m ahead projects near the centre column of CAM_FRONT
    front = rig.cameras["CAM_FRONT"]
    p = ego_to_image(front.intrinsics, front.sensor2ego) @ np.array([10.0, 0, 1.5, 1])
    assert p[2] > 0 and abs(p[0] / p[2] - 800) < 60


def test_bad_rig_files(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text("cameras: {}\n")
    with pytest.raises(ValueError, match="no 'cameras'"):
        load_rig(path)
    path.write_text("cameras:\n  A:\n    image_size: [9, 16]\n    intrinsics: [[0,0,0],[0,0,0],"
                    "[0,0,1]]\n    sensor2ego: {translation: [0,0,0], rotation: [1,0,0,0]}\n")
    with pytest.raises(ValueError, match="camera A"):
        load_rig(path)


def test_set_ego2img_compensates_motion_between_camera_stamps():
    K = np.array([[50.0, 0, 40], [0, 50, 20], [0, 0, 1]])
    ego_from_cam = make_transform(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]), (1, 0, 1.5))
    reference_pose = make_transform(np.eye(3), (100, 0, 0))
    later_pose = make_transform(np.eye(3), (100.5, 0, 0))     # moved 0.5 m forward
    point_ref = np.array([10.0, 1.0, 1.0, 1.0])                 # a static point, reference ego
    ego2img = set_ego2img([K, K], [ego_from_cam, ego_from_cam], [reference_pose, later_pose],
                          reference_pose)
    point_later = invert_transform(later_pose) @ reference_pose @ point_ref
    direct = ego_to_image(K, ego_from_cam)
    assert np.allclose(ego2img[0] @ point_ref, direct @ point_ref)
    assert np.allclose(ego2img[1] @ point_ref, direct @ point_later)


def nuscenes_like_jpeg(h=900, w=1600):
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([(xx * 0.15) % 255, (yy * 0.25) % 255, ((xx + yy) * 0.1) % 255], -1)
    array = np.clip(base + rng.normal(0, 6, base.shape), 0, 255).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="JPEG", quality=90)
    return buffer.getvalue()


@pytest.mark.parametrize("input_hw, reduced_hw", [((128, 352), (225, 400)),
                                                  ((256, 704), (450, 800))])
def test_reduced_jpeg_decode_matches_the_full_decode(input_hw, reduced_hw):
    data = nuscenes_like_jpeg()
    K = np.array([[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]])
    rgb, original_hw = decode_for_input(EncodedImage(True, "jpeg", data), input_hw)
    assert original_hw == (900, 1600) and rgb.shape[:2] == reduced_hw
    fast, K_fast = to_network_input(rgb, (900, 1600), K, input_hw, original_hw)
    full, K_full = to_network_input(decode_compressed(data), (900, 1600), K, input_hw)
    assert np.array_equal(K_fast, K_full) and fast.shape == full.shape
    difference = np.abs(fast.astype(int) - full)
    assert difference.mean() < 1.0 and difference.max() <= 8
    with pytest.raises(BadInput) as error:                 # the ORIGINAL size is checked
        to_network_input(rgb, (450, 800), K, input_hw, original_hw)
    assert error.value.kind == "wrong_image_size"


def test_reduced_decode_falls_back_when_the_scale_is_not_exact():
    data = nuscenes_like_jpeg(901, 1600)                    # 901 is not divisible by 2, 4, 8
    rgb, original_hw = decode_for_input(EncodedImage(True, "jpeg", data), (128, 352))
    assert original_hw == (901, 1600) and rgb.shape[:2] == (901, 1600)
    png_image = rgb_image(90, 160)
    rgb, original_hw = decode_for_input(EncodedImage(True, "png", encode(png_image, "PNG")),
                                        (32, 88))
    assert np.array_equal(rgb, png_image) and original_hw == (90, 160)
    with pytest.raises(BadInput) as error:
        decode_for_input(EncodedImage(True, "jpeg", data[:3000]), (128, 352))
    assert error.value.kind == "corrupt_image"


# ------------------------------------------------------------ JPEG sets decoded on the GPU
def photo_like(h=180, w=320, seed=0):
    """Smooth shading and edges (a JPEG of noise would be all artefacts)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    image = np.stack([100 + 60 * np.sin(x / (9 + 5 * c) + y / (13 + c)) for c in range(3)], -1)
    for _ in range(12):
        y0, x0 = rng.integers(0, h - 20), rng.integers(0, w - 20)
        image[y0:y0 + 30, x0:x0 + 50] += rng.uniform(-50, 50, 3)
    return np.clip(image, 0, 255).astype(np.uint8)


class PillowTorchvisionIO:
    """torchvision.io's decode_jpeg contract (list of CPU byte tensors in, [3, H, W] uint8
    out, RuntimeError on a bad JPEG) done with Pillow, always on the CPU: the device
    path's logic runs on the CPU (and asked for CUDA, it lands on the wrong device)."""

    class ImageReadMode:
        RGB = "RGB"

    def __init__(self):
        self.calls = 0

    def decode_jpeg(self, data, mode, device):
        import torch
        self.calls += 1
        out = []
        for tensor in data:
            try:
                image = Image.open(io.BytesIO(tensor.numpy().tobytes()), formats=("JPEG",))
                array = np.asarray(image.convert(mode))
            except OSError as error:
                raise RuntimeError(f"decode failed: {error}") from None
            out.append(torch.from_numpy(array.copy()).permute(2, 0, 1))
        return out


def test_resize_crop_tensor_matches_the_pillow_resize():
    import torch
    from odg_ros.online.images import resize_crop_tensor
    image = photo_like(900 // 5, 1600 // 5)
    for hw in ((64, 176), (128, 352), (180, 320), (200, 320)):     # shrink, same, pad
        expected = resize_crop(image, hw)
        got = resize_crop_tensor(torch.from_numpy(image).permute(2, 0, 1), hw)
        assert got.dtype == torch.uint8 and tuple(got.shape) == (*hw, 3)
        assert np.abs(got.numpy().astype(int) - expected).max() <= 1, hw


def test_jpeg_decoder_selection():
    import torch
    from odg_ros.online.images import device_jpeg_decoder, select_jpeg_decoder
    decoder, why = select_jpeg_decoder("cpu")
    assert decoder is None and "CPU (Pillow)" in why and "runs on cpu" in why

    def missing():
        raise ImportError("No module named 'torchvision'")

    decoder, why = select_jpeg_decoder("cuda", missing)
    assert decoder is None and "not available" in why and "torchvision" in why

    class NoNvjpeg(PillowTorchvisionIO):
        def decode_jpeg(self, data, mode, device):
            raise RuntimeError("torchvision was built without nvjpeg")

    decoder, why = select_jpeg_decoder("cuda", NoNvjpeg)
    assert decoder is None and "built without nvjpeg" in why
    # a decode that lands on the wrong device is refused too
    decoder, why = select_jpeg_decoder("cuda", PillowTorchvisionIO)
    assert decoder is None and "on cpu" in why
    decoder, why = device_jpeg_decoder(torch.device("cpu"), PillowTorchvisionIO)
    assert decoder is not None and "torchvision.io.decode_jpeg" in why


def device_decoder():
    import torch
    from odg_ros.online.images import DeviceJpegDecoder
    fake = PillowTorchvisionIO()
    return DeviceJpegDecoder(torch.device("cpu"), fake.decode_jpeg, "RGB"), fake


def test_device_decoder_gives_the_cpu_path_input_and_the_same_bad_inputs():
    decoder, fake = device_decoder()
    hw, input_hw = (180, 320), (64, 176)
    arrays = [photo_like(*hw, seed=k) for k in range(3)]
    images = [EncodedImage(True, "jpeg", encode(a, "JPEG")) for a in arrays]
    cams = ("A", "B", "C")
    out, ready = decoder.decode_set(images, cams, [hw] * 3, input_hw)
    assert ready is None and fake.calls == 1                      # one batched call
    assert tuple(out.shape) == (3, *input_hw, 3)
    for image, got in zip(images, out.numpy()):
        rgb, original_hw = decode_for_input(image, input_hw, hw)
        expected = to_network_input(rgb, hw, np.eye(3), input_hw, original_hw)[0]
        difference = np.abs(got.astype(int) - expected)
        assert difference.mean() < 1.0 and difference.max() <= 16   # the CPU path decodes
        # JPEGs reduced by DCT scaling (preprocess.draft_jpeg); here the full image

    # not all JPEG: the CPU path takes the set
    mixed = images[:2] + [EncodedImage(True, "png", encode(arrays[2], "PNG"))]
    assert decoder.decode_set(mixed, cams, [hw] * 3, input_hw) is None
    # a truncated JPEG, a wrong size, a huge header: BadInput naming the camera
    truncated = images[:2] + [EncodedImage(True, "jpeg", images[2].data[:400])]
    with pytest.raises(BadInput) as error:
        decoder.decode_set(truncated, cams, [hw] * 3, input_hw)
    assert error.value.kind == "corrupt_image" and error.value.message.startswith("C: ")
    with pytest.raises(BadInput) as error:
        decoder.decode_set(images, cams, [hw, (90, 160), hw], input_hw)
    assert error.value.kind == "wrong_image_size" and error.value.message.startswith("B: ")
    with pytest.raises(BadInput) as error:
        decoder.decode_set(images, cams, [hw] * 3, input_hw, max_pixels=100)
    assert error.value.kind == "image_too_large"


def test_pipeline_feeds_device_decoded_images_to_the_model():
    """The pipeline with a device decoder: the predictor takes the decoded tensor."""
    import torch
    from testing.helpers import tiny_config
    from odg_ros.network import ODG
    from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
    from odg_ros.online.predictor import OnlinePredictor
    cfg = tiny_config(score_threshold=0.0, box_score_threshold=0.0)
    torch.manual_seed(0)
    model = ODG(cfg).eval()
    rig = load_rig(resource_path("config/rig_nuscenes.yaml"))
    cams, hw = tuple(rig.cameras), (180, 320)
    pipeline = OnlinePipeline(OnlinePredictor(model, cfg, "cpu"),
                              PipelineSettings.from_parameters(cams),
                              lambda c, f, t: rig.cameras[c].sensor2ego)
    pipeline.jpeg_decoder = device_decoder()[0]
    for c in cams:
        pipeline.on_camera_info(c, adjust_intrinsics(rig.cameras[c].intrinsics, (900, 1600),
                                                     hw), *hw, frame_id=c)
    for t in np.arange(9.9, 10.3, 0.02):
        pipeline.on_pose(float(t), np.eye(4))
    for k, c in enumerate(cams):
        pipeline.on_image(c, 10.0 + 0.008 * k, EncodedImage(
            True, "jpeg", encode(photo_like(*hw, seed=k), "JPEG")), now=10.1)
    prepared = pipeline.prepare(pipeline.next_set(timeout=1.0))
    assert isinstance(prepared.images, torch.Tensor)
    result = pipeline.infer(prepared)
    predictor = pipeline.predictor
    for images in (prepared.images.numpy(), np.zeros_like(prepared.images.numpy())):
        predictor.reset()
        expected = predictor.step(images, prepared.ego2img, prepared.reference_pose, 10.0)
        # equal to the step on the same images as NumPy; blank images give another output
        same = np.array_equal(result.confidence, expected.confidence)
        assert same == (images.any() and np.array_equal(result.grid, expected.grid))


@pytest.mark.skipif(not __import__("torch").cuda.is_available(),
                    reason="nvJPEG decoding needs a CUDA device (none here)")
def test_jpeg_sets_decode_on_the_gpu_like_the_cpu_path():
    pytest.importorskip("torchvision", reason="torchvision is not installed (its CUDA "
                        "JPEG decoder is the device path)")
    from odg_ros.online.images import select_jpeg_decoder
    decoder, why = select_jpeg_decoder("cuda")
    assert decoder is not None, why
    hw, input_hw = (900, 1600), (256, 704)
    images = [EncodedImage(True, "jpeg", encode(photo_like(*hw, seed=k), "JPEG"))
              for k in range(6)]
    out, ready = decoder.decode_set(images, [str(k) for k in range(6)], [hw] * 6, input_hw)
    decoder.hand_over(out, ready)
    assert out.is_cuda and tuple(out.shape) == (6, *input_hw, 3)
    for image, got in zip(images, out.cpu().numpy()):
        rgb, original_hw = decode_for_input(image, input_hw, hw)
        expected = to_network_input(rgb, hw, np.eye(3), input_hw, original_hw)[0]
        assert np.abs(got.astype(int) - expected).mean() < 1.5     # nvJPEG's IDCT differs
