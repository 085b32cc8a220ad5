"""Monte Carlo SLAM (the gradient-guided particle filter paper): its config sections, the
filter (monte_carlo_slam) over particles that carry their own keyframe poses (slam_particles), the
elevator's vertical motion, and the `slam` pipeline with its summary and what it shows in
Foxglove (result_view).
"""
