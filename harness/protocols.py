"""Where a dataset's evaluation protocol YAML lives.

``DatasetSpec.protocol`` takes one of three forms:

* a plain name, ``"m3t-4fold"``: ``configs/protocols/m3t-4fold.yaml`` of the harness;
* a package resource, ``"my_dataset_pkg:protocol.yaml"`` (``package:path/inside/the/package``): a file a plugin
  ships inside its own package (list it as package data), found with ``importlib.resources``;
* an absolute file path (a ``str`` or ``pathlib.Path``), e.g. ``Path(__file__).with_name("protocol.yaml")``.

``shipped_protocol`` resolves the last two forms to a file; a plain name stays with ``harness.config``.
"""

from __future__ import annotations

import os
from pathlib import Path

from harness.errors import ConfigError


def protocol_form(protocol: str) -> str:
    """``"name"``, ``"resource"`` or ``"path"``: how ``protocol`` is to be found."""
    if os.path.isabs(protocol):
        return "path"
    if ":" in protocol:
        return "resource"
    return "name"


def shipped_protocol(protocol: str | os.PathLike[str]) -> Path | None:
    """The YAML file of a protocol given as a package resource or an absolute path; ``None`` for a plain name.

    A resource whose package cannot be imported, or a file that does not exist, is a ``ConfigError`` naming it.
    """
    text = os.fspath(protocol)
    form = protocol_form(text)
    if form == "name":
        return None
    if form == "path":
        path = Path(text)
    else:
        package, _, rel = text.partition(":")
        if not package or not rel:
            raise ConfigError(f"protocol {text!r}: a shipped protocol is written 'package:path/in/package.yaml'")
        from importlib.resources import files

        try:
            base = files(package)
        except (ModuleNotFoundError, TypeError) as exc:
            raise ConfigError(f"protocol {text!r}: package {package!r} cannot be imported ({exc})") from None
        path = Path(str(base.joinpath(*Path(rel).parts)))
    if not path.is_file():
        raise ConfigError(
            f"protocol {text!r}: no file {path}; a plugin that ships its protocol must install it "
            "with its package (package data)"
        )
    return path
