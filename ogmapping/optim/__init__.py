"""How the map is trained: the mapping loss and SSIM, keyframe windows, the moving average and anchor refinement."""
