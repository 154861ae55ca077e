"""The CLI lists the contract's commands and maps bad usage to exit status 2."""
import subprocess
import sys

from planner.cli import COMMANDS, main


def test_help_lists_every_contract_command():
    out = subprocess.run([sys.executable, "-m", "planner.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for name in ["demo", "register", "predict", "compare", "diagnose", "synth", "calibrate"]:
        assert name in out.stdout
        assert name in COMMANDS


def test_no_command_is_exit_2(capsys):
    assert main([]) == 2
