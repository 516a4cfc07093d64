"""DJI's temperature correction of iirp R-JPEGs: against DJI Thermal SDK reference decodes of real M3T files (when
the shared samples are present), hand-computed values of the equations, parameter overrides, and clear errors for
missing or damaged APP5 tables."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from conftest import SHARED
from harness.errors import ConfigError, DataError
from harness.sensing import dji_correction as dc
from harness.sensing import jpeg
from harness.sensing.radiometry import read_rjpeg, read_thermal, write_rjpeg

REAL = SHARED / "data" / "dji-m3t-rjpeg"
REAL_FILES = ["m3t_a", "m3t_b", "m3t_c"]
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} not present")


def _table(version: int = 0x14, fill: int = 16384, reflection: bool = False, humidity_flag: bool = False) -> bytes:
    """An APP5 payload: header with fields, then a 0x1C00-byte table of ``fill`` (or a callable of (i, j))."""
    head = np.full(128, 0xFFFF, dtype="<u2")
    head[0], head[1] = 0, version
    head[4:8] = (0, 0, 1 if humidity_flag else 0, 1)
    head[10:12] = (1, 1) if reflection else (0, 0)
    temps, dists = dc.tau_axes(version)
    tau = np.full((len(temps), len(dists)), fill, dtype="<u2")
    words = np.zeros(max(dc.OLD_TABLE_BYTES // 2, tau.size), dtype="<u2")
    words[: tau.size] = tau.ravel()
    return head.tobytes() + words.tobytes()


def _with_app5(src: bytes, payload: bytes | None) -> bytes:
    """``src`` (a JPEG) with its first APP5 segment replaced by ``payload`` (``None``: removed)."""
    layout = jpeg.read_segments(src)
    seg = next(s for s in layout.segments if s.marker == jpeg.APP5)
    end = seg.offset + 4 + len(seg.payload)
    return src[: seg.offset] + (jpeg.segment(jpeg.APP5, payload) if payload is not None else b"") + src[end:]


# ---------------------------------------------------------------------------------------------- real files
@needs_real
@pytest.mark.parametrize("name", REAL_FILES)
def test_corrected_temperature_matches_the_sdk_reference(name):
    rj = read_rjpeg(REAL / f"{name}.jpg")
    ref = np.load(REAL / f"{name}_reference.npz")
    assert rj.decoder == "dji" and rj.tau_table is not None
    t = rj.temperature_c
    assert t.dtype == np.float32 and t.shape == (512, 640)
    d = np.abs(t.astype(np.float64) - ref["temp_c"])
    assert d.max() <= 0.05
    assert d.max() == 0.0  # float32 rounding follows the SDK: bit for bit on these files
    # the correction is not a no-op: the blackbody temperature is 1.4-2.3 C below on average
    gap = ref["temp_c"].astype(np.float64) - rj.blackbody_c()
    assert gap.mean() > 1.0
    # dirp_measure's deci-C truncates toward zero
    np.testing.assert_array_equal(rj.deci_celsius(), ref["temp_dc"])


@needs_real
def test_real_app5_layout():
    data = (REAL / "m3t_a.jpg").read_bytes()
    app5 = jpeg.read_segments(data).payloads(jpeg.APP5)[0]
    assert len(app5) == 23818
    table = dc.parse_app5(app5, 0x200, "m3t_a.jpg")
    assert table.version == 0x14 and table.tau.shape == (56, 64) and table.humidity == 1 and not table.reflection
    assert table.tau[0, 0] == 16384  # no loss at 0.25 m, -25 C
    assert (np.diff(table.tau.astype(int), axis=1) <= 0).all()  # transmission falls with distance
    temps, dists = dc.tau_axes(0x14)
    assert temps[0] == pytest.approx(248.15) and temps[-1] == pytest.approx(1623.15)
    assert dists[0] == pytest.approx(0.25) and dists[19] == pytest.approx(1.2) and dists[-1] == pytest.approx(50.0)


@needs_real
def test_overrides_move_the_temperature_the_right_way():
    rj = read_rjpeg(REAL / "m3t_c.jpg")
    base = rj.corrected_c().astype(np.float64).mean()
    # re-measured at the file's values: identical
    np.testing.assert_array_equal(
        rj.corrected_c(emissivity=0.95, distance=5.0, humidity=50.0, reflected=25.0), rj.corrected_c()
    )
    assert rj.corrected_c(emissivity=0.85).mean() > base + 0.3  # less emissive: more of the signal is reflection
    assert rj.corrected_c(emissivity=1.0).mean() < base
    assert rj.corrected_c(distance=20.0).mean() > base + 0.1  # more air absorbs more
    assert rj.corrected_c(distance=1.0).mean() < base
    assert rj.corrected_c(humidity=95.0).mean() > base  # wetter air absorbs more
    assert rj.corrected_c(reflected=40.0).mean() < base - 1.0  # a warmer surrounding explains more of the signal
    np.testing.assert_array_equal(rj.blackbody_c(), read_rjpeg(REAL / "m3t_c.jpg", "blackbody").temperature_c)
    with pytest.raises(ConfigError, match="emissivity=0.05"):
        rj.corrected_c(emissivity=0.05)
    with pytest.raises(ConfigError, match="distance=40"):
        rj.corrected_c(distance=40.0)
    with pytest.raises(ConfigError, match="reflected"):  # M3T takes the air temperature from the reflected one
        rj.corrected_c(ambient=10.0)
    temp, info = read_thermal(REAL / "m3t_c.jpg", overrides={"emissivity": 0.85})
    assert info["decoder"] == "dji" and info["correction"]["emissivity"] == pytest.approx(0.85)
    np.testing.assert_array_equal(temp, rj.corrected_c(emissivity=0.85))


@needs_real
def test_damaged_or_missing_app5_is_a_clear_error(tmp_path):
    src = (REAL / "m3t_b.jpg").read_bytes()
    app5 = jpeg.read_segments(src).payloads(jpeg.APP5)[0]
    cut = tmp_path / "cut_table.jpg"
    cut.write_bytes(_with_app5(src, app5[:0x900]))
    with pytest.raises(DataError, match=r"cut_table\.jpg.*cut short.*blackbody"):
        read_rjpeg(cut)
    assert read_rjpeg(cut, decoder="blackbody").decoder == "blackbody"  # the way out the message names
    zeros = tmp_path / "zeros.jpg"
    zeros.write_bytes(_with_app5(src, app5[:0x100] + bytes(len(app5) - 0x100)))
    with pytest.raises(DataError, match=r"zeros\.jpg.*Q14"):
        read_thermal(zeros)
    tiny = tmp_path / "tiny.jpg"
    tiny.write_bytes(_with_app5(src, app5[:40]))
    with pytest.raises(DataError, match=r"tiny\.jpg.*header"):
        read_rjpeg(tiny)
    default = tmp_path / "default.jpg"
    default.write_bytes(_with_app5(src, b"\xff" * 4 + app5[4:]))
    with pytest.raises(dc.UnsupportedCorrection, match="default.jpg"):
        read_rjpeg(default, decoder="dji")
    with pytest.raises(
        dc.UnsupportedCorrection,
        match=r"default\.jpg: camera 'M3T'.*built-in default.*"
        r"--converter.*--approximate",
    ):
        read_rjpeg(default)  # auto: refused, no silent blackbody
    rj = read_rjpeg(default, approximate=True)  # the labelled approximate route, on request
    assert rj.decoder == "approximate" and rj.approximation.name == "builtin-tau-unity"
    none = tmp_path / "no_app5.jpg"
    none.write_bytes(_with_app5(src, None))
    with pytest.raises(dc.UnsupportedCorrection, match=r"no_app5\.jpg.*no APP5.*--converter"):
        read_rjpeg(none)
    with pytest.raises(dc.UnsupportedCorrection, match=r"no_app5\.jpg.*no APP5.*no approximate route"):
        read_rjpeg(none, approximate=True)
    with pytest.raises(DataError, match=r"no_app5\.jpg.*no APP5"):
        read_rjpeg(none, decoder="dji")
    rj = read_rjpeg(none, decoder="blackbody")
    assert rj.decoder == "blackbody"
    with pytest.raises(DataError, match=r"no_app5\.jpg.*no atmospheric-transmission table"):
        rj.corrected_c()
    with pytest.raises(ConfigError, match="decoder"):
        read_rjpeg(none, decoder="sdk")


# ---------------------------------------------------------------------------------------------- equations
def test_balance_hand_computed():
    def w(c):
        return (c + 273.15) ** 4

    # tau 1 (Q14 16384), emissivity 0.9, atmosphere 20 C: W0 = 0.9 W + 0.1 W(20)
    expect = ((w(40.0) - 0.1 * w(20.0)) / 0.9) ** 0.25 - 273.15
    got = dc.radiance_balance(np.array([40.0]), np.array([16384.0]), 0.9, 20.0)
    assert got[0] == pytest.approx(expect, abs=1e-4)
    # separate reflection: W0 = t e W + t (1-e) W_r + (1-t) W_a, t = 0.8
    t, e = 0.8, 0.9
    expect = ((w(40.0) - t * (1 - e) * w(10.0) - (1 - t) * w(20.0)) / (t * e)) ** 0.25 - 273.15
    got = dc.radiance_balance(np.array([40.0]), np.array([0.8 * 16384]), e, 20.0, reflected_c=10.0)
    assert got[0] == pytest.approx(expect, abs=1e-4)
    # a scene at the surrounding temperature stays there, whatever tau and emissivity
    assert dc.radiance_balance(np.array([20.0]), np.array([9000.0]), 0.5, 20.0)[0] == pytest.approx(20.0, abs=1e-4)


def test_tau_interpolation_and_humidity_hand_computed():
    temps, dists = dc.tau_axes(0x14)
    tau = (np.arange(len(temps))[:, None] * 10 + np.arange(len(dists))[None, :] * 100 + 5000).astype(np.uint16)
    table = dc.TauTable(
        tau=tau, temps_k=temps, distances_m=dists, version=0x14, humidity=1, reflection=False, max_distance=25.0
    )
    # 30 C = 303.15 K: a quarter of the way from 298.15 (row 2) to 323.15 (row 3); 5.25 m: half way 5.0 -> 5.5
    j = int(np.flatnonzero(np.isclose(dists, 5.0))[0])
    expect = 5000 + (2 + 0.2) * 10 + (j + 0.5) * 100
    assert dc.interpolate_tau(table, np.array([30.0]), 5.25)[0] == math.floor(expect + 0.5)
    # on a grid node: the cell itself
    assert dc.interpolate_tau(table, np.array([25.0]), 5.0)[0] == tau[2, j]
    # beyond the last distance: along temperature only, truncated; 30 C in float32 K is 303.149994, a hair
    # below a fifth of the row step, so 11320 + 2 - 1e-6 truncates to 11321
    assert tau[2, -1] == 11320
    assert dc.interpolate_tau(table, np.array([30.0]), 80.0)[0] == 11321
    # humidity: p_w at 50 % and 25 C is 0.5 * 611.2 * exp(17.67 * 25 / 268.5) = 1583 Pa
    assert dc.vapour_pressure_pa(0.5, 25.0) == 1583
    assert dc.vapour_pressure_pa(0.01, 25.0) == 800 and dc.vapour_pressure_pa(1.0, 60.0) == 3000
    tk = 40.0 + 273.15
    k = ((410.15 / tk) ** 4 - 1) * 0.01 - 0.04
    assert dc.humidity_exponent_coefficient(np.array([40.0]))[0] == pytest.approx(k, rel=1e-6)
    expect = math.trunc(12000 * (1583 / 1425) ** (k * math.log(5.0) * 1.4427))
    got = dc.humidity_adjusted_tau(np.array([12000.0]), np.array([40.0]), 0.5, 25.0, 5.0, version=1)[0]
    assert abs(got - expect) <= 1 and got < 12000  # float32 steps; humid air lowers the transmission
    assert dc.humidity_adjusted_tau(np.array([12000.0]), np.array([40.0]), 0.5, 25.0, 1.0)[0] == 12000  # ln 1 = 0


def test_perfect_transmission_and_emissivity_one_is_the_blackbody():
    table = dc.parse_app5(_table(fill=16384), 0x200, "unit")
    t0 = np.linspace(-10, 120, 200).astype(np.float32)
    out = dc.correct_temperature(t0, table, 1.0, 1.0, 50.0, 25.0, 25.0)
    np.testing.assert_allclose(out, t0, atol=1e-4)
    # lower transmission with emissivity 1: the object is further from the air temperature than it looks
    half = dc.parse_app5(_table(fill=8192), 0x200, "unit")
    out = dc.correct_temperature(np.array([40.0, 10.0], np.float32), half, 1.0, 1.0, 50.0, 25.0, 25.0)
    assert out[0] > 50.0 and out[1] < 0.0


def test_app5_header_variants():
    hdrless = bytes(0x100) + bytes(dc.OLD_TABLE_BYTES)
    with pytest.raises(DataError, match="Q14"):  # no header fields: table read from byte 0 (zeros)
        dc.parse_app5(hdrless, 0x200, "x.jpg")
    t = dc.parse_app5(_table(reflection=True), 0x200)
    assert t.reflection
    with pytest.raises(dc.UnsupportedCorrection, match="emissivity"):
        dc.parse_app5(_table(version=0x101), 0x200)
    with pytest.raises(DataError, match=r"x\.jpg.*45x88.*cut short"):  # v0300 tables have more cells
        dc.parse_app5(_table(version=0x102)[: 0x100 + dc.OLD_TABLE_BYTES], 0x300, "x.jpg")


# ---------------------------------------------------------------------------------------------- written files
def test_written_rjpeg_reads_back_by_the_blackbody_route_exactly(tmp_path):
    t = (5.0 + np.arange(48 * 64, dtype=np.float32).reshape(48, 64) / 1000).astype(np.float32)
    path = write_rjpeg(tmp_path / "w.jpg", t, params={"emissivity": 0.8, "distance": 20.0})
    rj = read_rjpeg(path)
    assert rj.decoder == "blackbody" and "only its header" in rj.decoder_note
    assert np.abs(rj.temperature_c - t).max() <= 1 / 32 + 1e-5
    temp, info = read_thermal(path)
    assert info["decoder"] == "blackbody" and np.array_equal(temp, rj.temperature_c)
    with pytest.raises(DataError, match=r"w\.jpg.*emissivity.*blackbody"):
        read_thermal(path, overrides={"emissivity": 0.9})
    with pytest.raises(DataError, match=r"w\.jpg.*blackbody"):
        read_rjpeg(path, decoder="dji")
    # the same picture with a camera-style table reads back corrected, differently from what was written
    layout = jpeg.read_segments(path.read_bytes())
    assert len(layout.payloads(jpeg.APP5)[0]) == dc.HEADER_BYTES
    tabled = tmp_path / "tabled.jpg"
    tabled.write_bytes(_with_app5(path.read_bytes(), _table(fill=14000)))
    rj2 = read_rjpeg(tabled)
    assert rj2.decoder == "dji"
    assert rj2.temperature_c.mean() < rj.temperature_c.mean()  # scene below the 25 C surrounding: corrected colder
    assert struct.unpack("<H", tabled.read_bytes()[:2])[0] == 0xD8FF


def test_decode_command_routes_and_overrides(tmp_path, cli_runner):
    t = np.full((16, 20), 30.0, np.float32)
    src = write_rjpeg(tmp_path / "s.jpg", t)
    res = cli_runner(["sensing", "decode", str(src), "--out", str(tmp_path / "o"), "--emissivity", "0.9"])
    assert res.exit_code == 1 and "s.jpg" in res.output and "blackbody" in res.output
    tabled = tmp_path / "tab.jpg"
    tabled.write_bytes(_with_app5(src.read_bytes(), _table(fill=15000)))
    res = cli_runner(["sensing", "decode", str(tabled), "--out", str(tmp_path / "o"), "--unit", "celsius"])
    assert res.exit_code == 0 and "dji" in res.output, res.output
    a, info = read_thermal(tmp_path / "o" / "tab.tif")
    res = cli_runner(
        ["sensing", "decode", str(tabled), "--out", str(tmp_path / "o2"), "--unit", "celsius", "--emissivity", "0.8"]
    )
    assert res.exit_code == 0, res.output
    b, _ = read_thermal(tmp_path / "o2" / "tab.tif")
    assert b.mean() > a.mean() > 30.0
    res = cli_runner(
        ["sensing", "decode", str(tabled), "--out", str(tmp_path / "o3"), "--unit", "celsius", "--blackbody"]
    )
    c, _ = read_thermal(tmp_path / "o3" / "tab.tif")
    assert res.exit_code == 0 and np.abs(c - 30.0).max() <= 1 / 32 + 1e-5
    res = cli_runner(["sensing", "decode", str(tabled), "--out", str(tmp_path / "o4"), "--distance", "40"])
    assert res.exit_code == 2 and "distance=40" in res.output and "Traceback" not in res.output


def test_config_selects_the_route_and_keys_the_cache():
    from harness.cache import cache_key
    from harness.config import load_config
    from harness.sensing.options import SensingOptions

    cfg = load_config()
    opts = SensingOptions.from_config(cfg)
    assert opts.decoder == "auto" and opts.measurement == {}
    sensing = dict(cfg["sensing"])
    custom = {**sensing, "radiometry": {**sensing["radiometry"], "emissivity": 0.9}}
    assert SensingOptions.from_config({"sensing": custom}).measurement == {"emissivity": 0.9}
    blackbody = {**sensing, "radiometry": {**sensing["radiometry"], "decoder": "blackbody"}}
    keys = {cache_key("fp", s, "m3t") for s in (sensing, custom, blackbody)}
    assert len(keys) == 3  # the decoded values differ, so do the prepared caches
