"""One CLI vocabulary: shared options declared once, help on every option, the old spellings for one release, one
store rule, the exit-code table and one progress helper."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import click
import pytest

from harness.commands import options as opt
from harness.errors import HarnessError

REPO = Path(__file__).resolve().parent.parent
WIDTH = 100
#: The vocabulary's options and their shared names.
VOCABULARY = {
    "--folds": "folds",
    "--seeds": "seeds",
    "--bootstrap-seed": "bootstrap-seed",
    "--format": "format",
    "--store": "store",
    "--no-progress": "no-progress",
    "--config": "config",
    "--set": "set",
}
#: Spellings the vocabulary retired; `synth --seed` is the generator's seed, not a training or bootstrap seed.
RETIRED = {"--fold", "--json", "--seed"}
#: `synth --seed` is the generator's seed, not a training seed.
OWN_MEANING = {("synth", "--seed")}
#: Commands that show progress (bars, or run/sweep's progress lines).
SHOWS_PROGRESS = {
    "run",
    "ablate",
    "sweep",
    "pretrain",
    "profile",
    "report",
    "compare-detectors",
    "prepare",
    "folds",
    "score",
    "synth",
    "sensing decode",
    "sensing displacement",
    "show",
    "screen",
    "benchmark run",
    "benchmark rerun",
}
#: Commands about one profile: their --profile defaults to it (the store rule, results/<profile>, is the same).
OWN_PROFILE = {"benchmark run": "benchmark", "benchmark export": "benchmark"}


def _walk(groups: bool = False) -> list[tuple[list[str], click.Command]]:
    from harness.cli import get_cli

    out: list[tuple[list[str], click.Command]] = []

    def walk(cmd: click.Command, path: list[str]) -> None:
        if isinstance(cmd, click.Group):
            if groups:
                out.append((path, cmd))
            ctx = click.Context(cmd)
            for name in cmd.list_commands(ctx):
                walk(cmd.get_command(ctx, name), path + [name])  # type: ignore[arg-type]
        else:
            out.append((path, cmd))

    walk(get_cli(), [])
    return out


@pytest.fixture
def extra_command():
    """Add throwaway commands to the CLI for one test: ``extra_command(click_command)``."""
    from harness.cli import get_cli

    cli = get_cli()
    added: list[str] = []

    def add(cmd: click.Command) -> None:
        cli.add_command(cmd)
        added.append(cmd.name)  # type: ignore[arg-type]

    yield add
    for name in added:
        cli.commands.pop(name, None)


# ------------------------------------------------------------------------------------------------ help
def test_every_command_and_option_has_help_and_every_page_fits_100_columns(host, cli_runner):
    pages = _walk(groups=True)
    assert len(pages) > 25
    for path, cmd in pages:
        name = " ".join(["harness", *path])
        assert (cmd.help or "").strip(), f"{name}: no help text"
        missing = [p.opts[0] for p in cmd.params if isinstance(p, click.Option) and not (p.help or "").strip()]
        assert not missing, f"{name}: options without help: {missing}"
        res = cli_runner([*path, "--help"], env={"COLUMNS": "250"})
        assert res.exit_code == 0, (name, res.output)
        long = [line for line in res.output.splitlines() if len(line) > WIDTH]
        assert not long, f"{name} --help: {len(long)} line(s) wider than {WIDTH}: {long[0]!r}"


def test_shared_options_come_from_the_one_declaration(host):
    for path, cmd in _walk():
        name = " ".join(path)
        opts = {o: p for p in cmd.params for o in p.opts}
        for o, p in opts.items():
            if (path[0], o) in OWN_MEANING:
                continue
            assert o not in RETIRED, f"harness {name}: {o} is a retired spelling"
            if o in VOCABULARY or o == "--profile":
                assert isinstance(p, opt.SharedOption), f"harness {name}: {o} is not declared in options.py"
                assert p.shared == VOCABULARY.get(o, "profile"), (name, o, p.shared)
        if "--format" in opts:
            fmt = opts["--format"]
            assert set(fmt.type.choices) <= set(opt.FORMATS) and fmt.default == "text", name  # type: ignore[union-attr]
        if "--store" in opts:  # the one rule, results/<profile>, needs the profile
            want = OWN_PROFILE.get(name, opt.DEFAULT_PROFILE)
            assert "--profile" in opts and opts["--profile"].default == want, name
        assert ("--no-progress" in opts) == (name in SHOWS_PROGRESS), f"harness {name}: --no-progress"


def test_one_store_rule():
    assert opt.default_store(None) == Path("results/smoke") == opt.resolve_store(None, "smoke")
    assert opt.resolve_store(None, "paper") == Path("results/paper")
    assert opt.resolve_store("elsewhere", "paper") == Path("elsewhere")


def _landmarks(path: Path) -> Path:
    pts = [(x, y) for x in (40.0, 300.0, 620.0) for y in (30.0, 250.0, 470.0)]
    rows = [
        {"scene": "s1", "group": "g", "rgb": [x, y], "thermal": [0.5 * x + 10 + (i % 3) * 0.1, 0.5 * y + 5]}
        for i, (x, y) in enumerate(pts)
    ]
    path.write_text(json.dumps({"landmarks": rows}))
    return path


def test_sensing_and_export_follow_the_store_rule(tmp_path, cli_runner, monkeypatch):
    """`sensing registration-error` used to write results/paper and `export-predictions` to read results/smoke."""
    monkeypatch.chdir(tmp_path)
    lm = _landmarks(tmp_path / "lm.json")
    res = cli_runner(["sensing", "registration-error", "--landmarks", str(lm), "--dataset", "d"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "results/smoke/d/_sensing/registration_error.json").is_file()
    assert not (tmp_path / "results/paper").exists()
    res = cli_runner(["sensing", "registration-error", "--landmarks", str(lm), "--dataset", "d", "--profile", "paper"])
    assert res.exit_code == 0 and (tmp_path / "results/paper/d/_sensing/registration_error.json").is_file()
    res = cli_runner(["export-predictions", "--out", str(tmp_path / "x.json")])
    assert res.exit_code == 2 and str(Path("results/smoke")) in res.output, res.output
    res = cli_runner(["export-predictions", "--profile", "paper", "--out", str(tmp_path / "x.json")])
    assert res.exit_code == 2 and str(Path("results/paper")) in res.output, res.output


# ------------------------------------------------------------------------------------------------ old spellings
class _Recorded(HarnessError):
    pass


@pytest.fixture
def record(monkeypatch):
    """``record("module", "function")``: the function records its arguments and stops the command (exit 2)."""
    calls: dict[str, tuple[tuple[Any, ...], dict[str, Any]]] = {}

    def patch(module: str, name: str, result: Any = None) -> dict:
        def fake(*args: Any, **kwargs: Any) -> Any:
            calls[name] = (args, kwargs)
            if result is None:
                raise _Recorded("recorded")
            return result

        monkeypatch.setattr(importlib.import_module(module), name, fake)
        return calls

    return patch


def _predictions(tmp_path: Path) -> str:
    p = tmp_path / "preds.json"
    p.write_text("[]")
    return str(p)


#: The library function each command hands its values to.
RECEIVER = {
    "ablate": "harness.runner:ablate",
    "pretrain": "harness.commands.pretrain:pretrain",
    "score": "harness.scoring.external:score_external",
    "report": "harness.report:build_report",
    "compare-detectors": "harness.report:compare_detectors",
    "export-predictions": "harness.scoring.export:export_predictions",
    "sensing decode": "harness.sensing.batch:decode_batch",
    "show": "harness.report.show:show",
    "profile": "harness.profiling:profile_detector",
    "export": "harness.profiling:export_detector",
    "synth": "adapters.datasets.synthetic:generate",
    "sensing register": "harness.sensing.registration:load_homography_entries",
    "export-fiftyone": "harness.report.fiftyone_export:export_fiftyone",
}
OLD_SPELLINGS = [
    # (old command line, how to read the value from the receiver's (args, kwargs), expected value, deprecated
    # spellings)
    ("ablate --dataset d --fold B", lambda a, k: a[3], "B", "--fold"),
    ("ablate --dataset d --fold=P4+P5", lambda a, k: a[3], "P4+P5", "--fold"),
    ("pretrain --detector x --fold val --seed 3", lambda a, k: (a[3], a[4]), ("val", 3), "--fold --seed"),
    ("score --dataset d --fold P1 --predictions PREDS --name n", lambda a, k: a[1], "P1", "--fold"),
    (
        "report --store STORE --seed 7 --format md",
        lambda a, k: (k["seed"], k["formats"]),
        (7, ["md"]),
        "--seed --format",
    ),
    ("compare-detectors a b --dataset d --store STORE --seed 5", lambda a, k: k["seed"], 5, "--seed"),
    ("export-predictions --seed 1 --out OUT", lambda a, k: (a[0], a[5]), (Path("results/smoke"), [1]), "--seed"),
    ("sensing decode PREDS --out OUT --format tiff", lambda a, k: a[2].fmt, "tiff", "--format"),
    ("report --store STORE --dataset a --dataset b,c", lambda a, k: a[1], ["a", "b", "c"], "--dataset"),
    (
        "show --dataset m3t-synth --store STORE --detector x --detector y",
        lambda a, k: k["detectors"],
        ("x", "y"),
        "--detector",
    ),
    ("profile --detector ours --no-store", lambda a, k: a[0], "ours", "--detector"),
    ("export --detector x --onnx OUT", lambda a, k: (a[0], Path(a[1]).name), ("x", "out"), "--onnx"),
    ("synth --profile tiny --out OUT", lambda a, k: k["profile"], "tiny", "--profile"),
    (
        "sensing register --similarity g=0,0,0,1 --init PREDS --out OUT",
        lambda a, k: Path(a[0]).name,
        "preds.json",
        "--init",
    ),
    ("export-fiftyone --dataset d --seed 1 --out OUT", lambda a, k: k["seed"], [1], "--seed"),
]


@pytest.mark.parametrize("argv,read,expected,old", OLD_SPELLINGS, ids=lambda v: None)
def test_old_spellings_still_work_with_one_deprecation_line(
    argv, read, expected, old, tmp_path, cli_runner, record, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    subs = {"PREDS": _predictions(tmp_path), "STORE": str(tmp_path), "OUT": str(tmp_path / "out")}
    words = argv.split()
    module, function = (RECEIVER.get(" ".join(words[:2])) or RECEIVER[words[0]]).split(":")
    calls = record(module, function)
    res = cli_runner([subs.get(a, a) for a in words])
    assert res.exit_code == 2 and "recorded" in res.stderr, res.output  # the library function got the call
    args, kwargs = calls[function]
    assert read(args, kwargs) == expected
    lines = [line for line in res.stderr.splitlines() if line.startswith("deprecated:")]
    assert [line.split(",")[0] for line in lines] == [f"deprecated: {o}" for o in old.split()], res.stderr
    assert all("next release" in line for line in lines) and "deprecated" not in res.stdout


def test_new_spellings_print_no_deprecation(tmp_path, cli_runner, record):
    calls = record("harness.runner", "ablate")
    res = cli_runner(["ablate", "--dataset", "d", "--folds", "B"])
    assert res.exit_code == 2 and calls["ablate"][0][3] == "B" and "deprecated" not in res.output


def test_old_json_flag_and_markdown_value_print_the_same_as_the_new_ones(tmp_path, cli_runner, record):
    old, new = cli_runner(["list", "--json"]), cli_runner(["list", "--format", "json"])
    assert old.exit_code == new.exit_code == 0
    assert json.loads(old.stdout) == json.loads(new.stdout)  # nothing but the JSON on stdout
    assert old.stderr.count("deprecated: --json, use --format json") == 1 and "deprecated" not in new.stderr

    class Table:
        mismatches: list[str] = []

        def render(self, fmt: str) -> str:
            return f"rendered as {fmt}"

    record("harness.report.compare", "build_table", Table())
    res = cli_runner(["compare", "--datasets", "d", "--store", str(tmp_path), "--format", "markdown"])
    assert res.exit_code == 0 and res.stdout.strip() == "rendered as markdown"
    assert "deprecated: --format markdown, use --format md" in res.stderr
    assert (
        cli_runner(["compare", "--datasets", "d", "--store", str(tmp_path), "--format", "md"]).stdout.strip()
        == "rendered as markdown"
    )

    class Comparison:
        def to_dict(self) -> dict:
            return {"ok": True}

    record("harness.report", "compare_detectors", Comparison())
    res = cli_runner(["compare-detectors", "a", "b", "--dataset", "d", "--store", str(tmp_path), "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout) == {"ok": True}


def test_rewriting_leaves_values_after_a_double_dash_alone():
    cmd = click.Command("x", params=[click.Option(["--folds"])])
    cmd.params[0] = opt.SharedOption(["--folds"], old={"--fold": ("--folds",)})
    assert opt.rewrite_deprecated(cmd, ["--fold", "A", "--", "--fold"]) == ["--folds", "A", "--", "--fold"]
    assert opt.rewrite_deprecated(cmd, ["--folds=B"]) == ["--folds=B"]


def test_one_fold_commands_refuse_a_list(cli_runner):
    res = cli_runner(["ablate", "--dataset", "d", "--folds", "P1,P2"])
    assert res.exit_code == 2 and "works on one fold" in res.output


def test_one_run_commands_refuse_a_list_of_seeds_and_filters_take_one(cli_runner, record, tmp_path):
    res = cli_runner(["pretrain", "--detector", "x", "--seeds", "0,1"])
    assert res.exit_code == 2 and "trains one run; give one seed" in res.output
    calls = record("harness.commands.pretrain", "pretrain")
    res = cli_runner(["pretrain", "--detector", "x", "--seeds", "3"])
    assert res.exit_code == 2 and calls["pretrain"][0][4] == 3 and "deprecated" not in res.output
    calls = record("harness.report.fiftyone_export", "export_fiftyone")
    res = cli_runner(["export-fiftyone", "--dataset", "d", "--seeds", "0,2", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and calls["export_fiftyone"][1]["seed"] == [0, 2]


#: One meaning per option name: (option, what it must be in every command that has it).
def _one_name(p: click.Parameter) -> bool:
    return not p.multiple and getattr(p, "shared", None) is None


ONE_MEANING = {
    "--profile": lambda p: getattr(p, "shared", None) == "profile",  # a run profile, smoke or paper
    "--seeds": lambda p: getattr(p, "shared", None) == "seeds",  # training seeds
    "--datasets": lambda p: getattr(p, "shared", None) == "datasets" and p.multiple,
    "--detectors": lambda p: getattr(p, "shared", None) == "detectors" and p.multiple,
    "--dataset": _one_name,  # one dataset, never a list
    "--detector": _one_name,
    "--onnx": lambda p: p.is_flag,  # profile's switch; export writes its file with --out
    "--init": lambda p: isinstance(p.type, click.Path) and not p.type.dir_okay,  # a checkpoint file
}


def test_every_option_name_has_one_meaning_across_the_cli(host):
    seen: dict[str, list[str]] = {}
    for path, cmd in _walk():
        for p in cmd.params:
            for o in getattr(p, "opts", []):
                if o in ONE_MEANING and (path[0], o) not in OWN_MEANING:
                    assert ONE_MEANING[o](p), f"harness {' '.join(path)} {o}: not the meaning it has elsewhere"
                    seen.setdefault(o, []).append(" ".join(path))
    assert set(seen) == set(ONE_MEANING), set(ONE_MEANING) - set(seen)
    assert seen["--init"] == ["pretrain", "run"] and seen["--onnx"] == ["profile"], seen


@pytest.mark.parametrize("plural", ["--datasets", "--detectors"])
def test_lists_of_names_are_comma_separated_or_repeated_alike(plural):
    cmd = click.Command("x", params=[], callback=lambda **kw: kw)
    opt.names_option(plural, help="h")(cmd.callback)
    cmd.params = list(getattr(cmd.callback, "__click_params__", []))
    ctx = cmd.make_context("x", [plural, "a,b", plural, "c"])
    assert ctx.params[plural.lstrip("-")] == ("a", "b", "c")
    assert cmd.make_context("x", [])


# ------------------------------------------------------------------------------------------------ exit codes
def _one_error_line(res: Any) -> None:
    assert "Traceback" not in res.output
    errors = [line for line in res.stderr.splitlines() if line.startswith(("error:", "Error:"))]
    assert len(errors) == 1, res.stderr


INPUT_ERRORS = [  # one per command family: training, data, scoring, reports, profiling, sensing, weights, cache
    (["run", "--detector", "nope", "--dataset", "m3t-synth"], "unknown detector 'nope'"),
    (["ablate", "--dataset", "nope", "--folds", "P1"], "unknown dataset 'nope'"),
    (["prepare", "--dataset", "nope"], "unknown dataset 'nope'"),
    (["export-predictions", "--store", "EMPTY", "--out", "x.json"], "no finished run"),
    (["report", "--store", "NOWHERE"], "no results store here"),
    (["compare-detectors", "a", "b", "--dataset", "d", "--store", "NOWHERE"], "no results store here"),
    (["profile", "--detectors", "nope", "--no-store"], "unknown detector 'nope'"),
    (["sensing", "register", "--out", "h.yaml"], "give --landmarks, --similarity or --auto"),
    (["weights", "import", "missing.pt", "--out", "w.safetensors"], "missing.pt"),
    (["cache", "rm", "--cache", "EMPTY"], "or pass --unused"),
    (["run", "--no-such-option"], "No such option"),
]


@pytest.mark.parametrize("argv,message", INPUT_ERRORS, ids=lambda v: " ".join(v[:2]) if isinstance(v, list) else None)
def test_usage_and_input_errors_exit_2_in_one_line(argv, message, tmp_path, cli_runner, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty").mkdir()
    subs = {"EMPTY": str(tmp_path / "empty"), "NOWHERE": str(tmp_path / "nowhere")}
    res = cli_runner([subs.get(a, a) for a in argv])
    assert res.exit_code == 2, res.output
    assert message in res.output
    _one_error_line(res)


def test_batches_with_failures_exit_1(tmp_path, cli_runner, monkeypatch, record):
    """Partly done: the sweep ran what it could, `cache verify` checked every dataset, `decode` decoded the rest."""
    from harness.sweep import JobResult, SweepSummary

    summary = SweepSummary(
        tmp_path,
        [
            JobResult("d/a/c2/P1/seed0", "trained", mAP50=0.5, mAP50_95=0.3),
            JobResult("d/a/c2/P2/seed0", "failed", error="ValueError: x"),
        ],
        [],
    )
    record("harness.sweep", "sweep", summary)
    res = cli_runner(["sweep", "--detectors", "a", "--datasets", "d"])
    assert res.exit_code == 1 and "d/a/c2/P1/seed0" in res.stdout
    assert "partly done: 1 of 2 runs failed" in res.stderr

    class Entry:
        ref, path, form, count = "d/abc", tmp_path, "compact", 3

    class Broken:
        def __init__(self, path: Path):
            pass

        def verify(self) -> list[str]:
            return ["sample 2: digest differs"]

    record("harness.cache.admin", "entries", [Entry()])
    monkeypatch.setattr(importlib.import_module("harness.cache"), "PreparedDataset", Broken)
    res = cli_runner(["cache", "verify", "--cache", str(tmp_path)])
    assert res.exit_code == 1 and "d/abc: 1 sample(s) failed" in res.stdout and "digest differs" in res.stderr
    assert "partly done: 1 prepared dataset(s) failed verification" in res.stderr

    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "bad_T.jpg").write_bytes(b"not a jpeg")
    res = cli_runner(["sensing", "decode", str(tmp_path / "in"), "--out", str(tmp_path / "out")])
    assert res.exit_code == 1 and "bad_T.jpg" in res.output and "partly done:" in res.stderr
    assert "Traceback" not in res.output


def _command(name: str, exc: BaseException) -> click.Command:
    @click.command(name=name)
    def cmd() -> None:
        """A command that raises."""
        raise exc

    return cmd


def test_a_bug_exits_70_with_a_short_message_and_the_traceback_only_with_v(cli_runner, extra_command, monkeypatch):
    monkeypatch.delenv("HARNESS_DEBUG", raising=False)
    extra_command(_command("boom", ValueError("boom went the harness\nsecond line")))
    res = cli_runner(["boom"])
    assert res.exit_code == 70
    first = res.stderr.splitlines()[0]
    assert first.startswith("bug: ValueError: boom went the harness (at tests/test_cli_vocabulary.py:")
    assert "report it" in res.stderr and "harness -v" in res.stderr
    assert "Traceback" not in res.output and res.stdout == ""
    res = cli_runner(["-v", "boom"])
    assert res.exit_code == 70 and "Traceback" in res.stderr and "raise exc" in res.stderr
    monkeypatch.setenv("HARNESS_DEBUG", "1")
    with pytest.raises(ValueError, match="boom went"):
        cli_runner(["boom"])


def test_plugin_commands_get_the_same_table(cli_runner, extra_command, monkeypatch):
    from harness.errors import DataError, PartlyDone

    monkeypatch.delenv("HARNESS_DEBUG", raising=False)
    extra_command(_command("missing-file", FileNotFoundError(2, "No such file or directory", "x.csv")))
    extra_command(_command("bad-input", DataError("x.csv: column 'scene' missing")))
    extra_command(_command("some-failed", PartlyDone("2 of 5 files failed (listed above)")))
    extra_command(_command("ctrl-c", KeyboardInterrupt()))
    res = cli_runner(["missing-file"])
    assert res.exit_code == 2 and "error: [Errno 2] No such file or directory: 'x.csv'" in res.stderr
    res = cli_runner(["bad-input"])
    assert res.exit_code == 2 and res.stderr.strip() == "error: x.csv: column 'scene' missing"
    res = cli_runner(["some-failed"])
    assert res.exit_code == 1 and res.stderr.strip() == "partly done: 2 of 5 files failed (listed above)"
    assert cli_runner(["ctrl-c"]).exit_code == 130


def test_a_bug_in_a_plugin_command_exits_70_from_the_console_entry_point(tmp_path):
    """The real `python -m harness` path: a plugin file whose command raises."""
    (tmp_path / "buggy_plugin.py").write_text(
        "import click\nfrom harness import hookimpl\n\n\n@hookimpl\ndef register_commands(cli):\n"
        "    @cli.command(name='buggy')\n    def buggy():\n        '''Fails.'''\n        return {}['key']\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "HARNESS_DEBUG"}
    env.update(HARNESS_PLUGINS_DIR=str(tmp_path), PYTHONPATH=str(REPO))
    res = subprocess.run(
        [sys.executable, "-m", "harness", "buggy"], capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path
    )
    assert res.returncode == 70, res.stderr
    assert "bug: KeyError: 'key' (at " in res.stderr and "buggy_plugin.py:10" in res.stderr
    assert "Traceback" not in res.stderr and res.stdout == ""


# ------------------------------------------------------------------------------------------------ progress
def test_bars_show_only_on_a_terminal_and_when_progress_is_on(monkeypatch):
    from harness import progress

    with progress.bar("x", total=3) as b:  # pytest captures stderr: not a terminal
        assert not b.shown
        b.advance()  # a hidden bar takes every call
        b.update(completed=2, total=4, description="y", note="z")
        b.restart("z", 5)
    monkeypatch.setattr(progress, "stderr_is_terminal", lambda: True)
    with progress.bar("x", total=3) as b:
        assert b.shown
        b.advance(2)
        with progress.bar("nested") as inner:  # rich >= 14.1 nests live displays; older rich: this one is silent
            inner.advance()
        b.advance()
    with progress.bar("x", enabled=False) as b:
        assert not b.shown
    with progress.switched_off():
        assert not progress.progress_on()
        with progress.bar("x") as b:
            assert not b.shown
    assert progress.progress_on()


def test_no_progress_switches_off_bars_and_lines_for_that_command_only(cli_runner, extra_command):
    import io

    from harness import progress

    seen: list[tuple[bool, str]] = []

    @click.command(name="probe")
    @opt.no_progress_option()
    def probe() -> None:
        """Records whether progress is on."""
        out = io.StringIO()
        p = progress.OverallProgress(runs=1, epochs=1, stream=out)
        p.start_run("x")
        p.epoch_done(1, 1)
        seen.append((progress.progress_on(), out.getvalue()))

    extra_command(probe)
    assert cli_runner(["probe", "--no-progress"]).exit_code == 0
    assert cli_runner(["probe"]).exit_code == 0
    assert seen[0] == (False, "") and seen[1][0] and seen[1][1].startswith("run 1/1 x epoch 1/1")
    assert progress.progress_on()  # nothing leaks out of the command


def test_a_usage_error_after_no_progress_leaves_progress_on(cli_runner, extra_command):
    from harness import progress

    @click.command(name="probe")
    @opt.no_progress_option()
    @click.option("--conf", type=click.FloatRange(0, 1), help="A number in [0, 1].")
    def probe(conf: float) -> None:
        """Does nothing."""

    extra_command(probe)
    assert cli_runner(["probe", "--no-progress", "--conf", "1.5"]).exit_code == 2
    assert progress.progress_on()


def test_progress_bars_are_set_up_in_one_place():
    offenders = []
    for folder in ("harness", "adapters"):
        for path in (REPO / folder).rglob("*.py"):
            if path == REPO / "harness" / "progress.py":
                continue
            text = path.read_text(encoding="utf-8")
            if "rich.progress" in text or "Progress(" in text.replace("OverallProgress(", "").replace(
                "SweepProgress(", ""
            ).replace("BenchmarkProgress(", "").replace("_Progress(", ""):
                offenders.append(str(path.relative_to(REPO)))
    assert not offenders, f"progress bars set up outside harness/progress.py: {offenders}"


# ------------------------------------------------------------------------------------------------ start-up
def test_help_and_listing_import_no_heavy_module(tmp_path):
    """`harness --help`, a command's help and `harness list` import neither torch nor cv2, scipy or rich."""
    code = (
        "import sys\nfrom harness.cli import main\n"
        "for argv in (['--help'], ['run', '--help'], ['sensing', 'decode', '--help'], ['list']):\n"
        "    try:\n        main(argv)\n    except SystemExit as e:\n        assert not e.code, (argv, e.code)\n"
        "heavy = ('torch', 'cv2', 'scipy', 'rich', 'matplotlib', 'onnx', 'onnxruntime', 'pycocotools')\n"
        "print(sorted(m for m in heavy if m in sys.modules), file=sys.stderr)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path
    )
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip().splitlines()[-1] == "[]", res.stderr
