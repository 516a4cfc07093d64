"""The folds of a prepared dataset and the COCO ground truth of their splits, written into its cache folder.

``resolve_folds`` reads the config's ``protocol.folds`` or the folds recorded at preparation; ``fold_indices`` the
samples of a fold's training and held-out groups; ``validation_split`` the validation split carved from a fold's
training groups for model selection (``protocol.selection: validation``); ``coco_path`` the COCO file (thermal frame)
of a split, written on first use under ``<prepared folder>/coco/``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from harness.api import DatasetSpec, Fold
from harness.cache.reader import PreparedDataset
from harness.errors import ConfigError, DataError
from harness.io import atomic_write_json


def resolve_folds(
    dataset_spec: DatasetSpec | str,
    prepared: PreparedDataset,
    cfg: Mapping[str, Any],
    selection: str | Sequence[str] | None = "all",
) -> list[Fold]:
    """The evaluation folds: ``cfg["protocol"]["folds"]`` (``{fold name: [held-out groups]}``, training on every
    other group present) when set, else the dataset's own folds recorded at preparation. ``selection``: ``"all"``,
    a fold name, a comma-separated list of names, or a list of names."""
    name = dataset_spec.name if isinstance(dataset_spec, DatasetSpec) else str(dataset_spec)
    present = sorted(set(prepared.groups))
    spec_folds = (cfg.get("protocol") or {}).get("folds")
    folds: list[Fold] = []
    if spec_folds:
        if not isinstance(spec_folds, Mapping):
            raise ConfigError(f"protocol.folds must map fold names to lists of held-out groups, got {spec_folds!r}")
        for fold_name, held in spec_folds.items():
            held_t = (held,) if isinstance(held, str) else tuple(held or ())
            missing = [g for g in held_t if g not in present]
            if missing:
                raise ConfigError(
                    f"protocol.folds: fold {fold_name!r} holds out {', '.join(map(repr, missing))}, "
                    f"which dataset {name!r} does not have; its groups are {', '.join(present)}"
                )
            if not held_t:
                raise ConfigError(f"protocol.folds: fold {fold_name!r} holds out no group")
            folds.append(Fold(str(fold_name), tuple(g for g in present if g not in held_t), held_t))
    empty: dict[str, tuple[str, ...]] = {}
    if not spec_folds:
        recorded = prepared.manifest.get("folds") or []
        for f in recorded:
            val = tuple(g for g in f["val_groups"] if g in present)
            if val:
                folds.append(Fold(f["name"], tuple(g for g in f["train_groups"] if g in present), val))
            else:
                empty[f["name"]] = tuple(f["val_groups"])
        if not folds:  # nothing recorded: leave one group out
            folds = [Fold(g, tuple(x for x in present if x != g), (g,)) for g in present]
    return select_folds(folds, selection, empty, name)


def refuse_repeats(given: Sequence[Any], head: str, each: str, shown: Callable[[Any], str] = repr) -> None:
    """An option's list (``--folds``, ``--seeds``) names each value once: one given twice would count twice in the
    mean and SD. The error starts with ``head`` (the option and its value), lists the repeated values (``shown``)
    and says what each stands for (``each``)."""
    twice = sorted({v for v in given if given.count(v) > 1})
    if twice:
        raise ConfigError(
            f"{head}{', '.join(map(shown, twice))} given more than once; {each}, and a repeated one would count "
            f"twice in the mean and SD"
        )


def select_folds(
    folds: list[Fold],
    selection: str | Sequence[str] | None,
    empty: Mapping[str, Sequence[str]] | None = None,
    dataset: str = "",
) -> list[Fold]:
    """The folds ``selection`` names. ``empty``: the dataset's folds left out because their held-out groups have no
    prepared sample (fold name -> those groups), named as such when asked for."""
    if selection is None or selection == "all" or selection == ["all"]:
        return folds
    names = [s.strip() for s in selection.split(",")] if isinstance(selection, str) else [str(s) for s in selection]
    shown = selection if isinstance(selection, str) else ",".join(names)
    if not any(names):
        raise ConfigError(f"--folds {shown!r} names no fold; give fold names, or 'all' for every fold")
    refuse_repeats(names, f"--folds {shown!r}: ", "each fold is scored once")
    by_name = {f.name: f for f in folds}
    gone = [n for n in names if n not in by_name and n in (empty or {})]
    if gone:
        raise ConfigError(
            "; ".join(
                f"fold {n!r} of dataset {dataset!r} holds out {', '.join(map(repr, (empty or {})[n]))}, which "
                f"ha{'s' if len((empty or {})[n]) == 1 else 've'} no prepared sample, so the fold is left out"
                for n in gone
            )
            + f" (the prepare report says why their files were skipped; available: {', '.join(by_name)})"
        )
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ConfigError(
            f"unknown fold(s) {', '.join(map(repr, unknown))}; available: {', '.join(by_name)} (or 'all')"
        )
    return [by_name[n] for n in names]


def fold_indices(prepared: PreparedDataset, fold: Fold) -> tuple[list[int], list[int]]:
    """Sample indices (into ``prepared``) of the fold's training and held-out groups."""
    train, val = prepared.indices(fold.train_groups), prepared.indices(fold.val_groups)
    if not val:
        raise DataError(f"fold {fold.name!r}: no prepared images in the held-out group(s) {', '.join(fold.val_groups)}")
    if not train and not fold.train_groups:
        raise DataError(
            f"fold {fold.name!r} holds out every group of the prepared data "
            f"({', '.join(fold.val_groups)}): nothing is left to train on; give the dataset a second "
            f"group or set protocol.folds"
        )
    if not train:
        raise DataError(f"fold {fold.name!r}: no prepared images to train on (groups {', '.join(fold.train_groups)})")
    return train, val


#: Under ``protocol.selection: validation`` with a single training group: every ``IMAGE_SPLIT_EVERY``-th of its images
#: (in prepared order, starting with the last of each run of five) is the validation split.
IMAGE_SPLIT_EVERY = 5


@dataclass(frozen=True)
class ValidationSplit:
    """A fold's training part divided for model selection: the model trains on ``train`` and is scored each epoch on
    ``validation``; the fold's held-out groups are in neither. ``groups``: the training groups held back whole (empty
    when ``how`` is ``"images"``: one training group only, so every ``IMAGE_SPLIT_EVERY``-th image of it)."""

    fold: str
    groups: tuple[str, ...]
    train: tuple[int, ...]
    validation: tuple[int, ...]
    how: str  # "smallest-group" | "configured" | "images"

    def record(self) -> dict[str, Any]:
        return {
            "validation_groups": list(self.groups),
            "validation_images": len(self.validation),
            "train_images": len(self.train),
            "how": self.how,
        }


def validation_split(prepared: PreparedDataset, fold: Fold, cfg: Mapping[str, Any] | None = None) -> ValidationSplit:
    """The validation split of ``fold``, carved from its training groups, deterministic per fold:

    * ``protocol.validation_groups: {fold name: [groups]}`` names the groups for a fold (training groups only);
    * otherwise the training group with the fewest prepared images (ties: the first by name), so that selection costs
      the fewest training images; on m3t-synth P4 (16 images) for folds P1, P2 and P3 and P2 (20) for P4+P5;
    * a fold with a single training group keeps it and validates on every ``IMAGE_SPLIT_EVERY``-th of its images
      (in prepared order): the only split left, and not group-disjoint within that group (``how: images``).

    The model then trains on the other training groups; the held-out groups are never part of either."""
    train_idx, _ = fold_indices(prepared, fold)
    present = [g for g in fold.train_groups if prepared.indices([g])]
    configured = ((cfg or {}).get("protocol") or {}).get("validation_groups") or {}
    if not isinstance(configured, Mapping):
        raise ConfigError(
            f"protocol.validation_groups must map fold names to lists of training groups, got {configured!r}"
        )
    if fold.name in configured:
        wanted = configured[fold.name]
        groups = tuple([wanted] if isinstance(wanted, str) else [str(g) for g in wanted or []])
        bad = [g for g in groups if g not in present]
        if not groups or bad:
            raise ConfigError(
                f"protocol.validation_groups: fold {fold.name!r} must name one or more of its training groups "
                f"({', '.join(present)}); {', '.join(map(repr, bad)) or 'none named'} "
                f"{'is' if len(bad) == 1 else 'are'} not"
            )
        if set(groups) >= set(present):
            raise ConfigError(
                f"protocol.validation_groups: fold {fold.name!r} holds back every training group "
                f"({', '.join(groups)}); nothing is left to train on"
            )
        how = "configured"
    elif len(present) > 1:
        sizes = {g: len(prepared.indices([g])) for g in present}
        groups = (min(sorted(present), key=lambda g: sizes[g]),)
        how = "smallest-group"
    else:
        val = tuple(i for k, i in enumerate(train_idx) if k % IMAGE_SPLIT_EVERY == IMAGE_SPLIT_EVERY - 1)
        if not val:
            raise DataError(
                f"fold {fold.name!r}: {len(train_idx)} training image(s) in one group are too few to hold back a "
                f"validation split; use protocol.selection=last"
            )
        return ValidationSplit(fold.name, (), tuple(i for i in train_idx if i not in set(val)), val, "images")
    held = set(groups)
    val = tuple(prepared.indices(groups))
    return ValidationSplit(fold.name, groups, tuple(i for i in train_idx if prepared.groups[i] not in held), val, how)


@dataclass
class FoldSupport:
    fold: str
    train_groups: tuple[str, ...]
    val_groups: tuple[str, ...]
    train_images: int
    train_instances: int
    val_images: int
    val_instances: int
    val_categories: dict[str, int]


def fold_support(prepared: PreparedDataset, folds: Iterable[Fold]) -> list[FoldSupport]:
    """Images and instances of each fold's training and held-out parts (what ``harness folds`` prints)."""
    out = []
    for f in folds:
        tr, va = fold_indices(prepared, f)
        st, sv = prepared.support(tr), prepared.support(va)
        out.append(
            FoldSupport(
                f.name,
                f.train_groups,
                f.val_groups,
                st["images"],
                st["instances"],
                sv["images"],
                sv["instances"],
                sv["categories"],
            )
        )
    return out


# ------------------------------------------------------------------------------------------------ COCO
_SAFE = re.compile(r"[^A-Za-z0-9_.+-]")


def coco_path(prepared: PreparedDataset, fold: Fold | None = None, split: str = "val") -> Path:
    """The COCO ground-truth file (thermal frame) of a fold's split, written when missing; ``fold=None``: all."""
    if fold is None:
        path = prepared.folder / "coco" / "all.json"
        idx = None
    else:
        if split not in ("train", "val"):
            raise ValueError(f"split must be 'train' or 'val', got {split!r}")
        path = prepared.folder / "coco" / f"{_SAFE.sub('_', fold.name)}-{split}.json"
        tr, va = fold_indices(prepared, fold)
        idx = tr if split == "train" else va
    if not path.exists():
        coco = prepared.coco(idx)
        coco["info"].update(
            {
                "fold": None if fold is None else fold.name,
                "split": split if fold else "all",
                "key": prepared.manifest.get("key"),
            }
        )
        atomic_write_json(path, coco, indent=None)
    return path


def ensure_coco(prepared: PreparedDataset, folds: Iterable[Fold]) -> None:
    """The COCO files of every split of ``folds`` (and of all samples) written."""
    coco_path(prepared)
    for f in folds:
        for split in ("train", "val"):
            coco_path(prepared, f, split)
