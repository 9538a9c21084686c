"""Denoiser backbones: the temporal U-Net and the base class any other backbone implements."""
from torchrl_ftb.diffusion.backbones.base import DenoiserBackbone, sinusoidal_embedding
from torchrl_ftb.diffusion.backbones.unet import TemporalUnet

__all__ = ["DenoiserBackbone", "TemporalUnet", "sinusoidal_embedding"]
