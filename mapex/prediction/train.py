"""Kept so `python -m mapex.prediction.train` still works; the module is mapex.training.train."""

import runpy

if __name__ == "__main__":  # run by name, not imported: mapex.prediction never imports training
    runpy.run_module("mapex.training.train", run_name="__main__", alter_sys=True)
