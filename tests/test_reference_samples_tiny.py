"""The shipped RGBT-Tiny-like references hold on this installation: the suite's data folder, generated here, prepares
exactly the samples every shipped cell was trained and scored on (both annotation sources, every encoding), as
`harness benchmark rerun --suite rgbt-tiny-synth` checks before it trains."""

from __future__ import annotations

import pytest

from harness import benchmark as B
from harness.references import load_references, shipped_root

SUITE = B.get_suite("rgbt-tiny-synth")
REFS = shipped_root() / SUITE.references

pytestmark = pytest.mark.skipif(not (REFS / "references.json").is_file(), reason="no shipped rgbt-tiny references")


@pytest.fixture(scope="module")
def here(tmp_path_factory):
    """The suite's data folder, generated in this environment, and a prepared-data cache of its own."""
    base = tmp_path_factory.mktemp("tinyrefs")
    mp = pytest.MonkeyPatch()
    mp.setenv("HARNESS_DATA", str(base / "data"))
    mp.setenv("HARNESS_CACHE", str(base / "cache"))
    assert B.ensure_data(SUITE) == SUITE.data_folder()
    yield base
    mp.undo()


@pytest.mark.slow
def test_the_shipped_tiny_references_record_every_cell_of_the_suite():
    refs = load_references(REFS)
    assert refs.dataset == "rgbt-tiny" and len(refs.manifest["cells"]) == 30
    assert set(refs.manifest["samples"]) == {
        "test-T/proxy8",
        "test-RGB/proxy8",
        "test-T/ir8",
        "test-RGB/ir8",
        "test-T/none",
    }
    assert refs.manifest["generator"]["profile"] == "small-320"


@pytest.mark.slow
@pytest.mark.parametrize(
    "cell",
    [
        "ours/proxy8/test-T/seed0",
        "ours/proxy8/test-RGB/seed0",
        "eme/ir8/test-T/seed0",
        "eme/ir8/test-RGB/seed0",
        "ours/none/test-T/seed0",
    ],
)
def test_this_installation_prepares_the_samples_of_the_shipped_tiny_references(here, cell):
    refs = load_references(REFS)
    det, enc, fold, seed = cell.split("/")
    request, ref = B.rerun_request(
        refs, det, enc, fold, int(seed.removeprefix("seed")), here / "store", overrides=SUITE.data_overrides()
    )
    checked = B.check_rerun(refs, ref, request)  # raises ReferenceMismatchError beyond a release's tolerance
    assert checked["samples"]["state"] == "identical", checked["samples"]
