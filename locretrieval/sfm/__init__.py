"""The SfM pipeline the SfM paradigms (`locretrieval.paradigms.local_sfm`, `global_sfm`) run on.

Its stages, in the order `pipeline.run_sfm` drives them: local `features`, `matching` (mutual
`nearest_neighbours` + ratio test, stored in `store`), `verification`, `triangulation` (maps of
known poses, `sparse_map`; or a `colmap_model`), and registration (`pnp`, outcomes in
`pose_cache`), in `workers` processes. `inputs` holds the ``sfm`` settings and the caches every
stage reads; `plan` counts and forecasts the work. Import the modules you need: this package
imports nothing on its own, so that reading settings does not load pycolmap.
"""
