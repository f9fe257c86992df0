"""Volumetric path tracing with majorant grids and the spatiotemporal denoiser (paper 002)."""
