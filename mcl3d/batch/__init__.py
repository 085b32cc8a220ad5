"""`mcl3d batch`: many runs of the pipelines (logs x seeds x particle counts x settings) on Ray.

`manifest` reads and checks the manifest and expands its jobs into runs; `commands` runs one
run through the real pipeline of its command (in a Ray worker process, with its own Taichi
runtime) and `figures` takes the run's key figures from what it wrote; `scheduler` hands the
runs to Ray, resubmits failed ones and reports each finished run; `results` and `plots` write
results.csv, results.json and the pictures; `pipeline.run` is the whole batch.
Ray is an optional dependency (`pip install 'mcl3d[batch]'`), imported only when a batch runs.
"""
