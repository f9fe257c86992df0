"""Compositing volumes with surfaces: opaque surfaces and their z-buffer, order-independent transparency."""
