"""PyTorch side of quietframe (training only): bilateral grid, NBG denoiser, temporal stage."""
