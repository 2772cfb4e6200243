"""nuScenes v1.0 tables of the synthetic dataset (schema of nuscenes-devkit) and
deterministic file writers (tokens from hashes, zip entries without wall-clock dates)."""
from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile

import numpy as np

from ..lidarseg import LIDARSEG_CLASSES

TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose",
          "log", "scene", "sample", "sample_data", "sample_annotation", "map", "lidarseg")

ATTRIBUTES = ("vehicle.moving", "vehicle.stopped", "vehicle.parked", "cycle.with_rider", "cycle.without_rider",
              "pedestrian.sitting_lying_down", "pedestrian.standing", "pedestrian.moving")
VISIBILITY = (("1", "v0-40", "visibility of whole object is between 0 and 40%"),
              ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
              ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
              ("4", "v80-100", "visibility of whole object is between 80 and 100%"))


def token(*parts) -> str:
    """32 hex digits, a pure function of ``parts`` (nuScenes tokens look the same)."""
    return hashlib.md5("|".join(str(p) for p in parts).encode()).hexdigest()


def visibility_token(fraction: float) -> str:
    return "1" if fraction < 0.4 else "2" if fraction < 0.6 else "3" if fraction < 0.8 else "4"


class Tables:
    """Accumulates the records of every table; ``write`` dumps them as <root>/<version>/*.json."""

    def __init__(self, seed: int):
        self.seed = seed
        self.records = {name: [] for name in TABLES}
        for index, name in enumerate(LIDARSEG_CLASSES):
            self.records["category"].append({"token": self.category_token(name), "name": name,
                                             "description": f"nuScenes-lidarseg class {name}", "index": index})
        for name in ATTRIBUTES:
            self.records["attribute"].append({"token": self.attribute_token(name), "name": name,
                                              "description": name})
        for tok, level, description in VISIBILITY:
            self.records["visibility"].append({"token": tok, "level": level, "description": description})

    def category_token(self, name):
        return token("category", name)

    def attribute_token(self, name):
        return token("attribute", name)

    def add(self, table, record):
        self.records[table].append(record)
        return record

    def write(self, root, version):
        out = os.path.join(root, version)
        os.makedirs(out, exist_ok=True)
        for name, records in self.records.items():
            with open(os.path.join(out, f"{name}.json"), "w") as f:
                json.dump(records, f, indent=1)


def link_chain(records: list[dict]):
    """Set prev/next of records already in time order."""
    for a, b in zip(records[:-1], records[1:]):
        a["next"], b["prev"] = b["token"], a["token"]


def save_npz(path, **arrays):
    """np.savez_compressed with fixed zip dates, so equal arrays give equal bytes."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
