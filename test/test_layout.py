"""The package's layout as docs/architecture.md states it: imports go down the layers, the
tools (bench, demo) are imported only by the commands and the demo session, no two public
functions or classes share a name, no two functions share a body (a copy with other names is
still a copy), no function runs past ~80 lines without saying why, the package never imports
the maintainer scripts (``tools/``) or the test helpers (``testing/``), every benchmark times
the one step the node runs (``OnlinePredictor``), never an assembly of its parts; the package
imports itself relatively, tests share helpers through ``testing/``, never by importing
another test module, and no two modules of the package share a file name (the commands,
named after the ``odg`` subcommand each implements, aside).

Each rule is checked by a function that takes the parsed package, so the tests below also
plant a violation and see each rule catch it."""
from __future__ import annotations

import ast
import copy
from pathlib import Path

import pytest

import odg_ros

PACKAGE = Path(odg_ros.__file__).resolve().parent

# Bottom to top; a module may import from its own subpackage and from the layers below.
# Subpackages within a layer are siblings and import nothing from each other.
LAYERS = (
    ("base",),                                  # the modules at the package root
    ("data", "network", "render", "metrics"),
    ("losses",),
    ("train", "online", "bags"),
    ("bench", "demo"),                          # the tools
    ("ros",),
    ("commands",),
)
TOOLS = ("bench", "demo")
# Above the package: maintainer scripts and test helpers import it, it never imports them.
OUTSIDE_PACKAGE = ("tools", "testing")
TOOL_IMPORTERS = ("odg_ros.commands", "odg_ros.ros.demo_session")
# the interface every command module has, and the two entry points (odg, odg_node)
SHARED_NAMES = {"add_arguments", "run", "main"}
LONGEST_FUNCTION = 80
# Functions of at least this many statements (nested ones counted, the docstring not) may not
# share a body; shorter ones (a lock and a flag, a property) repeat without being copies.
SHORTEST_COPY = 4
# The benchmarks of the online step (odg bench, its sweep, the maintainer scripts that time
# or profile it) run the node's own step: an OnlinePredictor. They import none of the step's
# parts and call none of the model's own forward paths, so no second assembly of the step can
# be timed in its place. A benchmark of one component against plain references says so here.
BENCHMARKS = ("odg_ros.bench", "tools.bench_", "tools.profile_")
COMPONENT_BENCHMARKS = {
    "tools.bench_backbone": "the step's backbone alone, against plain ResNets",
    "odg_ros.bench.budget_accuracy": "accuracy, not speed: one backbone pass a keyframe, "
                                     "decoded under every budget, ranking and bound",
}
STEP_PARTS = {"OnlineStep", "FeatureRing", "folded_for_inference", "voxelise", "pad_occupancy",
              "ranked_boxes", "occupancy_grid", "box_list", "Visibility", "online_inputs"}
MODEL_PATHS = {"decode_ring", "decode_stored", "extract_features"}


def parse_package(root: Path = PACKAGE) -> dict[str, ast.Module]:
    """module name -> its syntax tree, for every module of the package."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = ast.parse(path.read_text(), filename=str(path))
    return modules


def imports_of(name: str, tree: ast.Module, is_package: bool) -> set[str]:
    """The odg_ros modules ``name`` imports, at its top or inside functions."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "odg_ros"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "odg_ros":
                found.add(target)
    return found


SUBPACKAGES = {path.parent.name for path in PACKAGE.glob("*/__init__.py")}


def group(module: str) -> str:
    """The subpackage a module belongs to ('base' for the package root's modules)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in SUBPACKAGES else "base"


def layer_of(module: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if group(module) in layer)


def import_edges(modules: dict[str, ast.Module]) -> set[tuple[str, str]]:
    packages = {name for name in modules if (PACKAGE.parent / name.replace(".", "/")).is_dir()}
    return {(name, target) for name, tree in modules.items()
            for target in imports_of(name, tree, name in packages)}


def layering_violations(edges) -> list[str]:
    problems = []
    for importer, imported in sorted(edges):
        if group(importer) == group(imported):
            continue
        if layer_of(imported) >= layer_of(importer):
            problems.append(f"{importer} imports {imported} (layer {layer_of(imported)} "
                            f"from layer {layer_of(importer)})")
        elif group(imported) in TOOLS and not importer.startswith(TOOL_IMPORTERS):
            problems.append(f"{importer} imports the tool {imported}")
    return problems


def imports_from_outside(modules: dict[str, ast.Module]) -> list[str]:
    """Where a module of the package imports tools/ or testing/ (at its top or in a function)."""
    found = []
    for name, tree in modules.items():
        if not name.startswith("odg_ros"):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                targets = [node.module or ""]
            else:
                continue
            found += [f"{name}:{node.lineno} imports {target}" for target in targets
                      if target.split(".")[0] in OUTSIDE_PACKAGE]
    return found


def shared_public_names(modules: dict[str, ast.Module]) -> dict[str, list[str]]:
    where: dict[str, list[str]] = {}
    for name, tree in modules.items():
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) \
                    and not node.name.startswith("_") and node.name not in SHARED_NAMES:
                where.setdefault(node.name, []).append(name)
    return {n: places for n, places in where.items() if len(places) > 1}


# a command module is named after its ``odg`` subcommand (commands/score.py: odg score), so
# it may share the name of the module that does the work
NAMED_AFTER_COMMANDS = "odg_ros.commands."
MODULE_NAMES_ANYWHERE = {"__init__", "__main__"}


def shared_module_names(module_names) -> dict[str, list[str]]:
    """File name -> the modules of that name, where more than one module has it."""
    where: dict[str, list[str]] = {}
    for name in sorted(module_names):
        path = PACKAGE.parent / (name.replace(".", "/") + ".py")
        base = "__init__" if not path.exists() and (path.with_suffix("") / "__init__.py").exists() \
            else name.rsplit(".", 1)[-1]
        if base not in MODULE_NAMES_ANYWHERE and not name.startswith(NAMED_AFTER_COMMANDS):
            where.setdefault(base, []).append(name)
    return {base: names for base, names in where.items() if len(names) > 1}


def long_functions(modules: dict[str, ast.Module]) -> list[tuple[int, str]]:
    """(lines, where) of every function longer than LONGEST_FUNCTION lines whose docstring
    does not say why it is long ("Long because" / "Long for")."""
    found = []
    for name, tree in modules.items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                reason = "Long because" in (ast.get_docstring(node) or "") \
                    or "Long for" in (ast.get_docstring(node) or "")
                if length > LONGEST_FUNCTION and not reason:
                    found.append((length, f"{name}.{node.name} (line {node.lineno})"))
    return sorted(found, reverse=True)


class _Renamed(ast.NodeTransformer):
    """Every variable and argument renamed by its first appearance (v0, v1, ...), annotations
    dropped: two bodies that differ only in their names come out the same."""

    def __init__(self):
        self.names: dict[str, str] = {}

    def _rename(self, name: str) -> str:
        return self.names.setdefault(name, f"v{len(self.names)}")

    def visit_Name(self, node):
        node.id = self._rename(node.id)
        return node

    def visit_arg(self, node):
        node.arg, node.annotation = self._rename(node.arg), None
        return node


def normalised_body(function) -> tuple[str, int]:
    """(the function's body without its docstring, names renamed, as an AST dump; how many
    statements it has)."""
    function = copy.deepcopy(function)
    body = function.body[1:] if ast.get_docstring(function) is not None else function.body
    renamed = _Renamed()
    renamed.visit(function.args)
    body = [renamed.visit(statement) for statement in body]
    count = sum(isinstance(node, ast.stmt) for statement in body for node in ast.walk(statement))
    return ast.dump(ast.Module(body=body, type_ignores=[])), count


def copied_bodies(modules: dict[str, ast.Module]) -> list[list[str]]:
    """Groups of functions (SHORTEST_COPY statements or more) with one normalised body."""
    where: dict[str, list[str]] = {}
    for name, tree in modules.items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                body, statements = normalised_body(node)
                if statements >= SHORTEST_COPY:
                    where.setdefault(body, []).append(f"{name}.{node.name} (line {node.lineno})")
    return [places for places in where.values() if len(places) > 1]


def _last_name(node) -> str:
    """``x`` of ``x``, ``a.x``, ``a.b.x`` (else '')."""
    return node.id if isinstance(node, ast.Name) else \
        node.attr if isinstance(node, ast.Attribute) else ""


def step_assemblies(modules: dict[str, ast.Module]) -> list[str]:
    """Where a benchmark (BENCHMARKS, less COMPONENT_BENCHMARKS) imports a part of the step
    (STEP_PARTS) or runs the model itself: ``model(...)``, ``model.decode(...)`` or one of
    MODEL_PATHS on anything."""
    found = []
    for name, tree in modules.items():
        if not name.startswith(BENCHMARKS) or name in COMPONENT_BENCHMARKS:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                found += [f"{name}:{node.lineno} imports {a.name}" for a in node.names
                          if a.name in STEP_PARTS]
            elif isinstance(node, ast.Call):
                call, receiver = node.func, getattr(node.func, "value", None)
                if _last_name(call) == "model" or _last_name(call) in MODEL_PATHS or (
                        _last_name(call) == "decode" and _last_name(receiver) == "model"):
                    found.append(f"{name}:{node.lineno} calls {ast.unparse(call)}")
    return found


@pytest.fixture(scope="module")
def modules():
    return parse_package()


def test_every_subpackage_has_a_layer():
    assert SUBPACKAGES | {"base"} == {name for layer in LAYERS for name in layer}


def test_imports_go_down_the_layers(modules):
    assert layering_violations(import_edges(modules)) == []


def test_an_upward_import_or_a_library_import_of_a_tool_is_caught():
    planted = {("odg_ros.network.decoder", "odg_ros.online.step"),      # up
               ("odg_ros.train.trainer", "odg_ros.losses.criterion"),   # down: fine
               ("odg_ros.data.dataset", "odg_ros.metrics.score"),       # sibling
               ("odg_ros.ros.node", "odg_ros.bench.step_timing"),              # a tool, not from the
               ("odg_ros.geometry", "odg_ros.network.odg")}             # demo session; base up
    problems = layering_violations(planted)
    assert len(problems) == 4 and not any("train.trainer" in p for p in problems), problems


def test_the_package_never_imports_the_scripts_or_the_test_helpers(modules):
    assert imports_from_outside({**modules, **parse_tools()}) == []
    planted = {"odg_ros.train.extra": ast.parse(
        "import tools.revision\nfrom testing.helpers import tiny_config\n"
        "def f():\n    from tools import eval_budget\n"),
        "tools.extra": ast.parse("from odg_ros.bench.budget_cost import summary\n"
                                 "from tools.revision import module_at\n")}   # fine
    assert [p.split(" ", 1)[1] for p in imports_from_outside(planted)] == [
        "imports tools.revision", "imports testing.helpers", "imports tools"]


def test_no_two_public_functions_or_classes_share_a_name(modules):
    assert shared_public_names(modules) == {}
    planted = dict(modules, **{"odg_ros.extra": ast.parse("def build_world():\n    pass\n"),
                               "odg_ros.other": ast.parse("def build_world():\n    pass\n")})
    assert list(shared_public_names(planted)) == ["build_world"]


def test_no_two_modules_share_a_file_name(modules):
    assert shared_module_names(modules) == {}
    planted = list(modules) + ["odg_ros.online.rig", "odg_ros.synth_extra.rig",
                               "odg_ros.commands.soak_extra", "odg_ros.bench.soak_extra"]
    assert shared_module_names(planted) == {"rig": ["odg_ros.online.rig",
                                                    "odg_ros.synth_extra.rig"]}


def test_no_function_is_long_without_saying_why(modules):
    assert long_functions(modules) == []
    body = "\n".join(f"    x{i} = {i}" for i in range(LONGEST_FUNCTION))
    planted = {"odg_ros.extra": ast.parse(f"def long():\n{body}\n")}
    assert len(long_functions(planted)) == 1
    planted = {"odg_ros.extra": ast.parse(f'def long():\n    """Long because."""\n{body}\n')}
    assert long_functions(planted) == []


def test_no_two_functions_share_a_body(modules):
    assert copied_bodies({**modules, **parse_tools()}) == []
    original = ast.get_source_segment(
        (PACKAGE / "rotation.py").read_text(),
        next(node for node in modules["odg_ros.rotation"].body
             if getattr(node, "name", "") == "normalise_quaternions"))
    copied = original.replace("rotations", "q").replace("def normalise_quaternions", "def unit").replace("largest", "biggest").replace(": torch.Tensor", "")
    copied = copied.replace('"""[..., 4]', '"""A copy with other names: [..., 4]')
    planted = {**modules, "odg_ros.render.extra": ast.parse(copied)}
    assert [[place.split(" ")[0] for place in group] for group in copied_bodies(planted)] == [
        ["odg_ros.rotation.normalise_quaternions", "odg_ros.render.extra.unit"]]
    short = "def close(self):\n    with self._lock:\n        self._closed = True\n"
    assert copied_bodies({"odg_ros.a": ast.parse(short), "odg_ros.b": ast.parse(short)}) == []


def parse_tools() -> dict[str, ast.Module]:
    """tools.NAME -> its syntax tree, for the maintainer scripts."""
    return {f"tools.{path.stem}": ast.parse(path.read_text(), filename=str(path))
            for path in sorted((PACKAGE.parent / "tools").glob("*.py"))}


def test_every_benchmark_times_the_nodes_own_step(modules):
    benchmarks = {**modules, **parse_tools()}
    assert {n for n in benchmarks if n.startswith(BENCHMARKS)} >= {
        "odg_ros.bench.step_timing", "odg_ros.bench.sweep", "odg_ros.bench.budget_cost"}
    assert step_assemblies(benchmarks) == []
    assert set(COMPONENT_BENCHMARKS) <= set(benchmarks)
    planted = {"odg_ros.bench.fast": ast.parse(
        "from odg_ros.network.feature_ring import FeatureRing\n"
        "def step(model, ring, images, *geometry):\n"
        "    ring.push(model.extract_features(images))\n"
        "    return model.decode_ring(ring, *geometry)\n"),
        "tools.bench_decoder": ast.parse(
        "def run(self, frames, *geometry):\n"
        "    self.model.decode(frames, *geometry)\n    return self.model(frames, *geometry)\n"),
        "tools.bench_jpeg": ast.parse("def run(jpeg, data):\n    return jpeg.decode(data)\n"),
        "odg_ros.online.step": ast.parse("def f(model, x):\n    return model(x)\n")}
    assert sorted(p.split(" ", 1)[1] for p in step_assemblies(planted)) == [
        "calls model.decode_ring", "calls model.extract_features", "calls self.model",
        "calls self.model.decode", "imports FeatureRing"]


def imports_where(trees: dict[str, ast.Module], wrong) -> list[str]:
    """``where:line imports target`` for every import whose target (``a.b``, or ``..a`` for a
    relative one) makes ``wrong(target)`` true."""
    found = []
    for name, tree in trees.items():
        for node in ast.walk(tree):
            targets = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                ["." * node.level + (node.module or "")] if isinstance(node, ast.ImportFrom) \
                else []
            found += [f"{name}:{node.lineno} imports {t}" for t in targets if wrong(t)]
    return found


def absolute_self_imports(modules: dict[str, ast.Module]) -> list[str]:
    """Where a module of the package imports the package by its name (``from odg_ros.x import``,
    ``import odg_ros.x``): inside it, imports are relative, one style throughout."""
    return imports_where(modules, lambda target: target.split(".")[0] == "odg_ros")


def assert_import_rule(find, files: dict[str, ast.Module], planted: dict[str, str],
                       expected: list[str]) -> None:
    """``find`` (an imports_where rule) finds nothing in ``files``, and exactly ``expected``
    in the ``planted`` sources: the rule holds, and it can fail."""
    assert find(files) == []
    assert find({name: ast.parse(source) for name, source in planted.items()}) == expected


def test_the_package_imports_itself_relatively(modules):
    assert_import_rule(absolute_self_imports, modules, {"odg_ros.online.extra": (
        "from odg_ros.geometry import make_transform\nimport odg_ros.classes\n"
        "from odg_ros_msgs.msg import SemanticVoxelGrid\nfrom ..geometry import ego_warp\n"
        "def f():\n    from odg_ros.network import ODG\n")}, [
        "odg_ros.online.extra:1 imports odg_ros.geometry",
        "odg_ros.online.extra:2 imports odg_ros.classes",
        "odg_ros.online.extra:6 imports odg_ros.network"])


TESTS = PACKAGE.parent / "test"


def sibling_test_imports(tests: dict[str, ast.Module]) -> list[str]:
    """Where a test imports another test module (``test_*``, ``conftest``) instead of the
    shared helpers in ``testing/``: a test module is collected, not imported."""
    return imports_where(tests, lambda target: target.startswith(".")
                         or target.split(".")[0] in ("test", "conftest")
                         or target.split(".")[-1].startswith("test_"))


def test_tests_share_helpers_through_testing_only():
    tests = {str(path.relative_to(TESTS)): ast.parse(path.read_text(), filename=str(path))
             for path in sorted(TESTS.rglob("*.py"))}
    assert_import_rule(sibling_test_imports, tests, {"ros/test_a.py": (
        "from test_node import Harness\nimport test.online.test_step\n"
        "from .test_b import helper\nfrom testing.online import make_sets\n"
        "from odg_ros.online.step import OnlineStep\n")}, [
        "ros/test_a.py:1 imports test_node", "ros/test_a.py:2 imports test.online.test_step",
        "ros/test_a.py:3 imports .test_b"])
