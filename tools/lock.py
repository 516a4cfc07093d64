"""Refresh the locked environment: ``make lock`` (or ``python3 tools/lock.py``).

Resolves torch + the harness with its ``dev`` extra in a scratch virtual environment, with the hand-set pins of
``constraints.txt`` (the lock inputs), and writes two lock files at the repository root:

* ``requirements.lock``: everything ``make demo`` needs (the harness's own dependencies and torch's);
* ``requirements-dev.lock``: what ``make test`` and ``make lint`` add on top (the ``dev`` extra, and tidecv, which
  is installed without its dependencies).

Each line pins one package to one version with the sha256 of the file pip installs, all on that line, so
``sed 's/ --hash=.*//'`` strips the hashes. torch is left out of both files: the CPU build on the project's machines is
not the file the registry serves under the same version, so the set-up installs it in a step of its own
(``TORCH`` in the Makefile). Every other hash is checked against pip's default index alone (``pip --isolated``), so
a lock written where pip also reads local mirrors installs the same files everywhere else.

The hashes are for the platform and Python this runs on, which must be the ones the lock is for: Linux x86-64,
CPython 3.11. Output is sorted and carries no dates, so an unchanged resolve rewrites identical files.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
INPUTS = ROOT / "constraints.txt"
RUNTIME_LOCK = ROOT / "requirements.lock"
DEV_LOCK = ROOT / "requirements-dev.lock"
# What the lock is for; the Makefile installs with hashes only where the venv's Python matches.
PLATFORM, CACHE_TAG = "linux-x86_64", "cpython-311"
# Installed without dependencies: tidecv (the TIDE reference the error-analysis test compares against) asks for the GUI
# build of OpenCV, which would overwrite the headless cv2 it imports fine; the dev extra lists the rest of what it
# imports.
NO_DEPS = ("tidecv==1.0.1",)
# Never locked: torch comes in its own step, and the project is installed from the checkout.
UNLOCKED = {"torch", "rgbt-harness"}


def normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pip(venv_python: Path, *args: str, isolated: bool = False) -> None:
    cmd = [str(venv_python), "-m", "pip", *(["--isolated"] if isolated else []), "--disable-pip-version-check", *args]
    if isolated and os.environ.get("PIP_CERT"):
        cmd += ["--cert", os.environ["PIP_CERT"]]
    print("lock: " + shlex.join(["pip", *cmd[3:]]), file=sys.stderr)
    subprocess.run(cmd, check=True, cwd=ROOT)


def resolve(venv_python: Path, report: Path, *args: str, isolated: bool = False) -> dict[str, dict]:
    """What pip would install into an empty environment, by normalized name: {'name', 'version', 'sha256', 'url'}."""
    pip(
        venv_python,
        "install",
        "--dry-run",
        "--ignore-installed",
        "--quiet",
        "--report",
        str(report),
        *args,
        isolated=isolated,
    )
    found = {}
    for item in json.loads(report.read_text())["install"]:
        meta, info = item["metadata"], item["download_info"]
        found[normalize(meta["name"])] = {
            "name": normalize(meta["name"]),
            "version": meta["version"],
            "sha256": info.get("archive_info", {}).get("hashes", {}).get("sha256"),
            "url": info["url"],
        }
    return found


def line(pkg: dict, hashes: list[str]) -> str:
    return f"{pkg['name']}=={pkg['version']} " + " ".join(f"--hash=sha256:{h}" for h in hashes)


def header(title: str, torch_version: str) -> str:
    return f"""\
# {title}
# Written by `make lock` (tools/lock.py) from constraints.txt (the hand-set pins) and pyproject.toml; do not edit.
# Hashes are for Linux x86-64, CPython 3.11: `make venv` installs with `pip install --require-hashes --no-deps`
# there, and elsewhere installs the same pins without hashes (`sed 's/ --hash=.*//'`), saying so on stderr.
# Not in this file: torch=={torch_version}, installed by its own step (the Makefile's TORCH, default
# torch=={torch_version}: the CPU build), because the CPU wheel on the project's machines is not the file the registry
# serves under that version. On a GPU machine, swap in a CUDA build of the same release (its CUDA libraries come
# with it, unlocked; everything here stays as pinned):
#   make clean-venv && make venv TORCH_INDEX='--index-url URL'
# with URL the PyTorch CUDA wheel index for your CUDA version.
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--torch-index", default="", help="pip options for torch's index, as TORCH_INDEX in make")
    parser.add_argument(
        "--no-registry-check",
        action="store_true",
        help="skip checking the hashes against pip's default index alone (offline)",
    )
    args = parser.parse_args(argv)
    if sysconfig.get_platform() != PLATFORM or sys.implementation.cache_tag != CACHE_TAG:
        sys.exit(
            f"lock: the lock's hashes are for {PLATFORM} {CACHE_TAG}; this is {sysconfig.get_platform()} "
            f"{sys.implementation.cache_tag}: run `make lock` on such a machine (PYTHON=python3.11)"
        )
    torch_index = shlex.split(args.torch_index)
    with tempfile.TemporaryDirectory(prefix="rgbt-lock-") as tmp:
        scratch = Path(tmp)
        subprocess.run([sys.executable, "-m", "venv", str(scratch / "venv")], check=True)
        py = scratch / "venv" / "bin" / "python"
        inputs = ["-c", str(INPUTS), *torch_index]
        full = resolve(py, scratch / "full.json", *inputs, "torch", "-e", ".[dev]")
        torch = full.get("torch")
        if torch is None or "+cpu" not in torch["version"]:
            sys.exit(
                f"lock: the resolve took torch {torch and torch['version']}, not a CPU build: its CUDA libraries would "
                "enter the lock. Point pip at the PyTorch CPU wheel index (URL) for torch: "
                "make lock LOCK_ARGS=\"--torch-index '--extra-index-url URL'\""
            )
        # the runtime set, held to the full resolve's versions so the two files agree
        pins = scratch / "full-pins.txt"
        pins.write_text("".join(f"{p['name']}=={p['version']}\n" for n, p in full.items() if n not in UNLOCKED))
        runtime = resolve(py, scratch / "runtime.json", *inputs, "-c", str(pins), "torch", "-e", ".")
        extra = resolve(py, scratch / "nodeps.json", "--no-deps", *NO_DEPS)
        locked = {n: p for n, p in {**full, **extra}.items() if n not in UNLOCKED}
        missing = sorted(n for n, p in locked.items() if not p["sha256"])
        if missing:
            sys.exit(f"lock: pip reported no sha256 for {', '.join(missing)}")
        hashes = {n: [p["sha256"]] for n, p in locked.items()}
        if not args.no_registry_check:
            # the same pins from pip's default index alone; a file served there under another hash is added as such
            req = scratch / "hashed.txt"
            req.write_text("".join(line(p, hashes[n]) + "\n" for n, p in sorted(locked.items())))
            registry = resolve(
                py, scratch / "registry.json", "--no-deps", "--require-hashes", "-r", str(req), isolated=True
            )
            for n, p in sorted(locked.items()):
                theirs = registry[n]["sha256"]
                if theirs not in hashes[n]:
                    print(
                        f"lock: {n}=={p['version']}: the default index serves sha256 {theirs}, the resolve took "
                        f"{hashes[n][0]} ({p['url']}); both are allowed",
                        file=sys.stderr,
                    )
                    hashes[n].append(theirs)
    runtime_names = sorted(set(runtime) - UNLOCKED)
    dev_names = sorted(set(locked) - set(runtime_names))
    base = torch["version"].split("+")[0]
    RUNTIME_LOCK.write_text(
        header("What `make demo` installs: the harness's dependencies and torch's, each at one version.", base)
        + "".join(line(locked[n], sorted(hashes[n])) + "\n" for n in runtime_names)
    )
    DEV_LOCK.write_text(
        header("What `make test` and `make lint` add to requirements.lock: the dev extra, and tidecv.", base)
        + "# tidecv is installed without its dependencies: it asks for the GUI build of OpenCV.\n"
        + "".join(line(locked[n], sorted(hashes[n])) + "\n" for n in dev_names)
    )
    print(
        f"lock: {len(runtime_names)} packages in {RUNTIME_LOCK.name}, {len(dev_names)} in {DEV_LOCK.name} "
        f"(torch {torch['version']} in its own step)",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
