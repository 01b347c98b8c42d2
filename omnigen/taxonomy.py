"""Taxonomies: which classes a model trains on, as a map from the contract's fine classes.

Records always keep fine classes; a taxonomy is applied when data leaves for a model (exports,
training, evaluation). Presets live in omnigen/taxonomies/*.toml; users pass their own TOML with
the same shape: `name = "..."` and a `[classes]` table `fine = "target"`. Target classes are
numbered in order of first appearance in that table.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnigen.conventions import FINE_CLASSES

PRESETS_DIR = Path(__file__).parent / "taxonomies"


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
    def from_dict(cls, d: dict) -> "Taxonomy":
        """The inverse of to_dict: what checkpoints and manifests store. The class order is the
        stored `classes`, not the mapping's: a manifest is written with sorted keys."""
        rank = {c: i for i, c in enumerate(d.get("classes") or [])}
        mapping = sorted(d["mapping"].items(), key=lambda kv: rank.get(kv[1], len(rank)))  # stable
        return cls(d["name"], dict(mapping))


def recorded_taxonomy(manifest: dict) -> Taxonomy:
    """The taxonomy a dataset's manifest records, else fine: read from its whole mapping, so that a
    merge made with a custom TOML exports the same classes without that file at hand."""
    recorded = manifest.get("taxonomy") or {}
    if "mapping" in recorded:
        return Taxonomy.from_dict(recorded)
    return load_taxonomy(recorded.get("name", "fine"))


def load_taxonomy(name_or_path: str | Path = "fine") -> Taxonomy:
    """A preset by name (fine, coarse) or a TOML file; errors name the file and the field."""
    path = Path(name_or_path)
    if not path.suffix and (PRESETS_DIR / f"{name_or_path}.toml").exists():
        path = PRESETS_DIR / f"{name_or_path}.toml"
    if not path.exists():
        presets = sorted(p.stem for p in PRESETS_DIR.glob("*.toml"))
        raise ValueError(f"taxonomy {name_or_path!r}: not a preset ({', '.join(presets)}) nor a file")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML: {exc}") from None
    classes = data.get("classes")
    if not isinstance(classes, dict) or not classes:
        raise ValueError(f"{path}: field 'classes' must be a table of fine class = target class")
    for fine, target in classes.items():
        if fine not in FINE_CLASSES:
            raise ValueError(f"{path}: field 'classes.{fine}': not a fine class ({', '.join(FINE_CLASSES)})")
        if not isinstance(target, str) or not target:
            raise ValueError(f"{path}: field 'classes.{fine}': target must be a non-empty string")
    return Taxonomy(str(data.get("name", path.stem)), dict(classes))
