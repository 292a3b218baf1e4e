"""What the map is trained with: the mapping loss and SSIM, keyframes and their windows, the moving average, anchor
refinement, pose corrections and their Gauss-Newton steps, the hash table's lazy Adam."""
