"""The node's parameters from their one source, config/odg_node.schema.yaml (ROS-free).

The node declares them from here, validates the values it gets, and prints them for
``odg_node --help``; tools/node_parameters.py writes config/odg.yaml, docs/parameters.md and
the README's summary from the same schema, and a test keeps both current.

The same checks validate ``odg ... --set key=value`` (``model_settings``): every model
setting typed as ModelConfig declares it, with the schema's rule where the node has a
parameter of the same name (the score thresholds).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import yaml

from ..model_config import preset_names
from ..resources import resource_path

SCHEMA = "config/odg_node.schema.yaml"
TYPES = {"bool": bool, "int": int, "float": float, "string": str, "string_array": list,
         "int_array": list, "float_array": list}
_ELEMENTS = {"string_array": (str,), "int_array": (int,), "float_array": (int, float)}
GROUPS = {"inputs": "inputs", "sync": "synchronisation and history", "model": "model",
          "outputs": "outputs"}
_KEYS = {"type", "default", "description", "group", "enum", "minimum", "maximum",
         "exclusive_minimum", "or_fraction"}


@dataclass(frozen=True)
class Parameter:
    name: str
    type: str
    default: object
    description: str
    group: str
    enum: tuple | None = None
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: float | None = None
    # a string parameter that also takes a number 0 < x <= 1 (query_budget: auto | full | 0.6)
    or_fraction: bool = False

    def constraint(self) -> str:
        """The allowed values in a few words ('' when any value of the type is allowed)."""
        if self.enum and self.or_fraction:
            return "one of: " + ", ".join(map(str, self.enum)) + " or a fraction 0 < f <= 1"
        if self.enum:
            return "one of: " + ", ".join(map(str, self.enum))
        if self.minimum is not None and self.maximum is not None:
            return f"{self.minimum:g} to {self.maximum:g}"
        if self.exclusive_minimum is not None:
            return f"> {self.exclusive_minimum:g}"
        if self.minimum is not None:
            return f">= {self.minimum:g}"
        if self.maximum is not None:
            return f"<= {self.maximum:g}"
        return ""

    def check(self, value) -> str | None:
        """Why ``value`` is not allowed, or None."""
        if self.or_fraction and value not in (self.enum or ()):
            return self._check_fraction(value)
        expected = TYPES[self.type]
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            return f"{self.name}={value!r}: expected {self.type}"
        if expected is list and not all(isinstance(v, _ELEMENTS[self.type]) and
                                        not isinstance(v, bool) for v in value):
            return f"{self.name}={value!r}: expected a list of {self.type.split('_')[0]}s"
        if expected is float and math.isnan(value):
            return f"{self.name}=nan: expected a number"
        if self.enum and value not in self.enum:
            return f"{self.name}={value!r}: expected {self.constraint()}"
        too_low = (self.minimum is not None and value < self.minimum) or \
                  (self.exclusive_minimum is not None and value <= self.exclusive_minimum)
        too_high = self.maximum is not None and value > self.maximum
        if too_low or too_high:
            return f"{self.name}={value!r}: expected {self.constraint()}"
        return None

    def _check_fraction(self, value) -> str | None:
        try:
            fraction = float(value) if not isinstance(value, bool) else math.nan
        except (TypeError, ValueError):
            fraction = math.nan
        if not 0.0 < fraction <= 1.0:          # NaN too
            return f"{self.name}={value!r}: expected {self.constraint()}"
        return None


def load_schema(path: str | Path | None = None) -> dict[str, Parameter]:
    """name -> Parameter, in the schema's order. A malformed schema is a ValueError."""
    path = Path(path) if path is not None else resource_path(SCHEMA)
    entries = (yaml.safe_load(Path(path).read_text()) or {}).get("parameters") or {}
    parameters = {}
    for name, entry in entries.items():
        unknown = set(entry) - _KEYS
        if unknown or entry.get("type") not in TYPES or entry.get("group") not in GROUPS \
                or not entry.get("description") or "default" not in entry:
            raise ValueError(f"{path}: parameter {name}: needs type (one of {list(TYPES)}), "
                             f"default, description and group (one of {list(GROUPS)}); "
                             f"unknown keys: {sorted(unknown)}")
        enum = entry.get("enum")
        if enum == "nuscenes_presets":       # the presets of model/*.yaml the node's rig fits
            enum = preset_names("nuscenes")
        enum = tuple(enum) if enum is not None else None
        parameter = Parameter(name=name, type=entry["type"], default=entry["default"],
                              description=" ".join(str(entry["description"]).split()),
                              group=entry["group"], enum=enum, minimum=entry.get("minimum"),
                              maximum=entry.get("maximum"),
                              exclusive_minimum=entry.get("exclusive_minimum"),
                              or_fraction=bool(entry.get("or_fraction", False)))
        problem = parameter.check(parameter.default)
        if problem:
            raise ValueError(f"{path}: the default breaks the parameter's own rule: {problem}")
        parameters[name] = parameter
    return parameters


def validate(values: dict, schema: dict[str, Parameter] | None = None) -> dict:
    """``values`` with every problem (unknown name, wrong type, out of range) in one ValueError;
    names not given take their defaults. Floats given as integers become floats."""
    schema = load_schema() if schema is None else schema
    problems = [f"unknown parameter {name!r}" for name in values if name not in schema]
    problems += [p for name, value in values.items() if name in schema
                 for p in [schema[name].check(value)] if p]
    if problems:
        raise ValueError("; ".join(problems))
    result = {name: parameter.default for name, parameter in schema.items()}
    for name, value in values.items():
        result[name] = float(value) if schema[name].type == "float" else value
    return result


def params_file_parameters(path: str | Path) -> dict:
    """The parameters a ROS params file gives every node (its sections, ``/**`` and named,
    merged in order), without ``use_sim_time`` (rclpy's own, not in the schema)."""
    document = yaml.safe_load(Path(path).read_text()) or {}
    values = {}
    for section in document.values():
        values.update((section or {}).get("ros__parameters") or {})
    values.pop("use_sim_time", None)
    return values


def _yaml_value(value) -> str:
    """A value as one flow-style YAML scalar / list."""
    return yaml.safe_dump(value, default_flow_style=True, width=10_000).strip() \
        .removesuffix("\n...").removesuffix("...").strip()


def help_text(schema: dict[str, Parameter] | None = None) -> str:
    """``odg_node --help``: usage and every parameter with its default and allowed values."""
    schema = load_schema() if schema is None else schema
    lines = ["usage: odg_node [--help] [--ros-args -p NAME:=VALUE ... "
             "--params-file config/odg.yaml]", "",
             "ODG 3D semantic occupancy and moving objects from surround cameras.", "",
             "parameters (read at start-up; the schema is config/odg_node.schema.yaml):"]
    for group, title in GROUPS.items():
        lines.append(f"  {title}:")
        for p in (p for p in schema.values() if p.group == group):
            constraint = f"; {p.constraint()}" if p.constraint() else ""
            lines.append(f"    {p.name} ({p.type}, default {_yaml_value(p.default)}"
                         f"{constraint})")
            lines.append(f"        {p.description}")
    return "\n".join(lines)


def summary_table(schema: dict[str, Parameter] | None = None) -> str:
    """The README's parameter table: every name, one row per group (the details are in
    docs/parameters.md)."""
    schema = load_schema() if schema is None else schema
    rows = ["| group | parameters |", "|---|---|"]
    for group, title in GROUPS.items():
        names = ", ".join(f"`{p.name}`" for p in schema.values() if p.group == group)
        rows.append(f"| {title} | {names} |")
    return "\n".join(rows)


def markdown_table(schema: dict[str, Parameter] | None = None) -> str:
    """docs/parameters.md's table: type, default, allowed values, description."""
    schema = load_schema() if schema is None else schema
    rows = ["| Parameter | Type | Default | Allowed | Description |", "|---|---|---|---|---|"]
    for p in schema.values():
        default = "the six nuScenes cameras" if p.name == "camera_names" \
            else f"`{_yaml_value(p.default)}`"
        rows.append(f"| `{p.name}` | {p.type} | {default} | {p.constraint()} | "
                    f"{p.description.replace('|', '/')} |")
    return "\n".join(rows)


def params_file_text(schema: dict[str, Parameter] | None = None) -> str:
    """config/odg.yaml: every parameter at its default, grouped, with its allowed values."""
    schema = load_schema() if schema is None else schema
    lines = ["# Parameters of odg_node at their defaults, written from config/odg_node.schema.yaml",
             "# by tools/node_parameters.py --write (edit the schema, not this file; copy this",
             "# file to change values). `/**:` applies them whatever the node's name and",
             "# namespace: odg_node --ros-args --params-file config/odg.yaml",
             "/**:", "  ros__parameters:"]
    for group, title in GROUPS.items():
        lines.append(f"    # --- {title}")
        for p in (p for p in schema.values() if p.group == group):
            line = f"    {p.name}: {_yaml_value(p.default)}"
            if p.constraint():
                line = f"{line:<44}# {p.constraint()}"
            lines.append(line)
    return "\n".join(lines) + "\n"


def closest_name(name: str, known) -> str:
    """'; did you mean X?' for the known name closest to ``name`` ('' when none is close)."""
    import difflib
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


def unknown_parameters_text(names, schema: dict[str, Parameter]) -> str:
    """'unknown parameter(s) ...' naming each of ``names`` with the closest schema name
    ('' when there are none)."""
    names = sorted(names)
    if not names:
        return ""
    return "unknown parameter" + "s" * (len(names) > 1) + " " + ", ".join(
        f"{name!r}{closest_name(name, schema)}" for name in names)


def model_settings(schema: dict[str, Parameter] | None = None) -> dict[str, Parameter]:
    """The rules of ``--set``: one per ModelConfig field, typed from its annotation, the
    schema's rule where the node has the same parameter (its range, its meaning: a negative
    score threshold keeps the checkpoint's own)."""
    import dataclasses

    from ..model_config import ModelConfig
    schema = load_schema() if schema is None else schema
    kinds = {"str": "string", "bool": "bool", "int": "int", "float": "float",
             "tuple[int, int]": "int_array", "tuple[int, ...]": "int_array",
             "tuple[float, ...]": "float_array"}
    rules = {}
    for f in dataclasses.fields(ModelConfig):
        if f.name not in schema and str(f.type) not in kinds:
            continue                   # no text form (the calibration: odg export fits it)
        if f.name in schema:
            rules[f.name] = schema[f.name]
        else:
            rules[f.name] = Parameter(name=f.name, type=kinds[str(f.type)],
                                      default=f.default, description="", group="model")
    return rules


def parse_settings(items, rules: dict[str, Parameter] | None = None) -> dict:
    """``key=value`` texts (YAML values, as a params file holds them) -> {key: value}, each
    checked against its rule. Every problem raises one ValueError line: not KEY=VALUE, an
    unknown key (with the closest known one), a wrong type (``flase`` is no bool), a value
    out of range."""
    rules = model_settings() if rules is None else rules
    out = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        if key not in rules:
            raise ValueError(f"--set {key}: not a model setting{closest_name(key, rules)}")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ValueError(f"--set {item}: the value is not valid YAML") from None
        problem = rules[key].check(value)
        if problem:
            raise ValueError(f"--set {problem}")
        out[key] = float(value) if rules[key].type == "float" else value
    return out