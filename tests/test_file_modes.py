"""Files and folders the harness creates get the modes the umask gives (as open() and mkdir() would), so a cache or
results store on a shared server can be read by the colleagues the umask admits."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from harness.api import AlignedSample
from harness.io import atomic_write_json, atomic_write_text, current_umask, make_temp_dir


@pytest.fixture(params=[0o022, 0o002], ids=["umask022", "umask002"])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_current_umask_reads_without_changing_it(umask):
    assert current_umask() == umask
    assert current_umask() == umask


def test_atomic_writes_get_the_mode_open_would_give(umask, tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    a = atomic_write_json(tmp_path / "metrics.json", {"ap": 0.5})
    b = atomic_write_text(tmp_path / "sub" / "note.txt", "y")
    assert mode(a) == mode(b) == mode(plain) == 0o666 & ~umask
    assert mode(tmp_path / "sub") == 0o777 & ~umask
    atomic_write_json(a, {"ap": 0.6})  # replacing keeps the umask mode too
    assert mode(a) == 0o666 & ~umask


def test_temporary_folders_get_the_mode_mkdir_would_give(umask, tmp_path):
    (tmp_path / "plain").mkdir()
    tmp = make_temp_dir(prefix=".x.", suffix=".tmp", dir=tmp_path)
    assert mode(tmp) == mode(tmp_path / "plain") == 0o777 & ~umask


def test_a_prepared_folder_and_its_files_get_the_umask_modes(umask, tmp_path):
    from harness.cache import PreparedWriter

    w = PreparedWriter(tmp_path / "cache" / "key", "toy", ["car"])
    h, wd = 8, 10
    w.add(
        AlignedSample(
            0,
            np.zeros((h, wd, 3), np.uint8),
            np.full((h, wd), 20, np.float32),
            np.zeros((h, wd), np.uint8),
            np.array([[1, 1, 4, 4]], np.float32),
            np.array([0]),
            "g",
        )
    )
    folder = w.close({})
    assert mode(folder) == 0o777 & ~umask
    files = [p for p in folder.rglob("*") if p.is_file()]
    assert files and {mode(p) for p in files} == {0o666 & ~umask}


def test_decoded_files_and_their_sidecars_share_the_umask_mode(umask, tmp_path):
    from harness.sensing.batch import decode_batch
    from harness.sensing.radiometry import sidecar_path, write_rjpeg

    src = write_rjpeg(tmp_path / "f.jpg", np.full((12, 16), 21.0, np.float32))
    decode_batch([src], tmp_path / "out")
    png = tmp_path / "out" / "f.png"
    assert mode(png) == mode(sidecar_path(png)) == mode(src) == 0o666 & ~umask


@pytest.mark.parametrize("umask", [0o002], indirect=True, ids=["umask002"])  # one umask: generation takes seconds
def test_a_synthetic_dataset_folder_gets_the_umask_modes(umask, tmp_path):
    from adapters.datasets.synthetic import generate

    out = tmp_path / "synth"
    generate(out, profile="tiny", seed=0, progress=False, workers=1)
    folders = [out, *(p for p in out.rglob("*") if p.is_dir())]
    files = [p for p in out.rglob("*") if p.is_file()]
    assert {mode(p) for p in folders} == {0o777 & ~umask}
    assert files and {mode(p) for p in files} == {0o666 & ~umask}
