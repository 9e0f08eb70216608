"""Layer 1: image metrics (PSNR, SSIM, LPIPS) and their registry, the one list every report reads."""
