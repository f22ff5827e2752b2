"""Kept so `python -m mapex.prediction.evaluate` still works; it is mapex.training.evaluate."""

import runpy

if __name__ == "__main__":  # run by name, not imported: mapex.prediction never imports training
    runpy.run_module("mapex.training.evaluate", run_name="__main__", alter_sys=True)
