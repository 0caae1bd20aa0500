"""The timings the docs quote are one measured run's: the README, ``--help`` and
docs/performance.md give the same figure for the same command (grasp.evaluate.config.MEASURED)."""

from pathlib import Path

from grasp.evaluate.cli import build_parser
from grasp.evaluate.config import MEASURED, MEASURED_ON

ROOT = Path(__file__).resolve().parents[1]


def test_readme_help_and_performance_page_quote_the_measured_evaluation_times():
    help_text = " ".join(build_parser().format_help().split())  # argparse wraps lines
    readme = (ROOT / "README.md").read_text()
    performance = (ROOT / "docs" / "performance.md").read_text()
    assert MEASURED_ON in help_text
    for preset, run in MEASURED.items():
        assert run.text in help_text, (preset, run.text)
        row = [line for line in performance.splitlines()
               if line.startswith("|") and f"`{run.command}`" in line]
        assert row and run.text in row[0] and run.when in row[0], (preset, row)
        if preset == "default":  # the quick start's figure
            assert f"{run.text} on 2 cores" in readme
    assert "not measured" in help_text  # --full's figure is an estimate and says so
    assert "(default: default)" not in help_text  # --quick and --full are flags
