"""``harness score`` (predictions made elsewhere, scored on a fold) and ``harness export-predictions``."""

from __future__ import annotations

from typing import Any, Callable

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def _fmt(v) -> str:
    return "-" if v is None else f"{100 * float(v):.1f}"


def _frame_option(frames: tuple[str, ...], help: str) -> Callable[[Any], Any]:
    """``--frame``: the image frame boxes are in, one of ``frames`` (the first by default)."""
    return opt.choice_option("--frame", choices=frames, help=help)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="score-route")
    @click.argument("runs", nargs=-1, required=True, type=click.Path(file_okay=False, exists=True))
    def score_route_cmd(runs: tuple[str, ...]) -> None:
        """Score finished runs' held-out folds under the registration route a new flight gets.

        Each run's raw held-out captures go through `harness screen`'s front end with its default options (each
        inspection group registered automatically, pooled over its captures; the factory prior where that fails),
        and once with the prior alone; the scores are written to RUN/screening_route.json beside metrics.json and
        shown by `harness report` ("accuracy under the screening route")."""
        from harness.screen.route import score_screening_route, summary_lines

        for run in runs:
            result = score_screening_route(run)
            click.echo(f"{run}:")
            for line in summary_lines(result):
                click.echo(f"  {line}")
            click.echo(f"  -> {run}/screening_route.json")

    @cli.command(name="score")
    @click.option("--dataset", required=True, help="Dataset name (see `harness list`).")
    @opt.folds_option(
        one=True, required=True, old=("--fold",), help="The held-out fold the predictions are for, e.g. P1."
    )
    @opt.input_file_option(
        "--predictions",
        required=True,
        help="COCO results JSON: [{image_id, category_id, bbox [x,y,w,h], score}, ...].",
    )
    @opt.choice_option(
        "--box-format",
        choices=("xywh", "xyxy"),
        help="How each bbox is written: COCO's x, y, w, h, or corners x1, y1, x2, y2.",
    )
    @click.option("--name", required=True, help="Name of the external detector; stored as external/NAME.")
    @_frame_option(
        ("prepared", "thermal", "rgb"),
        "Frame of the boxes: the harness's prepared frame, or the original "
        "thermal or RGB image (moved like the ground truth).",
    )
    @opt.input_file_option(
        "--images",
        help="COCO JSON of the images (and categories) the predictions refer to; fold images it does "
        "not list count as missing.",
    )
    @click.option(
        "--image-key",
        default="file_name",
        show_default=True,
        help="Field naming each image (in the predictions or the image list); image_id reads the "
        "numeric file stems Ultralytics writes as ids.",
    )
    @click.option(
        "--category-map",
        default=None,
        metavar="THEIR=OURS,...|FILE.json",
        help="Their category ids or names -> the dataset's names [default: by name].",
    )
    @click.option("--params", type=float, default=None, help="Parameters of the external model, millions.")
    @click.option("--gflops", type=float, default=None, help="GFLOPs of the external model at 640.")
    @click.option("--root", default=None, help="Dataset root folder (as for prepare).")
    @opt.profile_option()
    @opt.config_options()
    @opt.store_option()
    @click.option("--force", is_flag=True, help="Replace an earlier score of the same name.")
    @click.option(
        "--allow-implausible",
        is_flag=True,
        help="Score predictions that look misread (unknown images or categories, shifted ids, "
        "normalised or corner boxes, boxes mostly outside the frame) as read, and label the stored "
        "result, instead of refusing.",
    )
    @opt.no_progress_option()
    def score_cmd(
        dataset: str, folds: str, predictions: str, name: str, category_map: str | None, **settings: Any
    ) -> None:
        """Score predictions made by another codebase against the prepared ground truth of one fold.

        The result is stored as a run of detector external/NAME, so `harness report`, `compare-detectors` and
        the paired bootstrap show it beside the trained detectors. Predictions that look misread (on unknown
        images or categories, ids that fit only shifted by one, boxes normalised, written as corners or mostly
        outside the frame) are refused with what was seen, unless --allow-implausible.

        \b
        Example:
          harness score --dataset m3t --folds P1 --predictions yolo_preds.json --images val.json \\
              --frame rgb --name yolov8s-official --params 11.13 --gflops 28.6
        """
        from harness.scoring.external import parse_category_map, score_external

        fold = folds
        res = score_external(
            dataset, fold, predictions, name, category_map=parse_category_map(category_map), **settings
        )
        for line in res.matching.lines():
            click.echo(line, err=True)
        m = res.metrics["metrics"]
        s = res.metrics["support"]
        click.echo(
            f"external/{name} on {dataset} fold {fold}: mAP50 {_fmt(m.get('mAP50'))}  "
            f"mAP50:95 {_fmt(m.get('mAP50_95'))}  P {_fmt(m.get('precision'))}  "
            f"R {_fmt(m.get('recall'))}  ({s['images']} images, {s['instances']} instances) [{res.state}]"
        )
        click.echo(f"stored: {res.run_path}")

    @cli.command(name="export-predictions")
    @opt.profile_option(uses_config=False)
    @opt.store_option(reads=True)
    @click.option("--dataset", default=None, help="Only runs of this dataset.")
    @click.option("--detector", default=None, help="Only runs of this detector.")
    @click.option("--encoding", default=None, help="Only runs with this encoding.")
    @opt.folds_option(default=None, help="Only runs of these held-out folds, comma-separated [default: all].")
    @opt.seeds_option(old=("--seed",), help="Only runs of these training seeds, comma-separated [default: all].")
    @_frame_option(("thermal", "rgb", "prepared"), "Frame of the exported boxes.")
    @click.option("--out", required=True, type=click.Path(), help="Output .json for one run, or a folder for several.")
    def export_cmd(profile, store, dataset, detector, encoding, folds, seeds, frame, out):
        """Write finished runs' held-out predictions as COCO results in an original image frame.

        Beside each X.json goes X.images.json (images and categories) that `harness score --images` reads
        back; scoring the export gives the run's metrics to the last digit.
        """
        from harness.scoring.export import export_predictions

        fold_list = opt.split_list(folds) or None
        for e in export_predictions(
            opt.resolve_store(store, profile),
            dataset,
            detector,
            encoding,
            fold_list,
            opt.parse_seeds(seeds),
            frame,
            out,
        ):
            inexact = f", {e.inexact} inexact" if e.inexact else ""
            click.echo(
                f"{e.run}: {e.detections} detections{inexact} on {e.images} images -> {e.path} "
                f"(image list {e.images_path.name})"
            )
