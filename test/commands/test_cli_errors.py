"""Every user mistake with `odg` is one line, `odg CMD: error: ...`, and exit code 2, with no
traceback (in-process main(argv) calls: fast). --debug shows the traceback instead."""
from __future__ import annotations

import pickle

import pytest
import torch

from odg_ros.commands import SUBCOMMANDS, build_parser, main


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_errors")
    infos = {"version": "v1.0-trainval", "dataset": "nuscenes", "dataroot": str(root),
             "infos": [{"token": "k0"}]}
    paths = {"root": root, "infos": root / "infos.pkl", "no_keyframes": root / "none.pkl",
             "empty": root / "empty.pkl", "truncated": root / "truncated.pt",
             "foreign": root / "foreign.pt", "missing": root / "missing.pt"}
    paths["infos"].write_bytes(pickle.dumps(infos))
    paths["no_keyframes"].write_bytes(pickle.dumps({**infos, "infos": []}))
    paths["empty"].write_bytes(b"")
    torch.save({"model": {"w": torch.zeros(3)}, "config": {}}, paths["truncated"])
    paths["truncated"].write_bytes(paths["truncated"].read_bytes()[:100])
    torch.save({"weights": [1, 2]}, paths["foreign"])
    (root / "world" / "v1.0-trainval").mkdir(parents=True)
    (root / "world" / "v1.0-trainval" / "scene.json").write_text("[]")
    return {k: str(v) for k, v in paths.items()}


# valid invocations, so that each case below adds only its mistake
EVAL = "eval --checkpoint {truncated} --data {infos}"
TRAIN = "train --data {infos} --out {root}/run"
PREPARE = "prepare --dataroot {root}/world --out {root}/i.pkl"

CASES = {   # name: (argv with {placeholders} from `files`, what the line must say)
    "eval: missing checkpoint": ("eval --checkpoint {missing} --data {infos}",
                                 "argument --checkpoint: file not found"),
    "eval: missing infos": ("eval --checkpoint {truncated} --data {root}/nope.pkl",
                            "argument --data: file not found"),
    "eval: truncated checkpoint": (EVAL, "not a readable checkpoint file"),
    "eval: not a checkpoint": ("eval --checkpoint {foreign} --data {infos}",
                               "not an odg_ros checkpoint"),
    "eval: empty infos file": ("eval --checkpoint {truncated} --data {empty}", "file is empty"),
    "eval: infos without keyframes": ("eval --checkpoint {truncated} --data {no_keyframes}",
                                      "holds no keyframes"),
    "eval: not an infos file": ("eval --checkpoint {truncated} --data {foreign}",
                                "is not an infos file"),
    "eval --limit -1": (f"{EVAL} --limit -1", "argument --limit: must be > 0, got -1"),
    "eval --device bogus": (f"{EVAL} --device gpu", "expected auto, cpu, cuda or cuda:N"),
    "train: unknown preset": (f"{TRAIN} --preset odg_x", "unknown preset 'odg_x': one of "
                              "odg_cpu, odg_l, odg_t, odg_waymo_cpu, odg_waymo_t"),
    "train --set nonsense=1": (f"{TRAIN} --set nonsense=1", "--set nonsense: not a model setting"),
    "train --set typo": (f"{TRAIN} --set num_frame=2", "did you mean num_frames"),
    "train --set without =": (f"{TRAIN} --set nonsense", "--set expects KEY=VALUE"),
    "train --epochs x": (f"{TRAIN} --epochs x", "expected an integer, got 'x'"),
    "bench: unknown preset": ("bench --preset odg_xl", "unknown preset"),
    "bench --sweep without --data": ("bench --sweep --preset odg_t",
                                     "--sweep needs --data INFOS"),
    "bench --compile: unknown mode": ("bench --compile eager,warp",
                                      "--compile: unknown mode(s) ['warp']"),
    "bench --compile graphs on a CPU": ("bench --compile graphs",
                                        "CUDA graphs need --device cuda"),
    "bench --precision: unknown": ("bench --precision fp32,fp8", "--precision 'fp32,fp8'"),
    "bench: a checkpoint and a preset": ("bench --checkpoint {foreign} --preset odg_t",
                                         "--checkpoint and --preset: give one"),
    "info: unknown preset": ("info --preset big", "unknown preset 'big'"),
    "synth into an existing world": ("synth --out {root}/world --scenes 1", "already exists"),
    "prepare: missing dataroot": ("prepare --dataroot {root}/nope --out {root}/i.pkl",
                                  "directory not found"),
    "prepare: wrong version": (f"{PREPARE} --version v1.0-mini",
                               "has no v1.0-mini/ table folder"),
    "prepare waymo: no pose file": (f"{PREPARE} --layout waymo", "cam_infos.pkl not found"),
    "prepare waymo: split": (f"{PREPARE} --layout waymo --split all",
                             "Occ3D-Waymo has train and val"),
    "score: missing infos": ("score --pred {root} --data {root}/nope.pkl",
                             "infos file not found"),
    "export: missing checkpoint": ("export --checkpoint {missing} --out {root}/o.pt",
                                   "file not found"),
    "unknown command": ("nonsense", "unknown command 'nonsense'"),
}
NOT_POSITIVE = (f"{EVAL} --limit 0", f"{TRAIN} --steps 0", f"{TRAIN} --steps -1",
                f"{TRAIN} --batch-size 0", f"{TRAIN} --lr nan", "bench --iters 0",
                "bench --iters -3", "bench --frames 0", "synth --out {root}/w --scenes 0",
                "synth --out {root}/w --seconds 0", "demo --seconds 0", "demo --rate -1")
for argv in NOT_POSITIVE:      # a count, a size or a rate: 0, negatives and NaN refused
    *_, option, value = argv.split()
    CASES[f"{argv.split()[0]} {option} {value}"] = (argv, f"argument {option}: must be > 0")
if not torch.cuda.is_available():
    CASES["--device cuda without CUDA"] = (f"{EVAL} --device cuda", "CUDA is not available here")
    CASES["bench --device cuda without CUDA"] = ("bench --device cuda", "CUDA is not available")


@pytest.mark.parametrize("case", CASES)
def test_a_user_error_is_one_line_and_exit_code_2(case, files, capsys):
    argv, expected = CASES[case]
    argv = argv.format(**files).split()
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "error:" in line]
    command = argv[0] if argv[0] in SUBCOMMANDS else ""
    assert len(lines) == 1 and lines[0].startswith(f"odg {command}: error: ".replace(
        "odg :", "odg:")), err
    assert expected in lines[0], err
    assert "Traceback" not in err


def test_debug_shows_the_traceback(files):
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        main(["eval", "--debug", "--checkpoint", files["truncated"], "--data", files["infos"]])


def test_every_option_says_what_it_does_and_its_default():
    for name in SUBCOMMANDS:
        _, parser = build_parser(name)
        parsers = [parser] + [sub for action in parser._actions
                              if hasattr(action, "_name_parser_map")
                              for sub in action.choices.values()]
        for p in parsers:
            for action in p._actions:
                if not action.option_strings or action.dest == "help":
                    continue
                option = f"odg {name} {action.option_strings[0]}"
                assert action.help, f"{option}: no help"
                flag = action.nargs == 0                # store_true and the like
                text = p._get_formatter()._get_help_string(action)
                assert flag or action.required or "default" in text, f"{option}: no default"
