"""``harness profile`` (parameters, GFLOPs in labelled conventions, latency) and ``harness export`` (ONNX)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl
from harness.textable import text_table


def _fmt(x: Any, spec: str = ".2f") -> str:
    return "-" if x is None else format(x, spec)


def _lat(rec: Any) -> str:
    if not isinstance(rec, dict) or "median_ms" not in rec:
        return "error" if isinstance(rec, dict) and "error" in rec else "-"
    return f"{rec['median_ms']:.1f}/{rec['p90_ms']:.1f}"


def profile_rows(results: list[dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the profile table (one row per detector)."""
    header = [
        "Detector",
        "Input",
        "Params (M)",
        "ref",
        "unused params",
        "GFLOPs paper",
        "ref",
        "GFLOPs exact",
        "GFLOPs fvcore",
        "torch ms med/p90",
        "ORT ms med/p90",
    ]
    rows = []
    for r in results:
        if "error" in r:
            rows.append([r["detector"]] + ["error"] + ["-"] * (len(header) - 2))
            continue
        ref = r.get("reference") or {}
        flops = r["flops"]
        fv = flops.get("fvcore") or {}
        lat = r.get("latency") or {}
        opts = ", ".join(f"{k}={v}" for k, v in sorted((r.get("model_options") or {}).items()))
        rows.append(
            [
                r["detector"] + (f" [{opts}]" if opts else ""),
                "x".join(str(s[1]) for s in r["input"]["shapes"]) + "ch",
                f"{r['params']['fused'] / 1e6:.3f}",
                _fmt(ref.get("params_m"), ".2f"),
                f"{r['params']['unreachable_count'] - r['params'].get('frozen_unreachable_count', 0):,}",
                f"{flops['paper']['gflops']:.3f}",
                _fmt(ref.get("gflops"), ".2f"),
                f"{flops['exact']['gflops']:.3f}",
                _fmt(fv.get("gflops"), ".3f") if "error" not in fv else "error",
                _lat(lat.get("torch")),
                _lat(lat.get("onnxruntime")),
            ]
        )
    return header, rows


def format_profiles(results: list[dict[str, Any]]) -> str:
    """The table plus the notes that make its numbers unambiguous."""
    from harness.profiling import CONVENTIONS

    header, rows = profile_rows(results)
    out = [text_table(header, rows), ""]
    failed = [r for r in results if "error" in r]
    results = [r for r in results if "error" not in r]
    for r in failed:
        out.append(f"{r['detector']}: not profiled: {r['error']}")
    if results:
        r0 = results[0]
        unfolded = [r["detector"] for r in results if not r["params"].get("bn_folded")]
        params = (
            "BN-folded parameter count"
            if not unfolded
            else f"parameter count, BN-folded except {', '.join(unfolded)} (no fold declared: as built)"
        )
        out.append(
            f"at {r0['imgsz']}x{r0['imgsz']}, batch 1, {r0['num_classes']} classes; Params = {params}; "
            f"'ref' = the detector's published figures, shown only beside the configuration they were "
            f"published for (its default model options, classes and input size)."
        )
    for name, text in CONVENTIONS.items():
        out.append(f"GFLOPs {name}: {text}.")
    for r in results:
        if r.get("label"):
            out.append(f"{r['detector']}: {r['label']}")
        lat = r.get("latency") or {}
        t, o = lat.get("torch") or {}, lat.get("onnxruntime") or {}
        if "median_ms" in t:
            ort = f", onnxruntime {o['threads']} thread(s) ({o['provider']})" if "median_ms" in o else ""
            out.append(
                f"{r['detector']}: latency over {t['runs']} runs after {t['warmup']} warm-up, torch "
                f"{t['threads']} thread(s) on {t['device']}" + ort
            )
        p = r["params"]
        frozen = set(p.get("frozen_unreachable", []))
        unused = [n for n in p["unreachable"] if n not in frozen]
        if unused:
            count = p["unreachable_count"] - p.get("frozen_unreachable_count", 0)
            names = ", ".join(unused[:6]) + (f" (+{len(unused) - 6} more)" if len(unused) > 6 else "")
            out.append(f"{r['detector']}: {count:,} parameters never take part in the forward pass: {names}")
        if frozen:
            out.append(
                f"{r['detector']}: {p['frozen_unreachable_count']:,} frozen parameters are outside the raw "
                f"forward (fixed, applied when boxes are decoded): {', '.join(sorted(frozen))}"
            )
        ref = r.get("reference") or {}
        if ref.get("source"):
            out.append(f"{r['detector']}: reference from {ref['source']}")
        for key in ("onnx",):
            if isinstance(r.get(key), dict) and "error" in r[key]:
                out.append(f"{r['detector']}: ONNX export failed: {r[key]['error']}")
    from harness.textable import fit_text

    return fit_text("\n".join(out))


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="profile")
    @opt.names_option(
        "--detectors",
        required=True,
        old=("--detector",),
        help="Detectors to profile, comma-separated or repeated, or 'all' for every registered detector.",
    )
    @opt.format_option("text", "json", old_json=True)
    @opt.model_shape_options()
    @click.option("--runs", type=int, default=30, show_default=True, help="Timed runs per latency back-end.")
    @click.option("--warmup", type=int, default=5, show_default=True, help="Untimed warm-up runs.")
    @click.option("--threads", type=int, default=None, help="Threads for torch and onnxruntime [default: torch's].")
    @click.option("--device", default="cpu", show_default=True, help="Device for torch latency (cpu, cuda).")
    @click.option("--latency/--no-latency", default=True, show_default=True, help="Time the torch forward pass.")
    @click.option("--onnx/--no-onnx", default=True, show_default=True, help="Export and time onnxruntime.")
    @click.option("--fvcore/--no-fvcore", default=True, show_default=True, help="Add fvcore's count and table.")
    @click.option("--table", "show_table", is_flag=True, help="Also print fvcore's per-module table.")
    @opt.store_option(help="Results store to write profiles into [default: results/<profile>].")
    @opt.profile_option(param="run_profile")
    @opt.config_options(
        help_set="Override one config key, e.g. --set model.scale=n (repeatable); the model section is used."
    )
    @click.option("--no-store", is_flag=True, help="Do not write the results store.")
    @opt.no_progress_option()
    def profile_cmd(
        detectors: tuple[str, ...],
        fmt: str,
        show_table: bool,
        store: Path | None,
        run_profile: str,
        config_files: tuple[str, ...],
        overrides: tuple[str, ...],
        no_store: bool,
        **measure: Any,
    ) -> None:
        """Parameters, GFLOPs ("paper" and "exact" conventions, fvcore) and latency of detectors at IMGSZ, batch 1."""
        from harness.config import load_config
        from harness.errors import HarnessError, PartlyDone
        from harness.plugins import get_host
        from harness.profiling import profile_detector
        from harness.progress import bar
        from harness.store import Store

        host = get_host()
        names = sorted(host.detectors()) if detectors == ("all",) else list(detectors)
        options = {}
        for name in names:
            spec = host.detector(name)  # unknown names fail here with the list of available ones
            cfg = load_config(
                run_profile,
                detector=spec.name,
                detector_defaults=spec.defaults,
                files=config_files,
                overrides=overrides,
            )
            options[name] = dict(cfg.get("model") or {})
        results = []
        with bar("profiling", total=len(names)) as progress:
            for name in names:
                progress.update(description=f"profiling {name}")
                try:
                    results.append(profile_detector(name, host=host, model_options=options[name], **measure))
                except HarnessError as exc:
                    if len(names) == 1:
                        raise
                    results.append({"detector": name, "error": str(exc)})  # the others are still profiled
                progress.advance()
        root = opt.resolve_store(store, run_profile)
        if not no_store:
            for r in results:
                if "error" not in r:
                    Store(root).write_profile(r["detector"], r)
        failed = [r["detector"] for r in results if "error" in r]
        if fmt == "json":
            click.echo(json.dumps(results, indent=2, default=str))
        else:
            click.echo(format_profiles(results))
        if show_table:
            for r in results:
                table = (r.get("flops", {}).get("fvcore") or {}).get("table")
                if table:
                    click.echo(f"\n{r['detector']}: {table}")
        if not no_store and fmt != "json":
            click.echo(f"\nprofiles written to {root / '_profiles'}")
        if failed:
            raise PartlyDone(f"could not profile {', '.join(failed)} (see above)")

    @cli.command(name="export")
    @click.option("--detector", required=True, help="Detector name.")
    @opt.option(
        "--out",
        "onnx_path",
        old=("--onnx",),
        required=True,
        type=click.Path(dir_okay=False, path_type=Path),
        help="Output .onnx file.",
    )
    @opt.model_shape_options(imgsz_help="Square input size of the traced graph.")
    @click.option("--opset", type=int, default=18, show_default=True, help="ONNX opset (17 or newer).")
    @click.option("--dynamic-batch", is_flag=True, help="Make the batch dimension dynamic.")
    @click.option(
        "--check/--no-check",
        default=True,
        show_default=True,
        help="Run the file in onnxruntime and require outputs equal to torch within 1e-4.",
    )
    def export_cmd(detector: str, onnx_path: Path, check: bool, **settings: Any) -> None:
        """Export a detector's raw forward (BN folded, no NMS) to ONNX and check it against torch."""
        from harness.profiling import export_detector

        rec = export_detector(detector, onnx_path, check=check, **settings)
        ins = ", ".join(f"{k} {v}" for k, v in rec["inputs"].items())
        outs = ", ".join(f"{k} {v}" for k, v in rec["outputs"].items())
        click.echo(
            f"wrote {rec['path']} (opset {rec['opset']}, {rec['exporter']} exporter, BN folded: {rec['fused']}, "
            f"NMS not in the graph)"
        )
        click.echo(f"inputs: {ins}")
        click.echo(f"outputs: {outs}")
        if check:
            click.echo(f"onnxruntime matches torch: max |diff| {rec['max_abs_diff']:.2g} <= {rec['atol']:g}")
