"""The `build-map` pipeline: TSDF maps from logs with poses, point-cloud maps, meshes and
tsdf_localization maps (the map structure itself lives in `mcl3d.maps`).
"""
