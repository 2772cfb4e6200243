"""JPEG decoders that install from PyPI, side by side on one nuScenes-sized (1600 x 900, 4:2:0)
JPEG, in one process, interleaved, medians; each one's pixels against Pillow's.

    OMP_NUM_THREADS=1 python -m tools.bench_jpeg [--repeats 30] [--image FILE.jpg]

Rows: the full-size decode, and the loader's work for a network input (reduced-scale decode
as preprocess.jpeg_reduction allows, then preprocess.resize_crop). Decoders: Pillow (the
fallback), simplejpeg, OpenCV's cv2.imdecode (opencv-python-headless), PyTurboJPEG (needs a
system libturbojpeg 3; reported as missing when it is absent). Without --image a textured
synthetic picture is written at quality 90. Last, the host normalisation of one ODG-T
sample (what the loader's workers did before they shipped uint8).
"""
import argparse
import io
import statistics
import time
from pathlib import Path

import numpy as np
from PIL import Image

from odg_ros import preprocess

SIZES = {"full 900x1600": None, "input 128x352": (128, 352), "input 256x704": (256, 704)}


def synthetic_jpeg(seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    h, w = 900, 1600
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 0.15 + 40 * np.sin(y / 37.0), y * 0.25 + 30 * np.cos(x / 23.0),
                    (x + y) * 0.08], -1) + rng.normal(0, 6, (h, w, 3))
    for _ in range(300):       # flat boxes: edges as in a street scene
        x0, y0 = rng.integers(0, w - 100), rng.integers(0, h - 100)
        img[y0:y0 + rng.integers(5, 100), x0:x0 + rng.integers(5, 100)] = rng.uniform(0, 255, 3)
    out = io.BytesIO()
    Image.fromarray(np.clip(img, 0, 255).astype(np.uint8)).save(out, "JPEG", quality=90)
    return out.getvalue()


def pillow(data, factor):
    with Image.open(io.BytesIO(data)) as im:
        if factor > 1:
            im.draft("RGB", (im.width // factor, im.height // factor))
        return np.asarray(im.convert("RGB"))


def decoders():
    found, missing = {"pillow": pillow}, {}
    try:
        import simplejpeg

        def simple(data, factor):
            h, w, _, _ = simplejpeg.decode_jpeg_header(data)
            return simplejpeg.decode_jpeg(data, "RGB", min_height=h // factor,
                                          min_width=w // factor, min_factor=factor)
        found["simplejpeg"] = simple
    except ImportError as error:
        missing["simplejpeg"] = str(error)
    try:
        import cv2
        flags = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2,
                 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}

        def opencv(data, factor):
            bgr = cv2.imdecode(np.frombuffer(data, np.uint8), flags[factor])
            return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        found["opencv"] = opencv
    except ImportError as error:
        missing["opencv"] = str(error)
    try:
        import turbojpeg
        jpeg = turbojpeg.TurboJPEG()

        def turbo(data, factor):
            return jpeg.decode(data, pixel_format=turbojpeg.TJPF_RGB,
                               scaling_factor=(1, factor))
        found["turbojpeg"] = turbo
    except Exception as error:  # ImportError, or its library missing (RuntimeError/OSError)
        missing["turbojpeg"] = f"{type(error).__name__}: {str(error).splitlines()[0]}"
    return found, missing


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--image", help="a JPEG to decode (default: a synthetic 1600x900)")
    args = parser.parse_args()
    data = Path(args.image).read_bytes() if args.image else synthetic_jpeg()
    found, missing = decoders()
    with Image.open(io.BytesIO(data)) as im:
        src_hw = (im.height, im.width)
    print(f"JPEG {src_hw[1]}x{src_hw[0]}, {len(data) / 1e3:.0f} kB; {args.repeats} interleaved "
          f"rounds, medians in ms")
    for name, why in missing.items():
        print(f"  {name}: not usable here ({why})")
    print(f"{'':16}" + "".join(f"{n:>22}" for n in found))
    for label, dst in SIZES.items():
        factor = 1 if dst is None else preprocess.jpeg_reduction(src_hw, dst)

        def work(decode):
            rgb = decode(data, factor)
            return rgb if dst is None else preprocess.resize_crop(rgb, dst)
        reference = work(pillow)
        times = {n: [] for n in found}
        for _ in range(args.repeats):
            for name, decode in found.items():
                start = time.perf_counter()
                work(decode)
                times[name].append(time.perf_counter() - start)
        base = statistics.median(times["pillow"])
        cells = []
        for name, decode in found.items():
            out = work(decode)
            diff = int(np.abs(out.astype(int) - reference).max()) if out.shape == \
                reference.shape else f"shape {out.shape}"
            med = statistics.median(times[name])
            cells.append(f"{med * 1e3:6.2f} ({med / base:4.2f}x, d{diff})")
        print(f"{label + f' /{factor}':16}" + "".join(f"{c:>22}" for c in cells))
    print("(ratio: time / Pillow's time; dN: largest pixel difference to Pillow's output)")
    worker_normalisation()


def worker_normalisation(shape=(8, 6, 256, 704, 3), repeats=5):
    """What the loader no longer does per ODG-T sample: normalise on the host, ship float32."""
    import torch
    images = torch.randint(0, 256, shape, dtype=torch.uint8)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        preprocess.normalize(images)
        times.append(time.perf_counter() - start)
    print(f"\nOne ODG-T sample {list(shape)}: uint8 {images.numel() / 2**20:.1f} MiB, float32 "
          f"{images.numel() * 4 / 2**20:.1f} MiB; preprocess.normalize on the host (what the "
          f"workers no longer do): {statistics.median(times) * 1e3:.0f} ms "
          f"({torch.get_num_threads()} thread(s), median of {repeats})")


if __name__ == "__main__":
    main()
