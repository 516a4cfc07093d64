"""The shipped reference results hold on this installation: the installed packages prepare exactly the samples the
references were trained and scored on, and samples that differ only as a library release makes them differ are
compared with a label, while other samples are refused with the versions that differ.

The guard (``test_installed_environment_prepares_the_references_samples``) generates the default synthetic set and
prepares it here, then checks every content digest the references record. It fails when a package release changes
the samples (OpenCV 5.1.0 in place of the locked 5.0.0 does), so the next such release turns a test red instead of
the demo."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from harness import provenance
from harness.cache import fingerprint as FP
from harness.references import (
    FINGERPRINT,
    MANIFEST,
    ReferenceMismatchError,
    check_matched,
    load_references,
    resolve,
)
from harness.store import RunKey

REFS = resolve("shipped")


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    """The default synthetic set (small, seed 0), generated and prepared in this environment with the references'
    profile."""
    from adapters.datasets import synthetic as S
    from harness.cache import prepare
    from harness.config import load_config

    base = tmp_path_factory.mktemp("refsamples")
    root = base / "m3t-synth-small-seed0"
    S.generate(root, profile="small", seed=0, progress=False, workers=2)
    refs = load_references("shipped")
    cfg = load_config(refs.profile)
    cfg["dataset"] = {**(cfg.get("dataset") or {}), "root": str(root)}
    return prepare("m3t-synth", cfg, cache_root=base / "cache", progress=False)


@pytest.mark.slow
def test_installed_environment_prepares_the_references_samples(prepared):
    from harness.cache.folds import resolve_folds
    from harness.plugins import get_host

    refs = load_references("shipped")
    host = get_host()
    folds = {f.name: f for f in resolve_folds(host.dataset(refs.dataset), prepared, {"protocol": _protocol()})}
    wrong = []
    for key, want in refs.manifest["samples"].items():
        fold, enc = key.split("/")
        f = folds[fold]
        for split, groups in (("train", f.train_groups), ("held_out", f.val_groups)):
            have = prepared.content_digest(prepared.indices(list(groups)), host.encoding(enc), {})
            if have != want[split]:
                wrong.append(f"{key} {split}: {have[:12]} (references {want[split][:12]})")
    for fold, want in refs.manifest["aligned"].items():
        have = prepared.content_digest(prepared.indices(list(folds[fold].val_groups)))
        if have != want["held_out"]:
            wrong.append(f"{fold} aligned held_out: {have[:12]} (references {want['held_out'][:12]})")
    versions = provenance.differences(
        provenance.sample_environment(), refs.manifest.get("samples_environment") or {}, None, "references"
    )
    assert not wrong, (
        f"this environment prepares other samples than the shipped references' ({len(wrong)} digests differ: "
        f"{'; '.join(wrong[:3])}); package versions that differ: {', '.join(versions) or 'none recorded'}; "
        "install the locked environment (`make venv`, requirements.lock) or remake the references"
    )


@pytest.mark.slow
def test_fingerprint_of_the_installed_samples_equals_the_shipped_one(prepared):
    from harness.plugins import get_host

    ref = FP.load(REFS / FINGERPRINT)
    host = get_host()
    mine = FP.compute(prepared, [(host.encoding(n), {}) for n in ("c2", "ir8", "linear16", "none")])
    planes = [k.removesuffix("/hash") for k in ref if k.endswith("/hash")]
    assert set(planes) == {"rgb", "aligned", "enc:c2", "enc:ir8", "enc:linear16"}
    d = FP.compare(mine, ref, planes)
    assert d.identical, d.describe()


def _protocol():
    import yaml

    cfg = yaml.safe_load(next(iter(sorted(REFS.rglob("config.yaml")))).read_text(encoding="utf-8"))
    return cfg["protocol"]


# ------------------------------------------------------------------------------------------------- tolerance
def _shipped_fp():
    return {k: v.copy() for k, v in FP.load(REFS / FINGERPRINT).items()}


def test_release_sized_differences_are_within_tolerance_and_described():
    ref = _shipped_fp()
    mine = _shipped_fp()
    mine["boxes"][:5, 0] += np.float32(3.0517578e-05)  # one float32 ulp at 256 px
    changed = np.arange(0, len(mine["rgb/hash"]), 25)
    mine["rgb/hash"][changed] ^= 1
    mine["rgb/sum"][changed] += 1.0  # one grey level on one value of each of those tiles
    d = FP.compare(mine, ref, ["rgb", "aligned", "enc:c2"])
    assert not d.identical and d.within()
    text = d.describe()
    assert "boxes moved by at most 3.1e-05 px (5 of" in text
    assert f"RGB pixels: 4 % of 32-px tiles changed ({len(changed):,} of {len(ref['rgb/hash']):,})" in text
    assert "temperatures (or 8-bit thermal), c2 identical" in text


@pytest.mark.parametrize(
    "mutate, expected",
    [
        (lambda fp: fp["boxes"].__setitem__((3, 2), fp["boxes"][3, 2] + 0.5), "boxes moved by at most 0.5 px"),
        (lambda fp: fp["labels"].__setitem__(7, (fp["labels"][7] + 1) % 8), "other labels on 1 boxes"),
        (lambda fp: fp["enc:c2/sum"].__setitem__(slice(0, 80), fp["enc:c2/sum"][:80] + 1024 * 1.2), "c2: "),
        (lambda fp: fp["ids"].__setitem__(0, 10**9), "other images: 112 samples"),
        (lambda fp: fp["shape"].__setitem__((4, 0), 255), "other image sizes in 1 of 112 samples"),
    ],
    ids=["box-half-pixel", "label", "c2-tile-mean", "image-id", "size"],
)
def test_other_samples_are_beyond_tolerance(mutate, expected):
    ref, mine = _shipped_fp(), _shipped_fp()
    mutate(mine)
    if expected == "c2: ":
        mine["enc:c2/hash"][:80] ^= 1
    d = FP.compare(mine, ref, ["rgb", "aligned", "enc:c2"])
    assert not d.within()
    assert expected in d.describe()


# ------------------------------------------------------------------------------------------------- matching
def _fake_run(prepared, fold="P1", encoding="c2", digest="0" * 32, env=None):
    from harness.plugins import get_host

    val = ["P1"] if fold == "P1" else [fold]
    enc = get_host().encoding(encoding)
    held_out = prepared.content_digest(prepared.indices(val), enc, {})
    return SimpleNamespace(
        key=RunKey("m3t-synth", "mine", encoding, fold, 0),
        metrics={
            "samples": {"held_out": held_out if digest is None else digest, "prepared": str(prepared.folder)},
            "environment": env or {"opencv": "5.1.0", "numpy": "2.4.6", "torch": "2.13.0+cpu"},
        },
        config={"meta": {"val_groups": val}, "dataset": {}},
    ), held_out


def _refs_copy(tmp_path, held_out_p1_c2="f" * 32, mutate=None):
    dst = tmp_path / "refs"
    dst.mkdir()
    shutil.copyfile(REFS / MANIFEST, dst / MANIFEST)
    manifest = json.loads((dst / MANIFEST).read_text())
    manifest["samples"]["P1/c2"]["held_out"] = held_out_p1_c2
    (dst / MANIFEST).write_text(json.dumps(manifest))
    fp = _shipped_fp()
    if mutate:
        mutate(fp)
    FP.save(dst / FINGERPRINT, fp)
    return load_references(dst)


@pytest.mark.slow
def test_samples_within_tolerance_are_compared_with_a_label(prepared, tmp_path):
    run, held_out = _fake_run(prepared, digest=None)
    refs = _refs_copy(tmp_path)  # the references name another digest; their fingerprint is these samples'
    notes = check_matched(refs, [run])
    assert len(notes) == 1 and notes[0].startswith("Compared within the tolerance of a library release")
    assert "mine/c2/P1/seed0" in notes[0] and "boxes identical" in notes[0]
    assert "OpenCV 5.1.0, references 5.0.0" in notes[0]


@pytest.mark.slow
def test_samples_beyond_tolerance_are_refused_with_versions_and_the_lock(prepared, tmp_path):
    run, _ = _fake_run(prepared, digest=None)

    def shift(fp):
        fp["boxes"][:, :] += 2.0

    refs = _refs_copy(tmp_path, mutate=shift)
    with pytest.raises(ReferenceMismatchError) as err:
        check_matched(refs, [run])
    text = str(err.value)
    assert "boxes moved by at most 2 px" in text
    assert "OpenCV 5.1.0, references 5.0.0" in text and "make venv" in text


@pytest.mark.slow
def test_a_run_whose_prepared_data_changed_is_not_measured(prepared, tmp_path):
    run, _ = _fake_run(prepared, digest="1" * 32)  # its recorded digest is not what the folder now holds
    refs = _refs_copy(tmp_path)
    with pytest.raises(ReferenceMismatchError, match="no longer holds the samples it was run on"):
        check_matched(refs, [run])


def test_prepared_manifest_records_the_sample_packages(tmp_path):
    env = provenance.sample_environment()
    assert {"python", "numpy", "opencv", "scipy"} <= set(env)
    import cv2

    assert env["opencv"] == cv2.__version__
    assert provenance.differences({"opencv": "5.1.0"}, {"opencv": "5.0.0"}, None, "references") == [
        "OpenCV 5.1.0, references 5.0.0"
    ]


@pytest.mark.slow
def test_reusing_a_cache_made_with_other_versions_says_so(prepared, caplog):
    from harness.cache.preparation import note_other_versions
    from harness.cache.reader import PreparedDataset

    ds = PreparedDataset(prepared.folder)
    assert note_other_versions(ds) == []
    ds.manifest["environment"] = {**ds.manifest["environment"], "opencv": "4.0.0"}
    with caplog.at_level("WARNING"):
        diffs = note_other_versions(ds)
    assert diffs == [f"OpenCV {provenance.sample_environment()['opencv']}, prepared with 4.0.0"]
    assert "harness prepare --force" in caplog.text
