"""The network: blocks, backbones, neck, head, the crop stage, and checkpoints that rebuild it."""
