"""Model configuration: one dataclass, presets are plain YAML files in ``model/``."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import yaml

from .classes import OccLabels, occ_labels
from .resources import resource_path


def preset_names(dataset: str | None = None) -> tuple[str, ...]:
    """The presets shipped in ``model/*.yaml`` (of one dataset's label set when given)."""
    names = []
    for path in sorted(resource_path("model").glob("*.yaml")):
        values = yaml.safe_load(path.read_text()) or {}
        if dataset is None or values.get("dataset", "nuscenes") == dataset:
            names.append(path.stem)
    return tuple(names)


PRESET_NAMES = preset_names()


# what a calibration holds (network/calibration.py applies it; odg export --calibrate fits
# it): the rates of the hazard, by name: (how many: per class "C" or "C+1" with free, what for)
HAZARD_RATES = {
    "hazard_inside": ("C+1", "class in the column, voxel between its lowest and highest"),
    "hazard_above_low": ("C+1", "class in the column, voxel up to 1.6 m above its highest"),
    "hazard_above_high": ("C+1", "class in the column, voxel higher"),
    "hazard_near_body": ("C", "class in the 3 x 3 columns around, voxel at body height"),
    "hazard_near_other": ("C", "class in the 3 x 3 columns around, voxel at another height"),
    "hazard_ring_body": ("C", "class in the ring of 16 columns around those, body height"),
}


def rate_lengths(num_classes: int) -> dict[str, int]:
    return {key: num_classes + (size == "C+1") for key, (size, _) in HAZARD_RATES.items()}


def check_calibration(values: dict, num_classes: int) -> None:
    """A clear error for a calibration dict that does not fit a model of ``num_classes``."""
    lengths = {"label_scale": num_classes, "label_bias": num_classes,
               **rate_lengths(num_classes)}
    for key, length in lengths.items():
        if len(values.get(key, ())) != length:
            raise ValueError(f"calibration {key}: expected {length} values, got "
                             f"{len(values.get(key, ()))}")
    for key in ("free_scale", "free_bias"):
        if not isinstance(values.get(key), (int, float)):
            raise ValueError(f"calibration {key}: expected a number")
    box = values.get("box")
    if box is not None and (len(box) != 2 or box[0] <= 0):
        raise ValueError("calibration box: expected [scale > 0, bias] or null")
    numbers = [v for key in lengths for v in values[key]] + \
        [values["free_scale"], values["free_bias"]] + list(box or ())
    if not all(math.isfinite(v) for v in numbers):
        raise ValueError("calibration: a value is not finite")
    if min(v for key in HAZARD_RATES for v in values[key]) < 0:
        raise ValueError("calibration: a hazard rate is negative")


@dataclass
class ModelConfig:
    name: str = "odg_t"
    # image encoder
    backbone: str = "resnet50"          # resnet18 | resnet34 | resnet50
    frozen_stages: int = 1               # stem + layer1 frozen, as OPUS/SparseBEV (-1: none)
    norm_eval: bool = True               # BN statistics fixed (pretrained); False trains them
    fpn_channels: int = 256
    num_levels: int = 4                  # FPN outputs at strides 4, 8, 16, 32
    # input
    num_cams: int = 6
    image_size: tuple[int, int] = (256, 704)  # network input H, W
    num_frames: int = 8                  # current + 7 history frames
    # decoder
    embed_dims: int = 256
    num_layers: int = 6
    num_heads: int = 8
    ffn_dims: int = 512
    num_static: int = 500                # S
    num_dynamic: int = 100               # D
    points_per_layer: tuple[int, ...] = (1, 4, 16, 32, 64, 128)  # K_l
    num_groups: int = 4
    sampling_points: int = 4             # per group per frame
    mixing_out_points: int = 32          # AdaMixer output points (OPUS: 32)
    # ablation switches (paper Table 4); the shipped presets keep all on
    motion_compensation: bool = True     # velocity warp of dynamic queries
    ego_compensation: bool = True        # ego-pose warp of every query
    das_attention: bool = True           # self-attention over concat(Q_d, Q_s)
    dual_queries: bool = True            # False: one query set (all static, no box head)
    # grid / classes
    pc_range: tuple[float, ...] = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)
    voxel_size: float = 0.4
    dataset: str = "nuscenes"            # label set: nuscenes (0..16, 17 free) | waymo (0..14, 15 free)
    num_classes: int = 17                # classes without free; must match the dataset's label set
    num_box_classes: int = 10
    # post-processing (docs/architecture.md sec. 4)
    score_threshold: float = 0.5
    max_distance_to_centroid: float = 3.0
    occupancy_padding: bool = True       # OPUS's test-time closing of the grid (network/padding)
    box_score_threshold: float = 0.3
    # what the grid's confidence, hazard and box scores mean as probabilities, fitted on training
    # worlds by odg export --calibrate (network/calibration.py); None: raw scores
    calibration: dict | None = None

    def __post_init__(self) -> None:
        self.image_size = tuple(self.image_size)
        self.points_per_layer = tuple(self.points_per_layer)
        self.pc_range = tuple(float(v) for v in self.pc_range)
        if len(self.points_per_layer) != self.num_layers:
            raise ValueError(f"points_per_layer has {len(self.points_per_layer)} entries, "
                             f"num_layers is {self.num_layers}")
        if self.embed_dims % self.num_groups or self.embed_dims % self.num_heads:
            raise ValueError("embed_dims must be divisible by num_groups and num_heads")
        if self.fpn_channels != self.embed_dims:
            raise ValueError("fpn_channels must equal embed_dims: sampled features are mixed "
                             "in the query's channel groups")
        if self.num_classes != occ_labels(self.dataset).num_classes:
            raise ValueError(f"num_classes={self.num_classes} does not match the {self.dataset} "
                             f"label set ({occ_labels(self.dataset).num_classes} classes + free)")
        if self.backbone not in ("resnet18", "resnet34", "resnet50"):
            raise ValueError(f"unknown backbone {self.backbone!r}")
        if self.calibration is not None:
            check_calibration(self.calibration, self.num_classes)

    @property
    def labels(self) -> OccLabels:
        """The occupancy label set: class names, free label, loss weights (classes.py)."""
        return occ_labels(self.dataset)

    @property
    def free_label(self) -> int:
        return self.num_classes

    @property
    def num_queries(self) -> int:
        return self.num_dynamic + self.num_static

    @property
    def dynamic_queries(self) -> int:
        """Dynamic queries the model has: ``num_dynamic``, or 0 for one query set (the
        ablation: every query static, no box head)."""
        return self.num_dynamic if self.dual_queries else 0

    @property
    def static_queries(self) -> int:
        return self.num_queries - self.dynamic_queries

    @property
    def gaussians_per_layer(self) -> list[int]:
        return [self.num_queries * k for k in self.points_per_layer]

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        r = self.pc_range
        return tuple(int(round((r[i + 3] - r[i]) / self.voxel_size)) for i in range(3))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def replace(self, **changes) -> "ModelConfig":
        return dataclasses.replace(self, **changes)


def load_preset(name_or_path: str | Path, **overrides) -> ModelConfig:
    """Load ``model/<name>.yaml`` (or a YAML path); keyword overrides win."""
    path = Path(name_or_path)
    if not path.suffix:
        path = resource_path(f"model/{name_or_path}.yaml")
    with open(path) as f:
        values = yaml.safe_load(f) or {}
    known = {f.name for f in dataclasses.fields(ModelConfig)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"{path}: unknown keys {sorted(unknown)}")
    values.update(overrides)
    return ModelConfig(**values)
