"""Monte Carlo SLAM (the gradient-guided particle filter paper): particles that carry their
own keyframe poses, GICP corrections, pruning, and the `slam` pipeline.
"""
