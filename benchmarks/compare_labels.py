"""Cycles' labels two ways: the raster id pass over the same geometry (`--labels gl`) against Cycles' own
one-sample label passes (`--labels cycles`), frame by frame, for every rig.

Renders the same frames twice with the Cycles backend (preview quality: the labels do not depend
on it) and prints, per frame: the annotated objects of each, the share of instance pixels that
agree, the mean and lowest per-object mask IoU (objects of 16 pixels or more, as annotated), the
median relative depth difference where both hit the same object, the largest occlusion difference
of matching objects, and each run's label-and-annotation time per frame.

    .venv/bin/python benchmarks/compare_labels.py [--frames 2] [--width 320] [--height 240] [--seed 5]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.record import FrameRecord  # noqa: E402
from omnigen.rigs.render import RenderJob, Renderer, read_depth_exr, read_instance_png  # noqa: E402


def render(rig: str, labels: str, root: Path, args: argparse.Namespace) -> tuple[Path, dict]:
    job = RenderJob(rig=rig, frames=args.frames, out=root / f"{rig}-{labels}", seed=args.seed, scene="downtown",
                    width=args.width, height=args.height, backend="cycles", quality="preview", labels=labels,
                    durable=False)
    summary = Renderer(job).run(show_progress=False)
    return job.out, summary.timings


def load(root: Path, name: str):
    rec = FrameRecord.from_dict(json.loads((root / "records" / name).read_text()))
    return rec, read_instance_png(root / rec.synthetic.instance), read_depth_exr(root / rec.synthetic.depth)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for rig in ("ego", "pole", "drone"):
            (gl, tg), (cy, tc) = render(rig, "gl", root, args), render(rig, "cycles", root, args)
            label_s = {name: (t["render"] - t["renderer_core"] + t["annotate"]) / args.frames
                       for name, t in (("gl", tg), ("cycles", tc))}
            print(f"{rig}: labels and annotation per frame: gl {label_s['gl']:.3f} s, cycles {label_s['cycles']:.3f} s")
            for f in sorted((gl / "records").glob("*.json")):
                a, ia, da = load(gl, f.name)
                b, ib, db = load(cy, f.name)
                ids = sorted((set(np.unique(ia).tolist()) | set(np.unique(ib).tolist())) - {0})
                ious = [((ia == i) & (ib == i)).sum() / ((ia == i) | (ib == i)).sum()
                        for i in ids if max((ia == i).sum(), (ib == i).sum()) >= 16]
                hit = np.isfinite(da) & np.isfinite(db) & (ia == ib) & (ia > 0)
                occ_b = {o.instance_id: o.occlusion for o in b.objects}
                docc = max((abs(o.occlusion - occ_b[o.instance_id]) for o in a.objects if o.instance_id in occ_b), default=0.0)
                print(f"  {f.stem}: objects gl {len(a.objects)} cycles {len(b.objects)}; pixels agreeing "
                      f"{(ia == ib).mean():.6f} ({int((ia != ib).sum())} differ); mask IoU mean {np.mean(ious):.4f} "
                      f"min {np.min(ious):.4f}; depth median rel. diff {np.median(np.abs(da[hit] - db[hit]) / db[hit]):.1e}; "
                      f"largest occlusion diff {docc:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
