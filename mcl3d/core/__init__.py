"""Shared foundations: typed errors, config sections and files, SE(3) helpers, the Taichi
runtime and backend probe, atomic output files.
"""
