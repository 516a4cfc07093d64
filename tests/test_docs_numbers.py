"""Figures the README and docs quote about the built-in data and commands, checked against the data and the code:
the synthetic set's held-out images and instances (the shipped reference results record the support of every fold,
and ``test_reference_samples`` ties those samples to the set this installation generates), the profiles the option
table and ``--help`` list, the cache size ``harness prepare`` prints; and recovery hints that must lead somewhere:
a reference run's gallery finds the same samples prepared here, a suggested ``compare-detectors`` command names the
reference results it compares with."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from harness.config import available
from harness.references import load_references

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _text(path: Path) -> str:
    return " ".join(path.read_text(encoding="utf-8").split())


def _int(s: str) -> int:
    return int(s.replace(",", ""))


def _support() -> dict[str, dict]:
    """The held-out support of each fold of the reference results (ours/c2, seed 0)."""
    refs = load_references("shipped")
    runs = [r for r in refs.runs() if r.key.detector == "ref:ours" and r.key.encoding == "c2" and r.key.seed == 0]
    return {r.key.fold: r.metrics["support"] for r in runs}


def test_the_readmes_held_out_images_and_instances_are_the_synthetic_sets():
    support = _support()
    assert sorted(support) == ["P1", "P2", "P3", "P4+P5"]
    text = _text(README)
    quoted = re.findall(r"on the same ([\d,]+) held-out images / ([\d,]+) instances", text)
    assert quoted, "the README no longer quotes the held-out support of all folds"
    for images, instances in quoted:
        assert _int(images) == sum(s["images"] for s in support.values())
        assert _int(instances) == sum(s["instances"] for s in support.values())
    m = re.search(
        r"on P4\+P5 \(([\d,]+) held-out images; ([\d,]+) delamination and ([\d,]+) water-seepage instances\)", text
    )
    assert m, "the README no longer quotes the ablation fold's support"
    p45 = support["P4+P5"]
    assert [_int(g) for g in m.groups()] == [
        p45["images"],
        p45["categories"]["delamination"],
        p45["categories"]["water_seepage"],
    ]


def test_the_profiles_the_readme_and_help_list_are_those_that_exist(cli_runner):
    profiles = set(available("profiles"))
    assert {"smoke", "demo", "benchmark", "paper"} <= profiles
    text = README.read_text(encoding="utf-8")
    listed = re.findall(r"`--profile ([a-z]+(?:\\?\|[a-z]+)+)`", text)
    assert listed, "the README no longer lists the profiles"
    for choices in listed:
        assert set(choices.replace("\\", "").split("|")) == profiles, choices
    helptext = " ".join(cli_runner(["run", "--help"]).output.split())
    assert all(f"{p}:" in helptext for p in profiles), helptext


def test_compare_detectors_on_a_reference_entry_asks_for_the_reference_results(cli_runner, tmp_path):
    from harness.report.build import _refs_option
    from harness.report.reader import StoreView

    res = cli_runner(
        ["compare-detectors", "ref:ours/c2", "ours/c2", "--dataset", "m3t-synth", "--store", str(tmp_path)]
    )
    text = " ".join(res.output.split())
    assert res.exit_code != 0 and "--reference-results shipped" in text and "harness run" not in text, text
    assert _refs_option(StoreView(tmp_path, references=load_references("shipped"))) == " --reference-results shipped"
    assert _refs_option(StoreView(tmp_path)) == ""


@pytest.fixture(scope="module")
def small_set(tmp_path_factory):
    """The default synthetic set (small, seed 0), generated and prepared here (compact form)."""
    from adapters.datasets import synthetic as S
    from harness.cache import prepare
    from harness.config import load_config

    base = tmp_path_factory.mktemp("docs-numbers")
    root = base / "m3t-synth-small-seed0"
    S.generate(root, profile="small", seed=0, progress=False, workers=2)
    cfg = load_config(protocol="m3t-4fold")
    cfg["dataset"] = {"root": str(root)}
    return prepare("m3t-synth", cfg, cache_root=base / "cache", progress=False), base / "cache"


def _mb(text: str) -> float:
    return float(re.search(r"cache ([\d.]+) MB", text).group(1))  # type: ignore[union-attr]


@pytest.mark.slow
def test_the_cache_size_prepare_prints_is_the_readmes(small_set):
    from harness.cache.admin import size_line
    from harness.commands.data import prepare_summary

    compact, _ = small_set
    line = size_line(compact)
    assert line in prepare_summary(compact)
    m = re.search(r"prints `cache ([\d.]+) MB \(compact form\) beside ([\d.]+) MB of source files`", _text(README))
    assert m, "the README no longer quotes what `harness prepare --dataset m3t-synth` prints"
    src = float(re.search(r"beside ([\d.]+) MB of source files", line).group(1))  # type: ignore[union-attr]
    # within 3 %: the compressed size moves a little with the codec libraries of an installation
    for quoted, measured in zip(map(float, m.groups()), (_mb(line), src)):
        assert quoted == pytest.approx(measured, rel=0.03), (m.groups(), line)
    print(line)


@pytest.mark.slow
def test_a_reference_runs_gallery_finds_the_same_samples_prepared_here(small_set):
    from harness.report.gallery import prepared_of

    _, cache = small_set
    refs = load_references("shipped")
    run = next(r for r in refs.runs() if r.key.fold == "P4+P5")
    samples, why = prepared_of(run, cache)
    assert why is None and samples is not None and samples.form == "compact"
    samples, why = prepared_of(run, cache / "elsewhere")
    assert samples is None and "harness synth" in why and "no prepared m3t-synth there holds the samples" in why
