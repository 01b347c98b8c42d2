"""The outside formats omnigen reads and writes, one module each: KITTI (kitti), DAIR-V2X (dair),
COCO keypoints (coco) and Ultralytics YOLO pose (yolo).

Why here, in the core: a format's conventions (its frames, class names, the text of its files)
are needed by more than one part: the KITTI converter and exporter, and the detector, which writes
KITTI labels of lifted boxes. Each imports the format from its one home; no part imports another
part for it. The generic maths they build on (rotations, cuboids, projection) is omnigen.geometry.
"""
