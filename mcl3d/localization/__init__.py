"""Monte Carlo localization in a TSDF map (the embedded-GPU MCL paper): particle state,
initialization, motion sources, the sensor model, the filter step, estimates and the
`localize` pipeline.
"""
