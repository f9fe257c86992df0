"""Froxel fog with a shadow grid shared by many viewers (paper 003)."""
