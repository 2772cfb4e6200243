"""What every ``odg`` command shares: argument types that check a value when it is parsed
(one clear line, exit code 2, instead of a failure deep inside), the options several commands
take (``add_device_option`` ...: one spelling and meaning of ``--device`` everywhere), the help
formatter that shows defaults, and UserError for a mistake found later.

A new option takes one of these types, e.g.
``parser.add_argument("--iters", type=positive_int, default=5, help="timed iterations")``.
Importing this module imports neither torch nor rclpy (``odg CMD --help`` stays fast).
"""
from __future__ import annotations

import argparse
import pickle
from pathlib import Path

class UserError(Exception):
    """A mistake in the command line or its files, found after parsing."""


# Reported as one line `odg CMD: error: ...` with exit code 2 (main, commands/__init__.py): a
# UserError and what the library raises for bad input (a missing or foreign file, a bad value).
USER_ERRORS = (UserError, FileNotFoundError, FileExistsError, NotADirectoryError,
               IsADirectoryError, PermissionError, ValueError)


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: ``odg CMD: error: ...`` (exit 2)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class DefaultsFormatter(argparse.RawDescriptionHelpFormatter):
    """Adds ``(default: X)`` to an option's help unless the help already says its default;
    options without one (None, a flag) explain themselves in their help."""

    def _get_help_string(self, action):
        text = action.help or ""
        if any(action.default is v for v in (None, False, argparse.SUPPRESS)) \
                or "default" in text or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


def _parse_number(text: str, kind):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None


def _bounded(kind, least, strict: bool, name: str):
    """-> an argument type for a ``kind`` > ``least`` (strict) or >= ``least``; NaN fails."""
    def parse(text: str):
        value = _parse_number(text, kind)
        if value != value or (value <= least if strict else value < least):
            raise argparse.ArgumentTypeError(f"must be {'>' if strict else '>='} {least}, "
                                             f"got {text}")
        return value
    parse.__name__ = parse.__qualname__ = name          # argparse names the type by it
    return parse


positive_int = _bounded(int, 0, strict=True, name="positive_int")
nonnegative_int = _bounded(int, 0, strict=False, name="nonnegative_int")
positive_float = _bounded(float, 0.0, strict=True, name="positive_float")
nonnegative_float = _bounded(float, 0.0, strict=False, name="nonnegative_float")


def probability(text: str) -> float:
    """A probability in [0, 1)."""
    value = _parse_number(text, float)
    if not 0.0 <= value < 1.0:                                          # NaN fails too
        raise argparse.ArgumentTypeError(f"{text}: expected a probability in [0, 1)")
    return value


# The path types return the text as given (a str, like an option without a type), checked.
def existing_file(text: str) -> str:
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"file not found: {text}")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"not a file: {text}")
    if path.stat().st_size == 0:
        raise argparse.ArgumentTypeError(f"file is empty: {text}")
    return text


def existing_dir(text: str) -> str:
    if not Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"directory not found: {text}")
    return text


def infos_file(text: str) -> str:
    """An infos pickle written by ``odg prepare`` that holds at least one keyframe."""
    path = existing_file(text)
    from ..data.prepare import load_infos
    try:
        infos = load_infos(path)
    except (pickle.UnpicklingError, EOFError, ValueError, AttributeError, ImportError) as e:
        raise argparse.ArgumentTypeError(f"{text} is not an infos file of odg prepare "
                                         f"({type(e).__name__})") from None
    if not infos["infos"]:
        raise argparse.ArgumentTypeError(f"{text} holds no keyframes (odg prepare of an "
                                         "empty split?)")
    return text


def preset(text: str) -> str:
    """A preset name (model/<name>.yaml) or the path of a preset YAML file."""
    from ..model_config import PRESET_NAMES
    if text in PRESET_NAMES or (Path(text).suffix in (".yaml", ".yml") and Path(text).is_file()):
        return text
    raise argparse.ArgumentTypeError(f"unknown preset {text!r}: one of "
                                     f"{', '.join(PRESET_NAMES)}, or a preset YAML file")


def device(text: str) -> str:
    """auto, cpu, cuda or cuda:N; a CUDA device must exist here."""
    if text in ("auto", "cpu"):
        return text
    index = text.removeprefix("cuda").removeprefix(":")
    if not text.startswith("cuda") or (index and not index.isdigit()) or text == "cuda:":
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda or cuda:N, got {text!r}")
    import torch
    if not torch.cuda.is_available():
        build = "built without CUDA" if torch.version.cuda is None else "no CUDA device found"
        raise argparse.ArgumentTypeError(f"{text}: CUDA is not available here (torch "
                                         f"{torch.__version__}, {build}); see the README's "
                                         "GPU install")
    if index and int(index) >= torch.cuda.device_count():
        raise argparse.ArgumentTypeError(f"{text}: only {torch.cuda.device_count()} CUDA "
                                         "devices here")
    return text


def config_overrides(items: list[str] | None) -> dict:
    """``--set key=value`` items -> {key: value} for ModelConfig, checked by the node's
    validator (online/parameters.py: types, ranges, unknown keys); a negative score
    threshold keeps the checkpoint's own, as the node's parameter does."""
    from ..online.parameters import parse_settings
    try:
        values = parse_settings(items)
    except ValueError as error:
        raise UserError(str(error)) from None
    return {k: v for k, v in values.items()
            if not (k in ("score_threshold", "box_score_threshold") and v < 0)}


# Options several commands take, spelled once: the same flag means the same thing everywhere.
def add_device_option(parser, default: str = "auto", help: str | None = None) -> None:
    parser.add_argument("--device", type=device, default=default,
                        help=help or "auto (cuda when available), cpu, cuda or cuda:N")


def add_preset_option(parser, default: str | None = "odg_cpu", help: str | None = None) -> None:
    from ..model_config import PRESET_NAMES
    parser.add_argument("--preset", type=preset, default=default,
                        help=help or f"model preset ({', '.join(PRESET_NAMES)}) or a preset "
                                     "YAML file")


def add_json_option(parser, help: str = "print JSON only") -> None:
    parser.add_argument("--json", action="store_true", help=help)


def add_set_option(parser, help: str) -> None:
    """``--set KEY=VALUE`` (repeatable), read with config_overrides."""
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help=help)


def add_backbone_start_options(parser) -> None:
    """Where a trained backbone starts from (odg train, odg profile train)."""
    parser.add_argument("--backbone-weights", type=existing_file,
                        help="ResNet checkpoint to start the backbone from: torchvision, timm, "
                             "or mmdetection/mmdet3d (backbone.* / img_backbone.* keys, e.g. "
                             "nuImages Cascade Mask R-CNN; default: none, which presets "
                             "with frozen stages refuse)")
    parser.add_argument("--backbone-from-scratch", action="store_true",
                        help="no pretrained weights: unfreeze a preset's frozen stem/layer1 and "
                             "train its BatchNorm statistics too")


def add_render_pixels_option(parser) -> None:
    parser.add_argument("--render-pixels", type=positive_int, default=512,
                        help="supervised LiDAR pixels per camera and step")
