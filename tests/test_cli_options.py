"""The CLI's option registry: each option declared once, mapped to a real field of the
library's values, and library hints said as flags in one place."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click
from click.testing import CliRunner

from standgrid.cli import cli
from standgrid.cli.options import CLUSTER, COMPARE, ENRICH, REGISTRY, TILE, say_flags
from standgrid.comparison.options import CompareOptions
from standgrid.engine.execution import Execution
from standgrid.enrichment.options import EnrichOptions
from standgrid.tiling.options import TileOptions

CLASSES = {c.__name__: c for c in (TileOptions, EnrichOptions, CompareOptions, Execution)}


def test_every_option_sets_a_field_of_a_library_value() -> None:
    for option in REGISTRY.values():
        assert option.fields, option.name
        for target in option.fields:
            cls, _, name = target.partition(".")
            assert name in {f.name for f in dataclasses.fields(CLASSES[cls])}, target


def test_run_offers_the_options_of_every_stage_with_the_same_help() -> None:
    helps = {}
    for name in ("tile", "enrich", "compare", "run"):
        command = cli.get_command(click.Context(cli), name)
        assert command is not None
        helps[name] = {p.name: getattr(p, "help", None) for p in command.params}
    for stage, names in (("tile", TILE), ("enrich", ENRICH), ("compare", COMPARE)):
        for name in names:
            assert helps[stage][name] == REGISTRY[name].attrs["help"]
            if name != "epochs":  # run enriches every epoch it tiled: its --epoch is tiling's
                assert helps["run"][name] == helps[stage][name], name
    assert set(CLUSTER) <= set(helps["run"]) and set(CLUSTER) <= set(helps["tile"])


def test_library_hints_become_flags_in_the_cli_only() -> None:
    assert say_flags("wait longer with option lock_timeout") == "wait longer with --lock-timeout"
    assert say_flags("give option anchor") == "give --anchor LAT LON ALT YAW"
    assert say_flags("option anchor: one mission") == "--anchor: one mission"
    assert say_flags("option epoch_from and option epoch_to") == "--from and --to"
    assert say_flags("an option nobody has") == "an option nobody has"


def test_an_option_out_of_range_is_a_usage_error_naming_the_flag(tmp_path: Path) -> None:
    runner = CliRunner()
    bad = runner.invoke(cli, ["tile", str(tmp_path), "-o", str(tmp_path / "c"), "--epoch", "a/b"])
    assert bad.exit_code == 2 and "OptionError: --epoch: 'a/b'" in bad.output
    bad = runner.invoke(cli, ["enrich", str(tmp_path), "--workers", "0"])
    assert bad.exit_code == 2 and "--workers: 0" in bad.output and "option " not in bad.output
    bad = runner.invoke(cli, ["run", str(tmp_path), "-o", str(tmp_path / "c"), "--pixel", "0"])
    assert bad.exit_code == 2 and "--pixel: 0.0" in bad.output
    assert not (tmp_path / "c").exists()  # refused before any work
