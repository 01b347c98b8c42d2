"""Taxonomies: which classes a model trains on, as a map from the contract's fine classes.

Records always keep fine classes; a taxonomy is applied when data leaves for a model (exports,
training, evaluation). Presets live in omnigen/taxonomies/*.toml; users pass their own TOML with
the same shape: `name = "..."` and a `[classes]` table `fine = "target"`. Target classes are
numbered in order of first appearance in that table.

Where a taxonomy may come from, and why: a preset by name, a TOML file the user named on the
command line (load_taxonomy: read as a regular file of at most TAXONOMY_MAX_BYTES), or the mapping
a manifest or checkpoint embeds (Taxonomy.from_dict). A manifest's entry is never a path to open:
a downloaded dataset could otherwise name /dev/zero or a FIFO and have `export` read gigabytes or
block for ever (recorded_taxonomy accepts a preset's name or an embedded mapping, nothing else).
Every malformed entry is a TaxonomyError naming the file and the field.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnigen.conventions import FINE_CLASSES
from omnigen.untrusted import read_regular

PRESETS_DIR = Path(__file__).parent / "taxonomies"

TAXONOMY_MAX_BYTES = 1 * 2**20
"""Largest taxonomy TOML read. A taxonomy maps a dozen fine classes, a few hundred bytes; a
megabyte is room for any comment, and keeps a path to a device or a huge file from being read."""


class TaxonomyError(ValueError):
    """A taxonomy that cannot be used: names the file (or what holds the entry) and the field."""

    def __init__(self, file: str | Path, field: str, message: str):
        self.file, self.field, self.message = str(file), field, message
        super().__init__(f"{file}: field '{field}': {message}")


@dataclass(frozen=True)
class Taxonomy:
    name: str
    mapping: dict[str, str]  # fine class -> target class; fine classes absent here are dropped

    @property
    def classes(self) -> list[str]:
        """Target classes in a stable order (first appearance in the mapping)."""
        return list(dict.fromkeys(self.mapping.values()))

    def target(self, fine: str) -> str | None:
        return self.mapping.get(fine)

    def class_id(self, fine: str) -> int | None:
        """0-based index of the target class of `fine`, or None when the taxonomy drops it."""
        target = self.mapping.get(fine)
        return None if target is None else self.classes.index(target)

    def fine_class_ids(self) -> np.ndarray:
        """Class id of each fine class, indexed as FINE_CLASSES (a record's `category`), -1 where
        the taxonomy drops it: the lookup every writer of class ids applies to whole columns."""
        return np.array([-1 if (c := self.class_id(f)) is None else c for f in FINE_CLASSES], dtype=np.int64)

    def to_dict(self) -> dict:
        return {"name": self.name, "classes": self.classes, "mapping": dict(self.mapping)}

    @classmethod
    def from_dict(cls, d: Any, file: str | Path = "<taxonomy>", field: str = "taxonomy") -> "Taxonomy":
        """The inverse of to_dict: what checkpoints and manifests store. The class order is the
        stored `classes`, not the mapping's: a manifest is written with sorted keys. Checked field
        by field (a TaxonomyError naming `file` and `field`): it may have been edited by hand."""
        if not isinstance(d, dict):
            raise TaxonomyError(file, field, "expected an object with name, classes and mapping")
        name = d.get("name")
        if not isinstance(name, str) or not name:
            raise TaxonomyError(file, f"{field}.name", f"expected a non-empty string, got {name!r}")
        mapping = check_mapping(d.get("mapping"), file, f"{field}.mapping")
        classes = d.get("classes")
        if classes is not None:
            check_class_order(classes, mapping, file, f"{field}.classes")
        rank = {c: i for i, c in enumerate(classes or [])}
        return cls(name, dict(sorted(mapping.items(), key=lambda kv: rank.get(kv[1], len(rank)))))  # stable


def check_mapping(mapping: Any, file: str | Path, field: str) -> dict[str, str]:
    """A non-empty table of fine class -> non-empty target class name."""
    if not isinstance(mapping, dict) or not mapping:
        raise TaxonomyError(file, field, "must be a table of fine class = target class")
    for fine, target in mapping.items():
        if fine not in FINE_CLASSES:
            raise TaxonomyError(file, f"{field}.{fine}", f"not a fine class ({', '.join(FINE_CLASSES)})")
        if not isinstance(target, str) or not target:
            raise TaxonomyError(file, f"{field}.{fine}", "target must be a non-empty string")
    return mapping


def check_class_order(classes: Any, mapping: dict[str, str], file: str | Path, field: str) -> None:
    """A stored class order names each target class of the mapping once, and nothing else: class
    ids are positions in it, so a name missing, doubled or unknown would shift them silently."""
    targets = set(mapping.values())
    if (not isinstance(classes, list) or not all(isinstance(c, str) for c in classes)
            or len(set(classes)) != len(classes) or set(classes) != targets):
        raise TaxonomyError(file, field, f"must list each target class of the mapping once "
                                         f"({', '.join(sorted(targets))}), got {classes!r}")


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml"))


def recorded_taxonomy(manifest: dict, file: str | Path = "manifest.json") -> Taxonomy:
    """The taxonomy a dataset's manifest records, else fine: read from its whole mapping, so that a
    merge made with a custom TOML exports the same classes without that file at hand; a bare
    name must be a preset's (never a file: see the module's docstring)."""
    recorded = manifest.get("taxonomy")
    if recorded is None:
        return preset_taxonomy("fine")
    if isinstance(recorded, dict) and "mapping" in recorded:
        return Taxonomy.from_dict(recorded, file, "taxonomy")
    if not isinstance(recorded, dict):
        raise TaxonomyError(file, "taxonomy", "expected an object with name, classes and mapping")
    name = recorded.get("name", "fine")
    if name not in preset_names():
        raise TaxonomyError(file, "taxonomy.name", f"{name!r} is not a preset ({', '.join(preset_names())}); a "
                                                   "manifest embeds its taxonomy's mapping or names a preset")
    return preset_taxonomy(name)


def preset_taxonomy(name: str) -> Taxonomy:
    """A preset of omnigen/taxonomies by name (the caller knows it is one)."""
    return _taxonomy_from_toml(PRESETS_DIR / f"{name}.toml")


def load_taxonomy(name_or_path: str | Path = "fine") -> Taxonomy:
    """A preset by name (fine, coarse) or a TOML file the user named; errors name the file and the field."""
    if str(name_or_path) in preset_names():
        return preset_taxonomy(str(name_or_path))
    path = Path(name_or_path)
    if not path.exists():
        raise ValueError(f"taxonomy {str(name_or_path)!r}: not a preset ({', '.join(preset_names())}) nor a file")
    return _taxonomy_from_toml(path)


def _taxonomy_from_toml(path: Path) -> Taxonomy:
    try:
        data = tomllib.loads(read_regular(path, TAXONOMY_MAX_BYTES).decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text (a taxonomy is a TOML file)") from None
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not name:
        raise TaxonomyError(path, "name", f"expected a non-empty string, got {name!r}")
    return Taxonomy(name, dict(check_mapping(data.get("classes"), path, "classes")))
