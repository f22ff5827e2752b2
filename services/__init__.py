"""Process glue for the Zenoh-distributed simulator (world, predictor workers, planner).

Only key expressions, codecs and process lifecycles live here; the algorithms are in
`mapex/`. See docs/design.md.
"""
