"""Differentiable Gaussian splatting of depth and semantic maps (paper Eq. 6), pure PyTorch.

    from ..render import render_gaussians, render_cameras, render_scenes, RenderResult
"""
from .splat import RenderResult, render_cameras, render_gaussians, render_scenes

__all__ = ["RenderResult", "render_cameras", "render_gaussians", "render_scenes"]
