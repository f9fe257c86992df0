"""Ambient global illumination in SH on the light grid (paper 000 §3.2)."""
