"""Taichi kernels and functions only: fields or ndarrays in, no Python objects, no I/O."""
