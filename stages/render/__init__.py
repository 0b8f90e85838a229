"""Gaussians bound to tets and a differentiable CPU rasterizer (PyTorch, float32)."""
