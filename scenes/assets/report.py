"""Print each procedural family's and furniture kind's mesh size and build time.

    python -m omnigen.scenes.assets.report [--draws N]

Why: the raster preview builds every agent in view every frame, so a family's triangle count and
build time are what it costs a frame; docs/scenes.md quotes this script's table. Triangle counts
are deterministic (seeded draws); times depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import time
import zlib

import numpy as np

from omnigen.scenes.assets import props
from omnigen.scenes.assets.build import AGENT_BUILDERS
from omnigen.scenes.assets.catalog import PROCEDURAL_FAMILIES, draw_asset
from omnigen.scenes.assets.parts import fit_to_dims

# Furniture at typical dims (the contract's ranges, docs/scenes.md).
FURNITURE_EXAMPLES = (
    ("tree", (3.2, 3.0, 6.0), {"species": "round"}),
    ("tree", (2.5, 2.5, 9.0), {"species": "conical"}),
    ("tree", (1.6, 1.6, 10.0), {"species": "columnar"}),
    ("tree", (7.0, 7.0, 9.0), {"species": "spreading"}),
    ("hedge", (10.0, 0.8, 1.2), {}),
    ("hedge", (10.0, 0.8, 1.2), {"clipped": False}),
    ("bush", (1.2, 1.0, 0.9), {}),
    ("planter", (1.5, 0.8, 1.3), {}),
    ("signpost", (0.12, 0.7, 2.6), {}),
    ("bus_shelter", (4.5, 1.6, 2.6), {}),
    ("fence", (10.0, 0.08, 1.1), {"style": "rail"}),
    ("fence", (10.0, 0.08, 1.1), {"style": "picket"}),
    ("guardrail", (20.0, 0.3, 0.75), {}),
)


def family_rows(draws: int) -> list[tuple[str, int, int, float]]:
    """(family, min triangles, max triangles, mean build+fit ms) over `draws` seeded draws."""
    rows = []
    for family in PROCEDURAL_FAMILIES:
        rng = np.random.default_rng(zlib.crc32(family.encode()))
        items = [draw_asset(rng, family) for _ in range(draws)]
        builder = AGENT_BUILDERS[family]
        tris = []
        t0 = time.perf_counter()
        for dims, spec in items:
            parts, _ = fit_to_dims(builder(dims, dict(spec.params)).meshes(), dims)
            tris.append(sum(len(m.faces) for m in parts.values()))
        ms = (time.perf_counter() - t0) / draws * 1000.0
        rows.append((family, min(tris), max(tris), ms))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100, help="draws per family")
    args = ap.parse_args(argv)
    print(f"{'family':14s} {'triangles':>11s} {'build+fit ms':>13s}")
    for family, lo, hi, ms in family_rows(args.draws):
        print(f"{family:14s} {lo:5d}-{hi:<5d} {ms:13.2f}")
    print(f"\n{'furniture':50s} {'triangles':>9s}")
    for kind, dims, params in FURNITURE_EXAMPLES:
        parts = props.FURNITURE_BUILDERS[kind](dims, params).meshes()
        label = f"{kind} {dims} {params or ''}"
        print(f"{label:50s} {sum(len(m.faces) for m in parts.values()):9d}")


if __name__ == "__main__":
    main()
