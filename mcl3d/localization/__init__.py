"""Monte Carlo localization in a TSDF map (the embedded-GPU MCL paper).

`localizer.Localizer.step` is one filter update: predict, weigh (`weighing`, the sensor model
of `sensor_model` on the device), estimate (`estimate`), resample (`resampling`), recover
(`recovery`); `search` holds the global search (coarse model, annealing, mode-preserving
resampling), `state` the filter state and per-scan result, `localization_config` the
parameters.
`pipeline.run` localizes a log (`log_inputs`: motion source, gravity, initial pose;
`output_files` and `localization_summary`: what a run writes and reports; `result_view`:
what it shows in Foxglove).
"""
