"""Several robots sharing one map and one predictor (docs/algorithms.md#teams): where they
start, what they claim, how they coordinate and the team's episode loop."""
