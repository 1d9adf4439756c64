"""The console scripts: every `python -m ofjax.<tool>` is also the command `ofjax-<tool>`."""

import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
TOOLS = ["synth", "inspect", "associate", "train", "export", "conventional", "eval", "measure",
         "demo"]  # the README's command-line tools


def test_every_tool_has_a_command():
  assert set(SCRIPTS) == {f"ofjax-{tool}" for tool in TOOLS}
  for tool in TOOLS:
    module = "ofjax.associate.__main__" if tool == "associate" else f"ofjax.{tool}"
    assert SCRIPTS[f"ofjax-{tool}"] == f"{module}:main"


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_entry_point_is_the_error_handling_main(name, capsys):
  module, attr = SCRIPTS[name].split(":")
  main = getattr(importlib.import_module(module), attr)
  assert hasattr(main, "__wrapped__")  # ofjax.errors.cli: user errors exit 2 without traceback
  with pytest.raises(SystemExit) as exit_info:
    main(["--help"])
  assert exit_info.value.code == 0
  assert "usage:" in capsys.readouterr().out


def test_installed_command_runs():
  command = Path(sys.executable).parent / "ofjax-export"
  if not command.exists():
    pytest.skip(f"{command} not installed (pip install -e . installs it)")
  done = subprocess.run([str(command), "/nonexistent/run"], capture_output=True, text=True)
  assert done.returncode == 2
  assert done.stderr.startswith("ofjax: error:") and "/nonexistent/run" in done.stderr
  assert "Traceback" not in done.stderr
