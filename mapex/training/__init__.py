"""Offline training of the learned predictor (docs/prediction.md): the snapshot dataset,
the training loop, calibration, batches and the predictions' evaluation.

Nothing at run time imports this package: predictors load the weights it writes through
`mapex.prediction`. It may use the explorer and the methods (to explore training worlds);
`mapex.prediction` must not.
"""
