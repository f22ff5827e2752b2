"""Pictures of a run: observed map with trajectory, predicted map, ground truth."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mapex.grid import observed_to_probability  # noqa: E402

ROBOT_COLOURS = ("tab:red", "tab:orange", "tab:purple", "tab:cyan", "tab:olive", "tab:pink")


def occupancy_image(probability: np.ndarray) -> np.ndarray:
    """Grey image of an occupancy-probability map: free white, unknown grey, walls black."""
    return 1.0 - np.clip(probability, 0.0, 1.0)


def plot_episode(
    path: Path,
    title: str,
    observed: np.ndarray,
    prediction: np.ndarray | None,
    ground_truth: np.ndarray,
    trajectories: list[np.ndarray],
) -> None:
    """Save a three-panel PNG of the final observed map, predicted map and ground truth,
    with each robot's trajectory (int (n, 2)) in a colour of its own."""
    panels = [("observed map O_T + trajectory", occupancy_image(observed_to_probability(observed)))]
    if prediction is not None:
        panels.append(("predicted map P_T (G)", occupancy_image(prediction)))
    panels.append(("ground truth", occupancy_image(ground_truth.astype(np.float32))))
    rows, cols = observed.shape
    width = 5.0 * len(panels) if cols < rows * 1.5 else 12.0
    layout = (1, len(panels)) if cols < rows * 1.5 else (len(panels), 1)
    height = width * rows / cols * (len(panels) if layout[1] == 1 else 1.0 / len(panels)) + 1.0
    fig, axes = plt.subplots(*layout, figsize=(width, height), squeeze=False)
    for ax, (name, image) in zip(axes.ravel(), panels, strict=True):
        ax.imshow(image, cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
        for robot, trajectory in enumerate(trajectories):
            colour = ROBOT_COLOURS[robot % len(ROBOT_COLOURS)]
            ax.plot(trajectory[:, 1], trajectory[:, 0], color=colour, linewidth=1.0)
            ax.plot(trajectory[0, 1], trajectory[0, 0], "o", color="tab:green", markersize=5)
            ax.plot(trajectory[-1, 1], trajectory[-1, 0], "s", color="tab:blue", markersize=5)
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)
