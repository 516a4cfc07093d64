"""``harness screen``: a finished run's detector over a new flight's raw captures (``harness.screen``)."""

from __future__ import annotations

import os
from typing import Any

import click

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `harness run`: shared CPUs, before torch is imported

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def _focal(text: str | None) -> tuple[float, float] | None:
    if not text:
        return None
    try:
        wide, thermal = (float(v) for v in text.split(","))
    except ValueError:
        raise click.BadParameter(f"{text!r}: expected WIDE,THERMAL in mm, e.g. 24,40") from None
    return wide, thermal


def summary_lines(res) -> list[str]:
    """What the command prints: counts per class, timings, failures and the frames registered by the prior."""
    from harness.textable import text_table

    lines = [
        f"screened {res.screened} frame(s) now, {res.skipped_done} earlier; {res.with_findings} with findings "
        f"(threshold {res.threshold:g}: {res.threshold_source})"
    ]
    if res.counts:
        from harness.screen.job import count_line

        lines.append(count_line(res.counts))
    if res.findings:
        rows = [[c, str(n)] for c, n in sorted(res.findings.items(), key=lambda kv: -kv[1])]
        lines.append(text_table(["class", "findings"], rows, "lr"))
    t = res.timings.get("per_frame_s") or {}
    if res.screened and t.get("model"):
        ms = {k: 1000 * (v or 0.0) for k, v in t.items()}
        lines.append(
            f"per frame: decode {ms['decode']:.0f} ms, undistort+register+warp {ms['align']:.0f} ms, "
            f"fourth channel {ms['encode']:.0f} ms, model {ms['model']:.0f} ms; front end = "
            f"{100 * res.timings['frontend_over_model']:.0f} % of the model's time; "
            f"{res.timings['frames_per_s']:.2f} frames/s overall"
        )
    if (res.temperatures or {}).get("approximate_frames"):
        from harness.screen.job import approximate_line

        lines.append(approximate_line(res.temperatures))
    pos = res.positions or {}
    if pos.get("exif") or pos.get("none"):
        lines.append(
            f"positions: {pos.get('xmp', 0)} frame(s) from DJI XMP, {pos.get('exif', 0)} from EXIF GPS "
            f"(gps_source exif in the outputs), {pos.get('none', 0)} without GPS"
        )
    for frame, why in res.rejected:
        lines.append(f"registration check failed, screened with the factory prior: {frame} ({why})")
    if res.failures:
        from harness.screen.job import grouped_failures

        lines.append(f"{len(res.failures)} bad file(s), skipped:")
        lines += [f"  {path}: {reason}" for path, reason in grouped_failures(res.failures)]
    lines.append(f"results: {res.out} (findings.csv, findings.geojson, index.html, manifest.json)")
    return lines


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="screen")
    @click.argument("flight", type=click.Path(file_okay=False, path_type=str))
    @opt.path_option(
        "--run",
        file_okay=False,
        exists=True,
        help="A finished run's folder in the results store: its model, sensing and encoding are used.",
    )
    @opt.input_file_option("--weights", help="A checkpoint instead of a run (with --detector and --dataset).")
    @click.option("--detector", default=None, help="With --weights: the detector the checkpoint is of.")
    @click.option("--dataset", default=None, help="With --weights: its categories, protocol and encoding.")
    @click.option("--encoding", default=None, help="With --weights: the encoding [default: the dataset's].")
    @opt.profile_option(help="With --weights: the run profile (configs/profiles/).")
    @opt.config_options(help_set="With --weights: override one config key (repeatable).")
    @click.option("--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
    @opt.choice_option(
        "--backend",
        choices=("torch", "onnx"),
        help="PyTorch, or the model's ONNX export in ONNX Runtime (exported into --out).",
    )
    @click.option("--device", default="cpu", show_default=True, help="Torch device (cpu, cuda).")
    @click.option(
        "--conf",
        type=click.FloatRange(0.0, 1.0),
        default=None,
        help="Report findings scoring at least this [default: the run's operating point].",
    )
    @opt.input_file_option(
        "--homography",
        help="A homographies YAML (undistorted wide pixels of the calibration K -> thermal pixels) used for "
        "every frame instead of automatic registration.",
    )
    @click.option("--group", default=None, help="The entry of --homography to use when it holds several.")
    @opt.input_file_option(
        "--rgb-camera", help="Wide camera calibration [default: the run's, from its config or prepared data]."
    )
    @opt.input_file_option("--thermal-camera", help="Thermal camera calibration [default: the run's].")
    @click.option("--no-undistort", is_flag=True, help="No lens undistortion (a run whose data had none).")
    @click.option(
        "--focal-35mm",
        default=None,
        metavar="WIDE,THERMAL",
        help="35-mm focal lengths for the factory prior when the EXIF lacks them, e.g. 24,40.",
    )
    @opt.choice_option(
        "--fallback",
        choices=("prior", "skip"),
        help="A group (or frame) whose automatic registration fails its check: screened with the factory "
        "prior and listed with its expected error, or listed and not screened.",
    )
    @opt.choice_option(
        "--rgb-decode",
        choices=("auto", "full"),
        help="auto: decode the wide JPEG at 1/2, 1/4 or 1/8 where the warp shrinks it by 2.2x or more, "
        "keeping at least 0.85 wide pixel per thermal pixel; full: always in full (bit-identical "
        "to the training data).",
    )
    @opt.choice_option(
        "--register",
        choices=("group", "frame"),
        help="Automatic registration once per inspection group, pooled over its captures (those within "
        "the run's sensing.groups.gap_s of each other; as the datasets register), or for every frame "
        "on its own.",
    )
    @opt.workers_option("Processes for the front end (decode, register, warp, fourth channel).")
    @click.option(
        "--threads",
        type=click.IntRange(min=1),
        default=None,
        help="Threads for the model (torch and ONNX Runtime) [default: torch's].",
    )
    @opt.decode_route_options()
    @click.option("--fail-fast", is_flag=True, help="Stop at the first bad file.")
    @click.option("--force", is_flag=True, help="Replace a screen in --out made with another model or settings.")
    @click.option("--no-overlays", is_flag=True, help="No overlay and thumbnail pictures.")
    @opt.no_progress_option()
    def screen_cmd(focal_35mm: str | None, no_overlays: bool, **request: Any) -> None:
        """Screen FLIGHT (a folder of DJI _W / _T captures) with a benchmarked detector.

        Each capture goes through the sensing pipeline and encoding the run was trained with (decode to C,
        undistort, register, warp, crop, fourth channel), then its model. Writes findings.csv and
        findings.geojson (class, score, boxes in thermal and RGB pixels, box temperatures and contrast, GPS
        and gimbal), an overlay per frame with findings, index.html and manifest.json. A re-run skips frames
        done. Bad files are listed and skipped (exit status 1).

        \b
        Example:
          harness screen flights/0603 --run results/paper/m3t/ours/c2/P1/seed0 --out screens/0603
        """
        from harness.errors import PartlyDone
        from harness.progress import progress_on
        from harness.screen import ScreenRequest, screen

        req = ScreenRequest(focal_35mm=_focal(focal_35mm), progress=progress_on(), overlays=not no_overlays, **request)
        res = screen(req)
        for line in summary_lines(res):
            click.echo(line)
        if res.nothing_screened:
            raise PartlyDone(f"nothing was screened: {res.why_nothing}")
        if not res.ok:
            raise PartlyDone(f"{len(res.failures)} bad file(s) skipped (listed above)")
