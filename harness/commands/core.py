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


#: What ``harness list`` shows of each kind of spec, between its name and the plugin that provides it.
LISTED_FIELDS = {
    "detector": ("input_kind", "description", "label"),
    "dataset": ("thermal", "categories", "default_encoding", "protocol", "description"),
    "encoding": ("channels", "needs", "description"),
}


def _records(host: Any, kind: str, specs: Any) -> list[dict[str, Any]]:
    """One plain record per spec (tuples as lists), sorted by name."""
    rows = []
    for s in specs:
        fields = {f: list(v) if isinstance(v := getattr(s, f), tuple) else v for f in LISTED_FIELDS[kind]}
        rows.append({"name": s.name, **fields, "plugin": host.owner(kind, s.name)})
    return sorted(rows, key=lambda r: r["name"])


def listing(host: Any) -> dict[str, list[dict[str, Any]]]:
    """Detectors, datasets and encodings as plain records (what ``harness list --format json`` prints)."""
    return {
        "detectors": _records(host, "detector", host.detectors().values()),
        "datasets": _records(host, "dataset", host.datasets().values()),
        "encodings": _records(host, "encoding", host.encodings().values()),
    }


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
