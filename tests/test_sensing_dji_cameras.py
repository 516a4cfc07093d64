"""Other DJI thermal cameras than the M3T: H20T (dirp) and M2EA (iirp without the APP4 tag) decode like DJI's
Thermal SDK; layouts whose temperatures need tables or code the file does not carry (hirp, the M4T's
emissivity re-mapping) are refused by default with the camera model, the format and both options (converter,
approximate) named; the correction's lookup table gives the same float32 values as the per-value correction;
the M3T dataset adapter reads these files too."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SHARED
from harness.errors import ConfigError, DataError
from harness.sensing import dji_correction as dc
from harness.sensing import dji_formats, jpeg
from harness.sensing.radiometry import read_rjpeg, read_thermal, write_rjpeg

CAMERAS = SHARED / "data" / "dji-rjpeg-cameras"
M3T = SHARED / "data" / "dji-m3t-rjpeg"
needs_cameras = pytest.mark.skipif(not CAMERAS.is_dir(), reason=f"{CAMERAS} not present")
DECODED = {"h20t_dirp": ("dirp", "ZH20T"), "m2ea_iirp": ("iirp", "MAVIC2-ENTERPRISE-ADVANCED")}
ALL = {
    **DECODED,
    "m4t_iirp": ("iirp", "M4T"),
    "m3td_hirp_a": ("hirp", "M3TD"),
    "m3td_hirp_b": ("hirp", "M3TD"),
    "m3td_hirp_c": ("hirp", "M3TD"),
}


@needs_cameras
@pytest.mark.parametrize("name", sorted(DECODED))
def test_decoded_cameras_match_the_sdk_reference(name):
    ref = np.load(CAMERAS / f"{name}_reference.npz")
    rj = read_rjpeg(CAMERAS / f"{name}.jpg")
    assert (rj.fmt, rj.exif["Model"], rj.decoder) == (*DECODED[name], "dji")
    np.testing.assert_array_equal(rj.raw14, ref["raw14"])
    t, info = read_thermal(CAMERAS / f"{name}.jpg")
    assert t.dtype == np.float32 and t.shape == (512, 640) and info["decoder"] == "dji"
    d = np.abs(t.astype(np.float64) - ref["temp_c"])
    assert d.max() <= 0.05
    assert d.max() == 0.0  # float32 steps in the SDK's order: bit for bit on these files
    np.testing.assert_array_equal(rj.deci_celsius(), ref["temp_dc"])


@needs_cameras
@pytest.mark.parametrize("name", sorted(ALL))
def test_original_raw_of_every_camera_is_exact(name):
    fmt, model, raw = dji_formats.read_original_raw(CAMERAS / f"{name}.jpg")
    assert (fmt, model) == ALL[name]
    np.testing.assert_array_equal(raw, np.load(CAMERAS / f"{name}_reference.npz")["raw14"])


@needs_cameras
@pytest.mark.parametrize("decoder", ["auto", "dji", "blackbody"])
def test_hirp_is_refused_naming_camera_and_format(decoder):
    refused = r"m3td_hirp_a\.jpg: camera 'M3TD', DJI R-JPEG format 'hirp'.*--converter dji_irp.*no approximate"
    with pytest.raises(dji_formats.UnsupportedFormat, match=refused):
        read_rjpeg(CAMERAS / "m3td_hirp_a.jpg", decoder)
    with pytest.raises(dji_formats.UnsupportedFormat, match=r"format 'hirp'.*no approximate route"):
        read_rjpeg(CAMERAS / "m3td_hirp_a.jpg", approximate=True)


@needs_cameras
def test_m4t_is_refused_by_default_naming_camera_format_and_both_options():
    path = CAMERAS / "m4t_iirp.jpg"
    with pytest.raises(
        dc.UnsupportedCorrection,
        match=r"camera 'M4T', DJI R-JPEG format 'iirp' \(APP4 format "
        r"version 0x300\).*emissivity.*--converter dji_irp",
    ):
        read_rjpeg(path, decoder="dji")
    with pytest.raises(
        dc.UnsupportedCorrection,
        match=r"m4t_iirp\.jpg: camera 'M4T', DJI R-JPEG format 'iirp'.*"
        r"--converter dji_irp.*--approximate",
    ) as err:
        read_rjpeg(path)
    assert err.value.kind == "emissivity-remap"
    rj = read_rjpeg(path, decoder="blackbody")  # uncorrected only when asked for
    assert rj.decoder == "blackbody"
    np.testing.assert_array_equal(rj.raw14, np.load(CAMERAS / "m4t_iirp_reference.npz")["raw14"])


@needs_cameras
def test_dirp_overrides_follow_the_sdk_ranges():
    rj = read_rjpeg(CAMERAS / "h20t_dirp.jpg")
    base = rj.corrected_c()
    lower_e = rj.corrected_c(emissivity=0.8)
    warm = base > 30.0  # well above the 23 C reflected temperature: a lower emissivity reads hotter
    assert (lower_e[warm] > base[warm]).all()
    with pytest.raises(ConfigError, match="humidity=10 %.*20..100"):
        rj.corrected_c(humidity=10.0)
    with pytest.raises(ConfigError, match="'ambient' does not apply to dirp"):
        rj.corrected_c(ambient=20.0)
    with pytest.raises(DataError, match="not blackbody counts"):
        read_rjpeg(CAMERAS / "h20t_dirp.jpg", decoder="blackbody")


@needs_cameras
def test_decode_command_decodes_what_it_can_and_names_the_rest(tmp_path, cli_runner):
    result = cli_runner(["sensing", "decode", str(CAMERAS), "--out", str(tmp_path)])
    assert result.exit_code == 1
    for name in ("h20t_dirp", "m2ea_iirp"):
        assert (tmp_path / f"{name}.png").is_file()
    assert not (tmp_path / "m4t_iirp.png").exists()  # no silent uncorrected fallback
    assert "m4t_iirp.jpg: camera 'M4T', DJI R-JPEG format 'iirp'" in result.output
    for name in ("m3td_hirp_a", "m3td_hirp_b", "m3td_hirp_c"):
        assert f"{name}.jpg: camera 'M3TD', DJI R-JPEG format 'hirp'" in result.output
    t, _ = read_thermal(tmp_path / "h20t_dirp.png")  # centi-kelvin: within 0.005 C of the reference
    assert np.abs(t - np.load(CAMERAS / "h20t_dirp_reference.npz")["temp_c"]).max() <= 0.0051


def test_unknown_camera_is_refused_naming_the_model(tmp_path):
    data = bytearray(
        write_rjpeg(tmp_path / "ok.jpg", np.full((8, 8), 20.0, np.float32), exif={"Model": "XT2"}).read_bytes()
    )
    app4 = next(s for s in jpeg.read_segments(bytes(data)).segments if s.marker == jpeg.APP4)
    data[app4.offset + 4 : app4.offset + 8] = b"\x00\x00\x00\x00"  # no format tag: the model decides
    path = tmp_path / "xt2.jpg"
    path.write_bytes(bytes(data))
    with pytest.raises(dji_formats.UnsupportedFormat, match=r"xt2\.jpg: camera 'XT2' does not write"):
        read_rjpeg(path)
    assert dji_formats.detect(None, "XT S") == "dirp-g"
    assert "camera 'XT S', DJI R-JPEG format 'dirp-g'" in str(dji_formats.refusal("f.jpg", "dirp-g", "XT S"))


@pytest.mark.skipif(not M3T.is_dir() or not CAMERAS.is_dir(), reason="shared R-JPEG samples not present")
@pytest.mark.parametrize("path", [M3T / "m3t_a.jpg", CAMERAS / "m2ea_iirp.jpg"], ids=["m3t", "m2ea"])
def test_lookup_table_equals_the_per_value_correction(path):
    rj = read_rjpeg(path)
    p = rj.correction_params()
    args = (rj.tau_table, p["emissivity"], p["distance"], p["humidity"], p["reflected"], p["atmosphere"])
    np.testing.assert_array_equal(dc.correct_raw14(rj.raw14, *args), dc.correct_temperature(rj.blackbody_c(), *args))


@needs_cameras
def test_temperatures_past_the_filled_table_rows_are_missing_not_invented():
    rj = read_rjpeg(CAMERAS / "m2ea_iirp.jpg")
    table = rj.tau_table
    assert 0 < table.valid_rows < len(table.temps_k)  # M2EA fills the rows up to its measuring range
    raw = np.array([[4800, int((table.valid_below_k + 10.0) * 16)]], dtype=np.uint16)
    p = rj.correction_params()
    out = dc.correct_raw14(raw, table, p["emissivity"], p["distance"], p["humidity"], p["reflected"], p["atmosphere"])
    assert np.isfinite(out[0, 0]) and np.isnan(out[0, 1])


@needs_cameras
def test_m3t_dataset_adapter_reads_other_cameras_thermal(tiny_source):
    from adapters.datasets.m3t import RawAligner, SkipPair, open_m3t

    aligner = RawAligner(open_m3t(tiny_source))
    temp, ir8, info = aligner.read_thermal(CAMERAS / "h20t_dirp.jpg")
    assert info["decoder"] == "dji" and ir8.shape == temp.shape == (512, 640)
    np.testing.assert_array_equal(temp, np.load(CAMERAS / "h20t_dirp_reference.npz")["temp_c"])
    with pytest.raises(SkipPair, match="camera 'M3TD', DJI R-JPEG format 'hirp'"):
        aligner.read_thermal(CAMERAS / "m3td_hirp_b.jpg")
