"""``harness weights import``: official checkpoints of other codebases to safetensors, without running their code."""

from __future__ import annotations

import json

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def summary_line(info: dict) -> str:
    lay = info["layout"]
    parts = [
        lay["family"],
        f"scale {lay['scale'] or '?'}",
        f"nc {lay['nc'] if lay['nc'] is not None else '?'}",
        f"{lay['in_channels'] or '?'} input channel(s)",
    ]
    if lay["two_stream"]:
        parts.append("two streams")
    return (
        f"{info['tensors']} tensors, {info['parameters'] / 1e6:.2f} M values from {info['weights_from']!r} "
        f"({', '.join(parts)})"
    )


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.group(name="weights")
    def weights_group() -> None:
        """Weights from other codebases (Ultralytics YOLOv8, YOLOv5, ICAFusion checkpoints)."""

    @weights_group.command(name="import")
    @click.argument("src", type=click.Path(dir_okay=False))
    @click.option("--out", required=True, type=click.Path(dir_okay=False), help="Output DST.safetensors.")
    @opt.format_option("text", "json", old_json=True)
    def import_cmd(src: str, out: str, fmt: str) -> None:
        """Convert a pickled checkpoint SRC into DST.safetensors plus DST.json, executing nothing from SRC.

        \b
        Reads Ultralytics (.pt from its trainer or YOLO.save()), YOLOv5 and ICAFusion checkpoints:
        tensors and containers are rebuilt, every other class becomes an inert placeholder, any other
        call the file asks for is refused, and every size is bounded by the file's own (a hostile file
        gets a one-line error). EMA weights are taken when present; half precision is cast to float32.
        Use the result with `harness run --init DST.safetensors` or `--set model.weights=DST.safetensors`.
        """
        from harness.weights import import_checkpoint

        res = import_checkpoint(src, out)
        if fmt == "json":  # the sidecar's JSON
            click.echo(json.dumps(res.info, indent=2))
            return
        lay = res.info["layout"]
        click.echo(f"{res.weights}: {summary_line(res.info)}")
        click.echo(f"sidecar: {res.sidecar}")
        if lay["suggested_detector"]:
            click.echo(f"use:     harness run --detector {lay['suggested_detector']} ... --init {res.weights}")
        for note in lay["notes"]:
            click.echo(f"note:    {note}")
