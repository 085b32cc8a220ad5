"""Taichi kernels and functions only: fields or ndarrays in, no Python objects, no I/O."""

from mcl3d.kernels import taichi_frontend

taichi_frontend.install()  # before any kernel module defines its functions
