"""What the demo relies on: a report that is written without reference results it cannot compare with
(``harness report --references-optional``), and runs that keep only the weights a screen needs
(``harness run --keep-weights final``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from engine_helpers import run_args, set_args
from report_fixtures import TINY_RUN, cli, synthetic_store, tiny_run
from screen_helpers import p1_flight

DATASET = "synth"


def _digest(store: Path, digest: str) -> None:
    """Record ``digest`` as the samples every run of ``store`` trained and scored on (``metrics.json`` ``samples``)."""
    for path in store.glob(f"{DATASET}/*/*/*/seed*/metrics.json"):
        metrics = json.loads(path.read_text())
        metrics["samples"] = {
            "encoding": "c2",
            "train": f"{digest}-train",
            "held_out": f"{digest}-held-out",
            "aligned": {"train": f"{digest}-train", "held_out": f"{digest}-held-out"},
        }
        path.write_text(json.dumps(metrics))


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """A user's store and a reference store of the same dataset and folds whose samples' digests differ."""
    from harness.references import export_references
    from harness.store import Store

    root = tmp_path_factory.mktemp("refs")
    bench = root / "bench"
    synthetic_store(bench, dataset=DATASET, detectors={"alpha": "medium"}, seed=1)
    _digest(bench, "reference")
    refs = root / "refs"
    export_references(bench, refs, [r.key for r in Store(bench).runs(dataset=DATASET)])
    user = root / "user"
    synthetic_store(user, dataset=DATASET, detectors={"ours": "strong", "beta": "weak"})
    _digest(user, "user")
    return user, refs


def _report(user: Path, refs: Path, out: Path, *extra: str, code: int = 0) -> str:
    args = ["report", "--store", str(user), "--reference-results", str(refs), "--out", str(out)]
    return cli([*args, "--resamples", "0", "--no-progress", *extra], code)


def test_without_the_option_a_mismatch_stops_the_report(stores, tmp_path):
    user, refs = stores
    out = _report(user, refs, tmp_path / "r", code=2)
    assert "other samples" in out
    assert not (tmp_path / "r" / "report.md").exists()


def test_with_the_option_the_report_is_written_and_says_why_in_one_line(stores, tmp_path, caplog):
    from harness.report.build import unavailable_references_line

    user, refs = stores
    with caplog.at_level(logging.WARNING):
        out = _report(user, refs, tmp_path / "r", "--references-optional")
    reason = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Reference results not shown")]
    assert len(reason) == 1, caplog.text
    line = reason[0]
    assert "\n" not in line and "other samples" in line and line.endswith(".")
    assert "to compare with them, generate the default synthetic set" in line
    assert "digest" not in line and "--reference-results" not in line  # the details and the option left out
    assert "report of" in out
    text = (tmp_path / "r" / "report.txt").read_text()
    md = (tmp_path / "r" / "report.md").read_text()
    html = (tmp_path / "r" / "report.html").read_text()
    # the line near the top: before the first dataset's part; no reference entry anywhere
    assert " ".join(text.split()).count(line) == 1 and text.index("Reference results not shown") < text.index("# synth")
    assert f"> {line}" in md.splitlines() and md.index(line) < md.index("## synth")
    assert "Reference results not shown: the reference results were trained" in html
    assert html.index("Reference results not shown") < html.index("<nav>")
    for doc in (text, md, html):
        assert "ref:alpha" not in doc and "ours" in doc
    assert line == unavailable_references_line(_mismatch(user, refs))


def _mismatch(user: Path, refs: Path) -> Exception:
    """The error the references raise for ``user``'s runs."""
    from harness.references import ReferenceMismatchError, load_references
    from harness.report.reader import StoreView

    try:
        StoreView(user, references=load_references(refs)).finished_runs(DATASET)
    except ReferenceMismatchError as exc:
        return exc
    raise AssertionError("the references were not refused")


def test_with_the_option_missing_references_are_named_instead(stores, tmp_path):
    user, _ = stores
    _report(user, tmp_path / "nowhere", tmp_path / "r", "--references-optional")
    text = " ".join((tmp_path / "r" / "report.txt").read_text().split())
    assert f"Reference results not shown: {tmp_path / 'nowhere' / 'references.json'}: no reference results" in text
    assert "ref:" not in text


def test_matched_references_are_still_shown_under_the_option(stores, tmp_path):
    from harness.references import export_references
    from harness.store import Store

    user, _ = stores
    same = tmp_path / "refs"
    export_references(user, same, [r.key for r in Store(user).runs(dataset=DATASET, detector="beta")])
    _report(user, same, tmp_path / "r", "--references-optional")
    text = (tmp_path / "r" / "report.txt").read_text()
    assert "ref:beta" in text and "Reference results not shown" not in text


@pytest.mark.parametrize(
    ("message", "line"),
    [
        (
            "the reference results (m3t-synth (generator v2, small, seed 0), benchmark profile: 256 px) were trained "
            "and scored on other samples than 2 of your run(s): a/b: digest 1, references 2; c/d: digest 3. Your data "
            "(data/x) differs from the references' in: seed 1 vs 0. A comparison needs the same samples: generate "
            "the default synthetic set (`harness synth`, seed 0), or leave out --reference-results.",
            "Reference results not shown: the reference results were trained and scored on other samples than 2 of "
            "your run(s); to compare with them, generate the default synthetic set (`harness synth`, seed 0).",
        ),
        (
            "cannot verify that 2 run(s) used the reference results' samples: they were stored before (a, b); rerun "
            "them with --force, or leave out --reference-results",
            "Reference results not shown: cannot verify that 2 run(s) used the reference results' samples; to "
            "compare with them, rerun them with --force.",
        ),
        ("something else", "Reference results not shown: something else."),
    ],
)
def test_the_line_is_the_errors_first_clause_and_its_fix(message, line):
    from harness.references import ReferenceMismatchError
    from harness.report.build import unavailable_references_line

    assert unavailable_references_line(ReferenceMismatchError(message)) == line


# ------------------------------------------------------------------------------------------------ weights
def _checkpoints(run: Path) -> list[str]:
    return sorted(p.name for p in (run / "checkpoints").iterdir())


def _fake_run(root: Path, state: str, final: str = "best"):
    from harness.store import Run, RunKey

    run = Run(root, RunKey(DATASET, "d", "c2", "P1", 0))
    (run.checkpoint_dir).mkdir(parents=True)
    for name in ("best.pt", "last.pt"):
        (run.checkpoint_dir / name).write_bytes(b"x")
    run.config_path.write_text(f"train:\n  final: {final}\n")
    paths = {k: str(run.checkpoint_dir / f"{k.split('_')[0]}.pt") for k in ("best_path", "last_path")}
    run.metrics_path.write_text(json.dumps({"train": paths}))
    run.set_status(state)
    return run


@pytest.mark.parametrize(
    ("state", "final", "kept"),
    [
        ("finished", "best", ["best.pt"]),
        ("finished", "last", ["last.pt"]),
        ("running", "best", ["best.pt", "last.pt"]),  # an interrupted run resumes from last.pt
        ("failed", "best", ["best.pt", "last.pt"]),
    ],
)
def test_only_a_finished_run_drops_the_weights_it_did_not_predict_with(tmp_path, state, final, kept):
    run = _fake_run(tmp_path, state, final)
    dropped = run.keep_final_checkpoint()
    assert _checkpoints(run.path) == kept
    assert sorted(p.name for p in dropped) == sorted({"best.pt", "last.pt"} - set(kept))
    recorded = json.loads(run.metrics_path.read_text())["train"]  # no recorded path leads to a deleted file
    assert sorted(Path(v).name for v in recorded.values() if v) == kept


def test_a_finished_run_without_best_weights_keeps_last(tmp_path):
    run = _fake_run(tmp_path, "finished")
    (run.checkpoint_dir / "best.pt").unlink()
    assert run.final_checkpoint() == run.checkpoint_dir / "last.pt"
    assert run.keep_final_checkpoint() == [] and _checkpoints(run.path) == ["last.pt"]


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_keep_weights_final_leaves_what_report_screen_and_a_rerun_need(tiny_source, tmp_path):
    """A real run (TinyDet, 1 epoch at 64 px) keeps both checkpoints by default; run again with
    ``--keep-weights final`` it is skipped and trimmed to best.pt, skipped again, redone with ``--force`` (trimmed as
    it finishes), and a report and a screen read it."""
    with tiny_run(tiny_source, tmp_path, "P1", "keep-weights") as run:
        assert _checkpoints(run) == ["best.pt", "last.pt"]
        metrics = (run / "metrics.json").read_bytes()
        args = run_args("tinydet", "m3t-synth", "P1", tmp_path / "store", *set_args(TINY_RUN))
        args += ["--set", f"dataset.root={tiny_source}"]
        out = cli([*args, "--keep-weights", "final"])
        assert "skipped" in out and _checkpoints(run) == ["best.pt"]
        after = json.loads((run / "metrics.json").read_text())
        before = json.loads(metrics)
        assert after["train"]["last_path"] is None and before["train"]["last_path"]  # it names no deleted file
        assert after["train"]["best_path"] == before["train"]["best_path"]
        after["train"]["last_path"] = before["train"]["last_path"]
        assert after == before  # nothing else changed
        assert "skipped" in cli([*args, "--keep-weights", "final"])  # a finished run needs no last.pt
        assert "trained" in cli([*args, "--keep-weights", "final", "--force"])  # redone from the start, trimmed
        assert _checkpoints(run) == ["best.pt"]
        text = cli(["report", "--store", str(tmp_path / "store"), "--print", "--resamples", "0", "--no-progress"])
        assert "tinydet" in text
        flight = p1_flight(tiny_source, tmp_path / "flight")
        cli(["screen", str(flight), "--run", str(run), "--out", str(tmp_path / "screen"), "--no-progress"])
        manifest = json.loads((tmp_path / "screen" / "manifest.json").read_text())
        assert manifest["model"]["weights"] == str(run / "checkpoints" / "best.pt")
        assert list((tmp_path / "screen" / "frames").glob("*.json"))


def test_a_kept_last_checkpoint_is_slimmed_to_the_weights_that_predicted(tmp_path):
    """Under ``final: last`` (and ``protocol.selection: last``) the run's ``last.pt`` is its final weights: kept
    without the optimiser and resume state, and read back as the same EMA weights."""
    import torch

    from harness.engine import checkpoint as ckpt

    run = _fake_run(tmp_path, "finished", final="last")
    model = torch.nn.Linear(64, 64)
    ema = {k: v + 1 for k, v in model.state_dict().items()}
    full = {
        "format": ckpt.FORMAT,
        "version": ckpt.VERSION,
        "epoch": 4,
        "done": True,
        "model": model.state_dict(),
        "optimizer": torch.optim.AdamW(model.parameters()).state_dict() | {"pad": torch.zeros(20000)},
        "ema": {"module": ema, "updates": 10},
        "rng": {"torch": torch.get_rng_state()},
        "history": [{"epoch": 1}],
    }
    ckpt.save(run.checkpoint_dir / "last.pt", full)
    before = (run.checkpoint_dir / "last.pt").stat().st_size
    assert run.keep_final_checkpoint() == [run.checkpoint_dir / "best.pt"]
    slim = ckpt.load(run.checkpoint_dir / "last.pt")
    assert set(slim) == {"format", "version", "epoch", "done", "model"}
    assert all(torch.equal(ckpt.state_dict_of(slim)[k], ema[k]) for k in ema)
    assert (run.checkpoint_dir / "last.pt").stat().st_size < before / 2
    assert run.keep_final_checkpoint() == []  # a second pass leaves it as it is
