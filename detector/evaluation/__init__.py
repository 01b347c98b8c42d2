"""How good predictions are: OKS mAP, corner errors, heading confusion, the box baseline, KITTI AP."""
