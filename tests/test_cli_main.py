"""The CLI group: every registered command loads, --help is instant (no heavy imports)."""

from __future__ import annotations

import subprocess
import sys

from click.testing import CliRunner

from standgrid.cli import COMMANDS, LazyGroup, cli

HEAVY = ("numpy", "scipy", "pandas", "geopandas", "laspy", "rasterio", "pyproj", "shapely")


def test_every_registered_command_exists() -> None:
    missing = [name for name in COMMANDS if LazyGroup._load(name) is None]
    assert missing == []


def test_group_help_lists_every_command() -> None:
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    for name in COMMANDS:
        assert name in result.output


def test_every_command_help_has_an_example() -> None:
    runner = CliRunner()
    for name in COMMANDS:
        result = runner.invoke(cli, [name, "--help"])
        assert result.exit_code == 0, (name, result.output)
        assert "Example" in result.output, name


def test_help_imports_no_heavy_library() -> None:
    code = (
        "import sys; import standgrid.cli as c\n"
        "[c.LazyGroup._load(n) for n in c.COMMANDS]\n"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == ""


def test_library_errors_become_one_line_messages(tmp_path) -> None:
    result = CliRunner().invoke(cli, ["info", str(tmp_path)])
    assert result.exit_code == 1
    assert result.output.startswith("Error: MissionNotFoundError: ")
    assert "Traceback" not in result.output
