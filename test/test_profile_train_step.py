"""tools/profile_train_step.py: host reads are counted where odg_ros asks for them, the tensor
methods are restored afterwards, and a whole profiled step reports its counts."""
import importlib.util
import json
from pathlib import Path

import torch

from helpers import tiny_config, write_tiny_split

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("profile_train_step",
                                              ROOT / "tools/profile_train_step.py")
tool = importlib.util.module_from_spec(spec)
spec.loader.exec_module(tool)


def test_host_reads_are_counted_on_the_device_and_methods_restored():
    originals = {name: getattr(torch.Tensor, name) for name in tool.HOST_READS}
    x = torch.ones(3)
    with tool.HostReadCounter("cpu") as reads:
        bool(x.all()), float(x.sum()), x.tolist()
    with tool.HostReadCounter("cuda") as reads_elsewhere:
        x.sum().item()
    assert sum(reads.sites.values()) == 3 and not reads_elsewhere.sites
    assert {site.split()[0] for site in reads.sites} == {"__bool__", "__float__", "tolist"}
    assert all(getattr(torch.Tensor, name) is f for name, f in originals.items())


def test_a_profiled_step_reports_calls_and_reads(tmp_path, capsys):
    split = write_tiny_split(tmp_path / "split", 2)
    preset = tmp_path / "tiny.yaml"
    preset.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v     # JSON is YAML
                                  for k, v in tiny_config(num_frames=2).to_dict().items()}))
    assert tool.main(["--preset", str(preset), "--data", str(split),
                      "--steps", "1", "--top", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "ATen calls/step" in lines[0] and "host reads/step" in lines[0]
    assert len(lines) == 4 and all(line.split()[0].isdigit() for line in lines[1:])
