"""diffusion/backbones stage."""
