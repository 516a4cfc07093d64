"""Every command's default output fits a 100-column terminal."""

from __future__ import annotations

import pytest

pytest.importorskip("harness.evaluation")

from report_fixtures import synthetic_store  # noqa: E402

WIDTH = 100


def _fits(text: str) -> None:
    long = [line for line in text.splitlines() if len(line) > WIDTH]
    assert not long, f"{len(long)} line(s) wider than {WIDTH}: {long[0]!r}"


@pytest.fixture(scope="module")
def wide_store(tmp_path_factory):
    return synthetic_store(
        tmp_path_factory.mktemp("wide"),
        folds=("P1", "P2", "P3", "P4+P5"),
        per_fold=4,
        detectors={"a-rather-long-detector-name": "strong", "beta": "weak"},
        encodings={"beta": ["ir8", "none"]},
        profiles={"a-rather-long-detector-name": (3_210_000, 8.2), "beta": (1_100_000, 2.5)},
    )


def test_store_commands_fit_100_columns(wide_store, tmp_path, cli_runner):
    root = str(wide_store.root)
    commands = [
        ["report", "--print", "--store", root, "--resamples", "0"],
        [
            "compare-detectors",
            "a-rather-long-detector-name",
            "beta/c2",
            "--dataset",
            "synth",
            "--store",
            root,
            "--resamples",
            "10",
        ],
        ["compare", "--datasets", "synth", "--store", root, "--allow-mismatched"],
        ["report", "--store", root, "--out", str(tmp_path / "rep"), "--resamples", "0"],
    ]
    for args in commands:
        res = cli_runner(args, env={"COLUMNS": str(WIDTH)})
        assert res.exit_code == 0, (args, res.output)
        _fits(res.stdout)


def test_listing_and_profile_fit_100_columns(host, cli_runner):
    from engine_helpers import tinydet_module
    from harness.testing import temporary_plugin

    tinydet_module()
    import harness_tinydet.plugin as tinydet_plugin

    with temporary_plugin(tinydet_plugin, name="tinydet-width"):
        for args in (
            ["list"],
            [
                "profile",
                "--detector",
                "tinydet,tinydet-dual",
                "--imgsz",
                "64",
                "--runs",
                "2",
                "--warmup",
                "1",
                "--no-onnx",
                "--no-store",
            ],
        ):
            res = cli_runner(args, env={"COLUMNS": str(WIDTH)})
            assert res.exit_code == 0, (args, res.output)
            _fits(res.stdout)


def test_text_tables_split_into_panels_that_keep_the_row_names():
    from harness.textable import text_table

    header = ["name", *[f"column {i}" for i in range(20)]]
    rows = [["alpha", *[f"{i}.000" for i in range(20)]], ["beta", *["-"] * 20]]
    text = text_table(header, rows)
    _fits(text)
    panels = text.split("\n\n")
    assert len(panels) > 1 and all(p.splitlines()[0].startswith("name") for p in panels)
    assert sum(p.splitlines()[0].count("column") for p in panels) == 20
    assert text_table(header, rows, width=None).count("\n") == 3  # one table when asked


def _help_pages():
    """Every command's ``--help`` argv, sub-commands of groups included."""
    import click

    from harness.cli import get_cli

    def walk(cmd, path):
        yield path + ["--help"]
        if isinstance(cmd, click.Group):
            ctx = click.Context(cmd)
            for name in cmd.list_commands(ctx):
                yield from walk(cmd.get_command(ctx, name), path + [name])

    return list(walk(get_cli(), []))


@pytest.mark.parametrize("columns", [100, 250])
def test_every_help_page_fits_100_columns(host, cli_runner, columns):
    """Wide terminal or not: click wraps help text to at most 100 columns, and the unwrapped blocks (examples) fit."""
    pages = _help_pages()
    assert len(pages) > 25
    for args in pages:
        res = cli_runner(args, env={"COLUMNS": str(columns)})
        assert res.exit_code == 0, (args, res.output)
        long = [line for line in res.output.splitlines() if len(line) > WIDTH]
        assert not long, f"harness {' '.join(args)}: {len(long)} line(s) wider than {WIDTH}: {long[0]!r}"
