"""The SfM machinery the SfM paradigms (`locretrieval.paradigms.sfm`) call, as verbs on what they
work on (hloc's style); it knows no paradigm.

Read top-down: the ``sfm`` config group (`settings`), local `features`, `matching` (mutual
`nearest_neighbours` + ratio test, stored in `store`), `verification`, `triangulation` (maps of
known poses, `sparse_map`; or a `colmap_model`), registration (`pnp`, `registration`, outcomes in
`pose_cache`; one query's registrations, `query_tasks`), in worker processes. `inputs` holds the
caches every verb reads; `work` counts the work; `pipeline` holds the verbs that stream the
queries through matching and the paradigms' maps and registrations. Import the modules you need:
this package imports nothing on its own, so that reading settings does not load pycolmap.
"""
