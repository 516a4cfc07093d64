"""``harness sensing ...``: radiometric decoding, calibration, registration and the sensor-level analyses."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def _size(value: str | None, what: str) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{what} must look like 640x512, got {value!r}") from None
    return w, h


def _write_result(
    result: dict[str, Any], analysis: str, dataset: str | None, store: Path | None, out: Path | None
) -> list[Path]:
    from harness.io import atomic_write_json
    from harness.sensing.analyses import nan_to_none

    clean = nan_to_none(result)
    written = []
    if out is not None:
        written.append(atomic_write_json(out, clean))
    if store and dataset:
        from harness.store import Store

        written.append(Store(store).write_sensing(dataset, analysis, clean))
    return written


def _route_cell(row: dict[str, Any]) -> str:
    """The route of one decoded file, short: ``dji``, ``approx. +-0.034 C``, ``dji_irp``, ``blackbody``."""
    route = row["route"]
    if route == "approximate" and row.get("approximate"):
        return f"approx. +-{row['approximate']['bound_c']:g} C"
    if route == "converter":
        return "dji_irp" if "dji_irp" in row.get("route_label", "") else "converter"
    return "blackbody (uncorr.)" if route == "blackbody" else route


def _num(value: float, digits: int) -> str:
    import math

    return "-" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def _method_option(what: str) -> Callable[[Any], Any]:
    """``--method lsq|ransac``: how ``register`` and ``registration-error`` fit a group's homography."""
    return opt.choice_option(
        "--method",
        choices=("lsq", "ransac"),
        help=f"{what}: least squares over all pairs, or RANSAC (outliers left out).",
    )


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.group(name="sensing")
    def sensing() -> None:
        """Sensing pipeline: decode R-JPEGs, calibrate cameras, register RGB to thermal, sensor-level analyses."""

    # ------------------------------------------------------------------------------------------------ decode
    @sensing.command(name="decode")
    @click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=Path))
    @click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Output folder.")
    @opt.choice_option(
        "--unit", choices=("centikelvin", "decicelsius", "celsius"), help="Storage unit of the temperature file."
    )
    @opt.option(
        "--file-type",
        "fmt",
        old=("--format",),
        type=click.Choice(["png", "tiff", "npy"]),
        default=None,
        help="File type of the temperature files [default: png for centikelvin, tiff otherwise].",
    )
    @click.option("--preview/--no-preview", default=False, help="Also write the 8-bit preview as <name>_ir8.png.")
    @opt.choice_option(
        "--decoder",
        choices=("auto", "dji", "blackbody"),
        help="auto: DJI's corrected temperature, or the route chosen below for files the harness cannot "
        "correct, else an error; dji: corrected or an error; blackbody: raw14/16-273.15, uncorrected.",
    )
    @click.option("--blackbody", is_flag=True, help="Same as --decoder blackbody.")
    @opt.decode_route_options()
    @click.option("--emissivity", type=float, default=None, help="Override the file's emissivity (0.1-1).")
    @click.option("--distance", type=float, default=None, help="Override the object distance, m (1-25).")
    @click.option("--humidity", type=float, default=None, help="Override the relative humidity, % (1-100).")
    @click.option(
        "--reflected",
        type=float,
        default=None,
        help="Override the reflected temperature, C (-40..100; M3T files also use it for the air).",
    )
    @opt.workers_option("Decode in this many processes.")
    @click.option("--fail-fast", is_flag=True, help="Stop at the first file that cannot be decoded.")
    @opt.no_progress_option()
    def decode_cmd(
        inputs: tuple[Path, ...],
        out_dir: Path,
        unit: str,
        fmt: str | None,
        preview: bool,
        decoder: str,
        blackbody: bool,
        approximate: bool,
        converter: str | None,
        dji_irp: str | None,
        converter_timeout: float | None,
        emissivity: float | None,
        distance: float | None,
        humidity: float | None,
        reflected: float | None,
        workers: int,
        fail_fast: bool,
    ) -> None:
        """Decode DJI R-JPEGs (files, or folders searched recursively) to temperature files (C) with a JSON
        sidecar stating the unit and the route.

        By default the temperature is DJI Thermal SDK's corrected one (emissivity, reflected temperature,
        atmospheric transmission from the file's APP5 table) at the file's measurement parameters or the ones
        given here; files the harness wrote itself (the synthetic generator) decode as blackbody. Files it cannot
        correct (hirp, girp, XT S, and tables only DJI's SDK holds) are refused naming camera and format, unless
        --converter or --approximate is given. docs/sensing.md has the camera table. Every readable file is
        decoded; the failures are listed at the end (exit status 1).
        """
        from harness.errors import PartlyDone
        from harness.progress import bar
        from harness.sensing.batch import DecodeOptions, decode_batch, format_failures
        from harness.sensing.dji_converter import resolve
        from harness.textable import text_table as _table

        overrides = {"emissivity": emissivity, "distance": distance, "humidity": humidity, "reflected": reflected}
        options = DecodeOptions(
            unit=unit,
            fmt=fmt,
            preview=preview,
            decoder="blackbody" if blackbody else decoder,
            overrides=overrides,
            approximate=approximate,
            converter=resolve(converter, dji_irp, converter_timeout),
        )
        with bar("decoding") as b:
            result = decode_batch(
                inputs,
                out_dir,
                options,
                workers=workers,
                fail_fast=fail_fast,
                progress=lambda done, total: b.update(completed=done, total=total),
            )
        rows = [
            [
                r["file"],
                r["size"],
                _route_cell(r),
                f"{r['min']:.2f}",
                f"{r['max']:.2f}",
                f"{r['mean']:.2f}",
                _num(r["emissivity"], 2),
                _num(r["distance"], 1),
                Path(r["written"]).name,
            ]
            for r in result.decoded
        ]
        if rows:
            click.echo(
                _table(
                    ["file", "size", "route", "min C", "max C", "mean C", "emissivity", "distance m", "written"],
                    rows,
                    align="lllrrrrrl",
                )
            )
        click.echo(format_failures(result))
        if result.failed:
            total = len(result.decoded) + len(result.failed)
            raise PartlyDone(f"{len(result.failed)} of {total} file(s) could not be decoded (listed above)")
        if not result.decoded:
            raise PartlyDone("nothing was decoded (no R-JPEG among the inputs)")

    # ------------------------------------------------------------------------------------------------ calibrate
    @sensing.command(name="calibrate")
    @click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
    @click.option("--pattern", required=True, help="Inner corners of the checkerboard, COLSxROWS (e.g. 9x6).")
    @click.option("--square", type=float, default=1.0, show_default=True, help="Square size (any unit).")
    @click.option("--thermal", is_flag=True, help="Thermal views (R-JPEG, temperature files or 8-bit frames).")
    @click.option("--name", default="", help="Camera name stored in the file.")
    @click.option("--out", type=click.Path(path_type=Path), required=True, help="Camera model YAML to write.")
    def calibrate_cmd(
        images: tuple[Path, ...], pattern: str, square: float, thermal: bool, name: str, out: Path
    ) -> None:
        """Calibrate one camera from checkerboard views and write its model (intrinsics, distortion, size)."""
        from harness.sensing.calibration import calibrate_checkerboard, load_view

        pat = _size(pattern, "--pattern")
        views = [(str(p), load_view(p, thermal=thermal)) for p in images]
        res = calibrate_checkerboard(
            views,
            pat,  # type: ignore[arg-type]
            square_size=square,
            thermal=thermal,
            name=name,
        )
        res.camera.save(out)
        cam = res.camera
        click.echo(f"{len(res.used)} of {len(views)} views used; RMS reprojection error {res.rms:.3f} px")
        if res.rejected:
            click.echo("board not found in: " + ", ".join(Path(r).name for r in res.rejected))
        click.echo(
            f"fx {cam.fx:.2f}  fy {cam.fy:.2f}  cx {cam.cx:.2f}  cy {cam.cy:.2f}  "
            f"dist {' '.join(f'{v:+.4f}' for v in cam.dist)}  -> {out}"
        )

    # ------------------------------------------------------------------------------------------------ register
    @sensing.command(name="register")
    @click.option(
        "--out",
        type=click.Path(path_type=Path),
        required=True,
        help="Homographies YAML to write (groups already in it are kept unless replaced).",
    )
    @opt.input_path_option("--landmarks", help="Landmarks CSV/JSON: one homography per group from its point pairs.")
    @_method_option("Fit to the landmarks")
    @click.option("--threshold", type=float, default=2.0, show_default=True, help="RANSAC inlier threshold, px.")
    @click.option(
        "--similarity",
        "similarities",
        multiple=True,
        metavar="GROUP=TX,TY,THETA,SCALE",
        help="A group's similarity parameters (thermal px, degrees, thermal px per RGB px). Repeatable.",
    )
    @click.option(
        "--auto",
        "auto_pairs",
        multiple=True,
        metavar="GROUP=RGB,THERMAL",
        help="Register a group automatically from one RGB image and one thermal file. Repeatable.",
    )
    @opt.option(
        "--start-homographies",
        "init_file",
        old=("--init",),
        type=click.Path(exists=True, path_type=Path),
        default=None,
        help="Homographies YAML to start --auto from (default: the group's entry in --out, "
        "else the EXIF focal-length prior, else RGB width fitted to thermal width).",
    )
    @click.option("--rgb-size", default=None, help="RGB image size WxH (centre of the similarity).")
    @click.option("--thermal-size", default=None, help="Thermal image size WxH (centre of the similarity).")
    @click.option(
        "--min-correlation",
        type=float,
        default=0.5,
        show_default=True,
        help="Automatic registration: reject pairs whose structure correlation stays below this.",
    )
    def register_cmd(
        out: Path,
        landmarks: Path | None,
        method: str,
        threshold: float,
        similarities: tuple[str, ...],
        auto_pairs: tuple[str, ...],
        init_file: Path | None,
        rgb_size: str | None,
        thermal_size: str | None,
        min_correlation: float,
    ) -> None:
        """Compute per-group RGB->thermal homographies and save them in an editable YAML file."""
        from harness.errors import DataError
        from harness.sensing import registration as reg
        from harness.textable import text_table as _table

        if not (landmarks or similarities or auto_pairs):
            raise click.UsageError("give --landmarks, --similarity or --auto")
        entries = reg.load_homography_entries(out) if out.exists() else {}
        starts = reg.load_homography_entries(init_file) if init_file else {}
        rows = []
        rs, ts = _size(rgb_size, "--rgb-size"), _size(thermal_size, "--thermal-size")
        if landmarks:
            try:
                fits = reg.fit_groups(reg.read_landmarks(landmarks), method, threshold)
            except DataError as exc:
                raise DataError(f"{landmarks}: {exc}") from None
            for group, fit in fits.items():
                entries[group] = fit.entry(rs, ts)
                rows.append([group, "landmarks", f"{int(fit.inliers.sum())}/{fit.pairs} pts, rmse {fit.rms_px:.2f} px"])
        for item in similarities:
            group, _, vals = item.partition("=")
            try:
                tx, ty, theta, scale = (float(v) for v in vals.split(","))
            except ValueError:
                raise click.BadParameter(f"--similarity {item!r}: expected GROUP=TX,TY,THETA,SCALE") from None
            entries[group] = reg.entry_from_similarity({"tx": tx, "ty": ty, "theta_deg": theta, "scale": scale}, rs, ts)
            rows.append([group, "similarity", f"t=({tx:g}, {ty:g}) theta={theta:g} deg scale={scale:g}"])
        for item in auto_pairs:
            group, _, files = item.partition("=")
            try:
                rgb_path, thermal_path = (Path(v) for v in files.split(","))
            except ValueError:
                raise click.BadParameter(f"--auto {item!r}: expected GROUP=RGB,THERMAL") from None
            res, rgb_shape, th_shape = reg.register_files(
                rgb_path, thermal_path, init=starts.get(group, entries.get(group)), min_correlation=min_correlation
            )
            status = "ok" if res.ok else f"REJECTED ({res.reason})"
            if res.ok:
                entries[group] = res.entry(rgb_shape, th_shape)
            rows.append(
                [group, "auto", f"correlation {res.correlation:.3f} (from {res.initial_correlation:.3f}), {status}"]
            )
        reg.save_homographies(out, entries)
        click.echo(_table(["group", "method", "result"], rows, align="lll"))
        click.echo(f"-> {out} ({len(entries)} group(s))")

    # ------------------------------------------------------------------------------------------------ analyses
    @sensing.command(name="registration-error")
    @opt.input_path_option(
        "--landmarks", required=True, help="Landmarks CSV (scene,group,rgb_x,rgb_y,thermal_x,thermal_y) or JSON."
    )
    @opt.input_path_option(
        "--homographies",
        help="Evaluate these per-group homographies; without, fit per group and score leave-one-out.",
    )
    @_method_option("Fit per group")
    @click.option(
        "--dataset", default=None, help="Dataset name: also write <store>/<dataset>/_sensing/registration_error.json."
    )
    @opt.profile_option(uses_config=False)
    @opt.store_option()
    @click.option("--out", type=click.Path(path_type=Path), default=None, help="Also write the JSON here.")
    @opt.input_path_option(
        "--truth",
        help="True per-group homographies: also report the landmarks' error under them and the fitted "
        "homographies' distance from them (default: ground_truth/homographies.yaml of a synthetic set "
        "when the landmarks are its registration/landmarks.json).",
    )
    def registration_error_cmd(
        landmarks: Path,
        homographies: Path | None,
        method: str,
        dataset: str | None,
        profile: str,
        store: Path | None,
        out: Path | None,
        truth: Path | None,
    ) -> None:
        """Registration error on landmark pairs: mean, median, P95 and per-scene mean, in thermal pixels."""
        from harness.sensing.analyses import format_registration_error, registration_error_study
        from harness.sensing.registration import load_homography_entries, read_landmarks, support_boxes

        lm = read_landmarks(landmarks)
        Hs, support = None, None
        if homographies is not None:
            entries = load_homography_entries(homographies)
            Hs = {g: e.H for g, e in entries.items()}
            support = support_boxes(entries)
        result = registration_error_study(lm, Hs, method=method, support=support)
        result.update(
            {
                "analysis": "registration_error",
                "landmarks_file": str(landmarks),
                "homographies_file": str(homographies) if homographies else None,
            }
        )
        click.echo(format_registration_error(result))
        beside = landmarks.parent.parent / "ground_truth" / "homographies.yaml"  # a synthetic set's layout
        truth = truth if truth is not None else (beside if beside.is_file() else None)
        if truth is not None:
            from harness.sensing.registration.truth import against_truth, format_against_truth

            true_entries = load_homography_entries(truth)
            sizes = {tuple(e.thermal_size) for e in true_entries.values() if e.thermal_size}
            result["truth"] = against_truth(
                lm,
                {g: e.H for g, e in true_entries.items()},
                Hs,
                next(iter(sizes)) if len(sizes) == 1 else None,  # type: ignore[arg-type]
                method=method,
            )
            result["truth_file"] = str(truth)
            click.echo("\n" + format_against_truth(result["truth"], result))
        for path in _write_result(result, "registration_error", dataset, opt.resolve_store(store, profile), out):
            click.echo(f"-> {path}")

    @sensing.command(name="displacement")
    @click.option("--dataset", default=None, help="Prepare (or reuse the cache of) this dataset.")
    @click.option(
        "--prepared",
        type=click.Path(exists=True, file_okay=False, path_type=Path),
        default=None,
        help="A prepared dataset folder instead of --dataset.",
    )
    @click.option(
        "--shifts", default=None, help="Comma-separated displacements in px [default: sensing.displacement.shifts]."
    )
    @click.option("--max-images", type=int, default=None, help="Use at most this many images.")
    @opt.option(
        "--set",
        "overrides",
        shared="set",
        multiple=True,
        metavar="KEY=VALUE",
        help="Override one config key, e.g. --set encoding.c2.sigma=11 (repeatable).",
    )
    @opt.profile_option(uses_config=False)
    @opt.store_option()
    @click.option("--no-store", is_flag=True, help="Do not write into the results store.")
    @click.option("--out", type=click.Path(path_type=Path), default=None, help="Also write the JSON here.")
    @opt.no_progress_option()
    def displacement_cmd(
        dataset: str | None,
        prepared: Path | None,
        shifts: str | None,
        max_images: int | None,
        overrides: tuple[str, ...],
        profile: str,
        store: Path | None,
        no_store: bool,
        out: Path | None,
    ) -> None:
        """How much C2 contrast boxes keep when the thermal map is shifted 2-15 px (R_c(d) in %)."""
        from harness.config import load_config
        from harness.errors import HarnessError
        from harness.progress import bar
        from harness.sensing.analyses import displacement_study, format_displacement
        from harness.sensing.options import SensingOptions

        if (dataset is None) == (prepared is None):
            raise click.UsageError("give exactly one of --dataset or --prepared")
        cfg = load_config(overrides=overrides)
        opts = SensingOptions.from_config(cfg)
        shift_list = [int(v) for v in shifts.split(",")] if shifts else list(opts.displacement_shifts)
        c2_params = {
            "sigma": 11.0,
            "percentile": 99.0,
            "floor": 0.05,
            **dict(cfg.get("encoding", {}).get("c2", {}) or {}),
        }
        if prepared is not None:
            from harness.cache import PreparedDataset

            data = PreparedDataset(prepared)
        else:
            try:
                from harness.cache import prepare
            except ImportError:
                raise HarnessError(
                    "this installation has no dataset preparation (harness.cache); "
                    "prepare the dataset elsewhere and pass --prepared DIR"
                ) from None
            data = prepare(dataset, cfg)  # type: ignore[arg-type]
        n = len(data) if max_images is None else min(len(data), max_images)
        with bar("displacement", total=n) as b:
            result = displacement_study(
                iter(data), data.categories, shift_list, max_images=max_images, progress=b.advance, **c2_params
            )
        result["dataset"] = data.name
        click.echo(format_displacement(result))
        target = None if no_store else opt.resolve_store(store, profile)
        for path in _write_result(result, "displacement", data.name, target, out):
            click.echo(f"-> {path}")
