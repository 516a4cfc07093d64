"""``harness list`` and ``harness plugins``: what is installed and who provides it."""

from __future__ import annotations

import json
from typing import Any

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def _warn_problems(host: Any) -> None:
    for problem in host.problems:
        click.secho(f"warning: {problem}", err=True, fg="yellow")


def listing(host: Any) -> dict[str, list[dict[str, Any]]]:
    """Detectors, datasets and encodings as plain records (what ``harness list --format json`` prints)."""
    detectors = [
        {
            "name": s.name,
            "input_kind": s.input_kind,
            "description": s.description,
            "label": s.label,
            "plugin": host.owner("detector", s.name),
        }
        for s in host.detectors().values()
    ]
    datasets = [
        {
            "name": s.name,
            "thermal": s.thermal,
            "categories": list(s.categories),
            "default_encoding": s.default_encoding,
            "protocol": s.protocol,
            "description": s.description,
            "plugin": host.owner("dataset", s.name),
        }
        for s in host.datasets().values()
    ]
    encodings = [
        {
            "name": s.name,
            "channels": s.channels,
            "needs": s.needs,
            "description": s.description,
            "plugin": host.owner("encoding", s.name),
        }
        for s in host.encodings().values()
    ]
    key = lambda r: r["name"]  # noqa: E731
    return {"detectors": sorted(detectors, key=key), "datasets": sorted(datasets, key=key),
            "encodings": sorted(encodings, key=key)}


def format_listing(data: dict[str, list[dict[str, Any]]]) -> str:
    lines: list[str] = []
    kinds = {"single": "single-stream [R,G,B]+encoding", "dual": "dual-stream (rgb, thermal)"}
    for section, rows in data.items():
        lines.append(f"{section}:")
        if not rows:
            lines.append("  (none)")
        width = max((len(r["name"]) for r in rows), default=0)
        for r in rows:
            if section == "detectors":
                extra = kinds[r["input_kind"]]
            elif section == "datasets":
                n = len(r["categories"])
                cats = f"{n} categor{'y' if n == 1 else 'ies'}" if n else "categories from the data"
                extra = f"{r['thermal']} thermal, {cats}, encoding {r['default_encoding']}"
            else:
                extra = f"{r['channels']} channel(s) from {r['needs'] or 'nothing'}"
            label = f" [{r['label']}]" if r.get("label") else ""
            desc = f" - {r['description']}" if r.get("description") else ""
            lines.append(f"  {r['name']:<{width}}  {extra}{label}{desc}")
    from harness.textable import fit_text

    return fit_text("\n".join(lines))


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="list")
    @opt.format_option("text", "json", old_json=True)
    def list_cmd(fmt: str) -> None:
        """List the detectors, datasets and encodings that the loaded plugins provide."""
        from harness.plugins import get_host

        host = get_host()
        data = listing(host)
        _warn_problems(host)
        click.echo(json.dumps(data, indent=2) if fmt == "json" else format_listing(data))

    @cli.command(name="plugins")
    @click.option("--hook", default=None, help="Only plugins that implement this hook.")
    @click.option("--external", is_flag=True, help="Only third-party plugins (hide the built-in ones).")
    def plugins_cmd(hook: str | None, external: bool) -> None:
        """Print the loaded plugins as JSON: name, distribution and version, hooks, names registered.

        Third-party plugins come from the `harness` entry-point group; set HARNESS_LOAD_PLUGINS to a comma-separated
        list of distribution names to load only those, HARNESS_DISABLE_PLUGIN_AUTOLOAD=1 to load none.
        """
        from harness.plugins import get_host

        host = get_host()
        records = [r for r in host.plugin_info(hook=hook) if not (external and r["builtin"])]
        out: dict[str, Any] = {"plugins": records}
        problems = host.problems
        if problems:
            out["problems"] = [{"plugin": p.plugin, "stage": p.stage, "message": p.message} for p in problems]
        click.echo(json.dumps(out, indent=2))
