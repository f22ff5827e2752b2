"""MapEx: frontier exploration with probabilistic information gain from map predictions.

`mapex` holds the pure algorithms (worlds, sensor, frontiers, navigation, visibility,
methods, prediction, metrics, the episode loop). It knows nothing of Zenoh; the
process glue lives in `services/`.
"""

__version__ = "0.1.0"
