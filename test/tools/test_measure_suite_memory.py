"""tools/measure_suite_memory.py: the peak memory of a command counts the processes it starts."""
import sys

from tools.measure_suite_memory import measure


def test_the_peak_counts_a_grandchild_and_the_exit_code_comes_back():
    grandchild = "import time; b = b'x' * (300 << 20); time.sleep(2)"
    child = (f"import subprocess, sys; sys.exit(subprocess.run([sys.executable, '-c', "
             f"{grandchild!r}]).returncode + 3)")
    result = measure([sys.executable, "-c", child], every=0.1)
    assert result["exit_code"] == 3 and result["stopped"] is None
    assert 0.28 < result["pss_gib"] < 1.0 and result["rss_gib"] >= result["pss_gib"] - 0.05
    assert result["processes_at_pss_peak"] == 2
    assert any("b'x'" in line for line in result["top_at_pss_peak"])
