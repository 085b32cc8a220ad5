"""Trajectory evaluation: ATE and RPE equal to evo's, and plots of the results.
"""
