"""Images in, COCO-results detections out: NMS, the crop stage's refinement, vertical edges, ONNX."""
