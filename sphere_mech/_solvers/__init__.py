"""Integrators on (S^2)^n, each a diffrax solver."""
