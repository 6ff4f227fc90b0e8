"""Official train/val/test split files of the layout benchmarks.

* MatterportLayout (``data_list/mp3d_{train,val,test}.txt`` of the Matterport3DLayoutAnnotation release, and
  LGT-Net's ``split/{train,val,test}.txt`` copies): one panorama per line, ``<scene_id> <pano_id>``; the
  sample name is ``<scene_id>_<pano_id>`` (the file names of the images and labels). A line with a single
  token is taken as the whole name (lists written for other datasets).
* ZInD (``zind_partition.json``, written by ZInD's ``partition_zind.py``): ``{"train": [house ids], "val":
  [...], "test": [...]}``.

Split names are ``train``, ``val`` and ``test``; anything else is an error that lists them.
"""
from __future__ import annotations

import json
from pathlib import Path

from .validate import DataValidationError, UnreadableFileError, invalid, read_text

SPLITS = ("train", "val", "test")


def check_split_name(split: str, what: str) -> str:
    if split not in SPLITS:
        raise ValueError(f"{what}: unknown split {split!r}; expected one of {', '.join(SPLITS)}")
    return split


def check_relative_path(rel: str, where: str | Path) -> str:
    """A path read from a dataset file (a split list, a JSON field) that must stay inside the dataset root: not
    absolute (``/x``, ``~/x``, ``C:\\x``) and without a ``..`` part (checked on the text, so links inside the
    dataset still work). Anything else is a :class:`~omnidl.data.validate.DataValidationError` naming ``where``
    (the file and line or field)."""
    text = str(rel)
    parts = text.replace("\\", "/").split("/")
    if text.startswith(("/", "\\", "~")) or (len(text) > 1 and text[1] == ":") or ".." in parts:
        raise DataValidationError(f"{where}: path {text!r} leaves the dataset root; expected a path relative to "
                                  "the dataset root, without '..'")
    return text


def read_split_list(path: str | Path) -> list[str]:
    """Sample names of a split file (``<scene> <pano>`` or ``<name>`` per line; blank lines and ``#`` comments
    skipped), in file order. Duplicates, lines with more than two fields and names that leave the dataset root
    (:func:`check_relative_path`) are errors naming the line."""
    path = Path(path)
    names: list[str] = []
    seen: dict[str, int] = {}
    for i, line in enumerate(read_text(path, "split list").splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = s.split()
        if len(parts) > 2:
            raise DataValidationError(f"{path}:{i}: split line is {line!r}, expected '<scene_id> <pano_id>' or "
                                      "'<name>'")
        name = check_relative_path("_".join(parts), f"{path}:{i}")
        if name in seen:
            raise DataValidationError(f"{path}:{i}: {name!r} is listed twice (first on line {seen[name]}); "
                                      "expected each panorama once")
        seen[name] = i
        names.append(name)
    if not names:
        raise DataValidationError(f"{path}: split list is empty, expected one panorama per line")
    return names


def find_split_file(root: Path, split: str, patterns: tuple[str, ...], what: str) -> Path:
    """The first existing ``root / pattern.format(split=split)``; a clear error lists the places looked at."""
    check_split_name(split, what)
    cands = [root / p.format(split=split) for p in patterns]
    for c in cands:
        if c.is_file():
            return c
    raise FileNotFoundError(f"{what}: no split file for split {split!r} (looked for {[str(c) for c in cands]}); "
                            "put the official list there, pass data.split_file=PATH, or data.split=null for all files")


def read_zind_partition(path: str | Path, split: str) -> list[str]:
    """House ids of ``split`` in a ZInD ``zind_partition.json``."""
    path = Path(path)
    check_split_name(split, f"ZInD partition {path}")
    try:
        data = json.loads(read_text(path, "ZInD partition"))
    except json.JSONDecodeError as e:
        raise UnreadableFileError(f"cannot parse {path} (ZInD partition: {e.msg} at line {e.lineno}; expected "
                                  "JSON)") from e
    if not isinstance(data, dict):
        raise invalid(path, "ZInD partition", f"a JSON {type(data).__name__}", 'an object {"train": [...], ...}')
    if split not in data:
        raise invalid(path, "ZInD partition", f"an object with keys {sorted(data)}", f"a {split!r} key")
    ids = data[split]
    if not isinstance(ids, list) or not all(isinstance(h, (str, int)) for h in ids):
        raise invalid(path, f"partition[{split!r}]", f"a {type(ids).__name__}", "a list of house ids")
    return [str(h) for h in ids]
