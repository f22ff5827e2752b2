"""What several robots sharing one map need (docs/algorithms.md#teams): where they start,
one prediction per epoch, and the team's state that `mapex.episode` runs."""
