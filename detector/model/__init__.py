"""The network: blocks, backbones, neck, head, the crop stage, the boxes and detections they share, and checkpoints that rebuild it."""
