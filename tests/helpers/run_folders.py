"""Finished run folders in the format of mapex.results, for the report's tests."""

import json

import numpy as np

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.results import episode_name

SHAPE = (12, 18)


def write_run(
    root,
    world,
    method,
    start=0,
    seed=0,
    cov=0.5,
    iou=0.4,
    tu=0.3,
    steps=200,
    early=False,
    degraded=None,
    snapshots=True,
    prediction=True,
    end_reason=None,
    predictor="lama",
):
    """A finished run folder whose curves are constant at the given AUCs (so curve means and
    metrics.json agree); snapshots at 100 and 200 of a small map."""
    name = episode_name(world, method, start, seed, predictor=predictor)
    folder = root / name
    folder.mkdir(parents=True)
    metrics = {
        "world": world,
        "method": method,
        "predictor": predictor,
        "start_index": start,
        "seed": seed,
        "steps": steps,
        "finished_at": 150 if early else None,
        "early_termination": early,
        "end_reason": end_reason or ("explored" if early else "budget"),
        "auc": {"coverage": cov, "iou": iou, "tu": tu},
        "final": {"coverage": cov, "iou": iou, "tu": tu},
        "replans": 3,
        "wall_time_s": 1.0,
        "config": {},
    }
    if degraded is not None:
        metrics["degraded_steps"] = degraded
    (folder / "metrics.json").write_text(json.dumps(metrics))
    lines = ["step,coverage,iou,tu"]
    for t in range(0, steps + 1, 50):
        lines.append(f"{t},{cov:.6f},{iou:.6f},{f'{tu:.6f}' if t % 100 == 0 else ''}")
    (folder / "curves.csv").write_text("\n".join(lines) + "\n")
    if snapshots:
        observed = np.full((2, *SHAPE), UNKNOWN, dtype=np.uint8)
        observed[:, 2:6, 2:8] = FREE
        observed[:, 1, :] = OCCUPIED
        arrays = {"steps": np.array([100, 200], dtype=np.int64), "observed": observed}
        if prediction:
            arrays["prediction"] = np.full((2, *SHAPE), 40, dtype=np.uint8)
        np.savez_compressed(folder / "snapshots.npz", **arrays)
    return folder
