"""Warp device code shared by every renderer: structs, ray-box, trilinear sampling, phase, lights, integration."""
