"""Detection node: per-frame instance masks from /camera/instances or torchvision Mask R-CNN (paper Sec. 5.1)."""
