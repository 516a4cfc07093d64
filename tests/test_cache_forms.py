"""Cache forms: the compact cache loads exactly the raw cache's samples, stays small, and references 8-bit sources."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from datasets_helpers import synth_cfg
from harness.cache import forms as CF
from harness.cache import prepare
from harness.errors import DataError


def _same(a, b) -> None:
    assert len(a) == len(b)
    for i in range(len(a)):
        x, y = a[i], b[i]
        assert x.image_id == y.image_id and x.group == y.group and x.meta == y.meta
        for f in ("rgb", "ir8", "boxes", "labels"):
            got, want = np.asarray(getattr(y, f)), np.asarray(getattr(x, f))
            assert got.dtype == want.dtype and got.shape == want.shape and got.tobytes() == want.tobytes(), f
        if x.thermal is None:
            assert y.thermal is None
        else:  # bit for bit, NaN included
            assert np.asarray(x.thermal).tobytes() == np.asarray(y.thermal).tobytes()


# ------------------------------------------------------------------------------------------------ codecs
def test_temperature_codec_is_exact_bit_for_bit():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:128]
    raw14 = 6000 + 4 * xx + 3 * yy + rng.integers(0, 8, (96, 128))  # a scene of integer sensor counts
    t = (raw14 / 16.0 - 273.15).astype(np.float32)  # a calibration curve of integer counts
    t[0, 0], t[1, 1], t[2, 2] = np.nan, -0.0, np.inf
    data = CF.encode_f32(t)
    assert data[:1] == b"P" and len(data) < t.nbytes / 2
    assert CF.decode_f32(np.frombuffer(data, np.uint8), t.shape, "x").tobytes() == t.tobytes()
    noisy = rng.normal(20, 5, (300, 300)).astype(np.float32)  # > 65,536 distinct values: shuffled zlib, still exact
    data = CF.encode_f32(noisy)
    assert data[:1] == b"Z"
    assert CF.decode_f32(np.frombuffer(data, np.uint8), noisy.shape, "x").tobytes() == noisy.tobytes()
    with pytest.raises(DataError, match="damaged compressed temperatures"):
        CF.decode_f32(np.frombuffer(b"Q123", np.uint8), t.shape, "sample 7")


@pytest.mark.parametrize("codec", CF.U8_CODECS)
def test_image_codec_is_lossless(codec):
    if codec == "zstd":
        pytest.importorskip("zstandard")
    rng = np.random.default_rng(1)
    for img in (rng.integers(0, 256, (40, 56, 3), dtype=np.uint8), rng.integers(0, 256, (40, 56), dtype=np.uint8)):
        assert np.array_equal(CF.decode_u8(CF.encode_u8(img, codec), img.shape, "x", codec), img)
    with pytest.raises(DataError, match="sample 3: damaged compressed image"):
        CF.decode_u8(np.zeros(10, np.uint8), (40, 56), "sample 3", codec)


# ------------------------------------------------------------------------------------------------ radiometric
@pytest.mark.parametrize("codec", CF.U8_CODECS)
def test_compact_and_raw_forms_load_identical_samples_and_encodings(tiny, tmp_path, monkeypatch, codec):
    from harness.encodings import ENCODINGS

    if codec == "zstd":
        pytest.importorskip("zstandard")
    monkeypatch.setattr(CF, "default_u8_codec", lambda: codec)
    cfg = synth_cfg(tiny)
    raw = prepare("m3t-synth", cfg, cache_root=tmp_path / "c", progress=False, form="raw")
    compact = prepare("m3t-synth", cfg, cache_root=tmp_path / "c", progress=False)
    assert (raw.form, compact.form) == ("raw", "compact") and raw.folder != compact.folder
    assert compact.manifest["codec"]["u8"] == codec
    assert compact.folder.name == raw.folder.name.removesuffix("-raw")
    _same(raw, compact)
    size = lambda ds: sum(p.stat().st_size for p in ds.folder.rglob("*") if p.is_file())  # noqa: E731
    assert size(compact) < size(raw) / 2
    encs = {e.name: e for e in ENCODINGS}
    for name in ("c2", "ir8"):
        for i in range(len(raw)):
            a, b = raw.channel(i, encs[name]), compact.channel(i, encs[name])
            assert a.tobytes() == b.tobytes() and not b.flags.writeable
    # the environment picks the form when the caller does not
    monkeypatch.setenv("HARNESS_CACHE_FORM", "raw")
    again = prepare("m3t-synth", cfg, cache_root=tmp_path / "c", progress=False)
    assert again.from_cache and again.folder == raw.folder
    monkeypatch.setenv("HARNESS_CACHE_FORM", "zip")
    with pytest.raises(DataError, match="unknown cache form 'zip'"):
        prepare("m3t-synth", cfg, cache_root=tmp_path / "c", progress=False)


# ------------------------------------------------------------------------------------------------ 8-bit references
@pytest.fixture
def rgbt640(tmp_path):
    """An RGBT-Tiny-layout folder of 640x512 JPEG pairs."""
    from eightbit_fixtures import write_rgbt_tiny

    root = tmp_path / "RGBT-Tiny"
    write_rgbt_tiny(root, train_seqs=("DJI_0001_1",), test_seqs=("DJI_0101_1",), frames=2, size=(640, 512))
    return root


def _rgbt_cfg(root: Path) -> dict:
    from harness.config import load_config

    return load_config(protocol="rgbt-tiny", overrides=[f"dataset.root={root}"])


def test_eight_bit_sources_are_referenced_not_copied(rgbt640, tmp_path):
    from harness.encodings import ENCODINGS

    cfg = _rgbt_cfg(rgbt640)
    compact = prepare("rgbt-tiny", cfg, cache_root=tmp_path / "c", progress=False)
    raw = prepare("rgbt-tiny", cfg, cache_root=tmp_path / "c", progress=False, form="raw")
    assert all("src" in r for r in compact.records) and compact.manifest["referenced_bytes"] > 0
    _same(raw, compact)
    proxy8 = next(e for e in ENCODINGS if e.name == "proxy8")
    for i in range(len(raw)):
        assert raw.channel(i, proxy8).tobytes() == compact.channel(i, proxy8).tobytes()
    images = sum(p.stat().st_size for p in (rgbt640 / "images").rglob("*.jpg"))
    cache = sum(p.stat().st_size for p in compact.folder.rglob("*") if p.is_file())
    raw_size = sum(p.stat().st_size for p in raw.folder.rglob("*") if p.is_file())
    assert cache <= 1.5 * images and raw_size > 3 * images


def test_a_changed_source_file_is_an_error_naming_it(rgbt640, tmp_path):
    import cv2

    compact = prepare("rgbt-tiny", _rgbt_cfg(rgbt640), cache_root=tmp_path / "c", progress=False)
    ref = compact.records[0]["src"]
    path = compact.sources[ref["base"]] / ref["rgb"]
    st = path.stat()
    img = cv2.imread(str(path))
    cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 60])  # re-encoded: different pixels
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))  # even with the old modification time
    reopened = type(compact)(compact.folder)
    with pytest.raises(DataError, match=f"{path.name}: source file changed since it was prepared"):
        reopened.rgb(0)  # what the data loader reads
    with pytest.raises(DataError, match=f"{path.name}: source file changed since it was prepared"):
        reopened[0]
    assert reopened.rgb(1).shape == (512, 640, 3)
    assert reopened.verify() and len(reopened.verify()) == 1
    path.unlink()
    with pytest.raises(DataError, match=f"{path.name}: source file of a prepared sample is missing"):
        type(compact)(compact.folder)[0]


# ------------------------------------------------------------------------------------------------ CLI
def test_prepare_prints_sizes_and_cache_lists_verifies_and_removes(rgbt640, tmp_path, cli_runner):
    cache = tmp_path / "c"
    out = cli_runner(["prepare", "--dataset", "rgbt-tiny", "--root", str(rgbt640), "--cache", str(cache)]).output
    assert "(compact form) beside" in out and "of source files" in out
    cli_runner(
        ["prepare", "--dataset", "rgbt-tiny", "--root", str(rgbt640), "--cache", str(cache), "--cache-form", "raw"]
    )
    (cache / "rgbt-tiny" / ".x.tmp").mkdir()
    os.utime(cache / "rgbt-tiny" / ".x.tmp", (0, 0))  # an interrupted preparation's leftover
    listed = cli_runner(["cache", "list", "--cache", str(cache)]).output
    assert max(map(len, listed.splitlines())) <= 100
    assert "compact" in listed and "raw" in listed and "3 prepared" in listed
    assert "ok (4 samples)" in cli_runner(["cache", "verify", "--cache", str(cache)]).output
    dry = cli_runner(["cache", "rm", "--unused", "--dry-run", "--cache", str(cache)]).output
    assert "would remove rgbt-tiny/.x.tmp" in dry and "raw" not in dry
    assert (cache / "rgbt-tiny" / ".x.tmp").exists()
    cli_runner(["cache", "rm", "--unused", "--cache", str(cache)])
    assert not (cache / "rgbt-tiny" / ".x.tmp").exists() and len(list((cache / "rgbt-tiny").iterdir())) == 2
    raw = next(p.name for p in (cache / "rgbt-tiny").iterdir() if p.name.endswith("-raw"))
    assert "freed" in cli_runner(["cache", "rm", f"rgbt-tiny/{raw}", "--cache", str(cache)]).output
    assert [p.name for p in (cache / "rgbt-tiny").iterdir()] == [raw.removesuffix("-raw")]
    bad = cli_runner(["cache", "rm", "m3fd", "--cache", str(cache)])
    assert bad.exit_code != 0 and "no prepared dataset 'm3fd'" in bad.output
    bad = cli_runner(["cache", "rm", "--cache", str(cache)])
    assert bad.exit_code != 0 and "or pass --unused" in bad.output


def test_a_raw_cache_from_before_cache_forms_is_prepared_again_compact(tiny, tmp_path):
    cfg = synth_cfg(tiny)
    raw = prepare("m3t-synth", cfg, cache_root=tmp_path / "c", progress=False, form="raw")
    old = raw.folder.with_name(raw.folder.name.removesuffix("-raw"))
    raw.folder.rename(old)  # the raw layout in the default folder, as written before cache forms existed
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["form"]
    (old / "manifest.json").write_text(json.dumps(manifest))
    ds = prepare("m3t-synth", cfg, cache_root=tmp_path / "c", progress=False)
    assert ds.form == "compact" and not ds.from_cache and ds.folder == old and not (old / "rgb.u8").exists()
